"""VPoser checkpoints, read strictly: :func:`load` (``load(path, size) -> (VPoser, CheckpointReport)``)
reads the official V02_05 Lightning checkpoint and the project's ``priors/weights/vposer.pt``;
:func:`load_vposer_v1_state` the official v1.0 state dict ``TR00_E096.pt`` (part of the
frequency-guided prior's release). Both go through :func:`priors.checkpoints.load_state_strict`.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

from benchmark.core.safe_loading import is_lightning_bookkeeping, torch_load_weights, torch_load_with_stand_ins
from priors.checkpoints import CheckpointReport, check_size, load_state_strict
from priors.vposer.model import PAPER_CONFIG, VPoser, VPoserV1

log = logging.getLogger(__name__)


DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "vposer.pt"
OFFICIAL_PREFIX = "vp_model."
WHERE_TO_GET = (
    "VPoser V02_05 is distributed (registration required) as V02_05.zip on the SMPL-X download page "
    "https://smpl-x.is.tue.mpg.de/download.php; unzip it and pass the folder (or its "
    "snapshots/*.ckpt file), e.g. `--weights /path/V02_05` (`--weights vposer-slerp=/path/V02_05` for run, fit-check and encoder-check, which "
    "take several priors)"
)


# -- strict checkpoint loading ---------------------------------------------------------------
def _optional(key: str) -> bool:
    """Entries loaded when present but not required: BatchNorm's ``num_batches_tracked`` counters
    (unused in eval mode; absent from checkpoints written by older torch versions)."""
    return key.endswith("num_batches_tracked")


def resolve_checkpoint(path: str | Path) -> tuple[Path, str]:
    """A checkpoint file from a file path or a ``V02_05`` folder; returns (file, why this file).

    A folder is searched for ``snapshots/*.ckpt`` (or ``*.ckpt`` directly inside it) and the file
    with the highest ``epoch=NN`` in its name is taken (the official loader takes the newest by
    modification time, which depends on how the zip was extracted).
    """
    p = Path(path).expanduser()
    if p.is_file():
        return p, "file given"
    if not p.exists():
        raise FileNotFoundError(f"VPoser weights not found: {p} does not exist. {WHERE_TO_GET}")
    candidates = sorted((p / "snapshots").glob("*.ckpt")) or sorted(p.glob("*.ckpt"))
    if not candidates:
        raise FileNotFoundError(
            f"no VPoser checkpoint in folder {p}: expected {p}/snapshots/*.ckpt (layout V02_05/V02_05.yaml, "
            f"V02_05/snapshots/V02_05_epoch=13_val_loss=0.03.ckpt). {WHERE_TO_GET}"
        )
    epochs = {}
    for c in candidates:
        m = re.search(r"epoch=(\d+)", c.name)
        if m is None:
            raise ValueError(
                f"cannot choose a VPoser checkpoint in {c.parent}: {c.name} has no 'epoch=NN' in its name "
                f"(found {[x.name for x in candidates]}); pass the .ckpt file itself"
            )
        epochs[c] = int(m.group(1))
    best = max(candidates, key=lambda c: (epochs[c], c.name))
    why = f"highest epoch ({epochs[best]}) among {[c.name for c in candidates]} in {best.parent}"
    return best, why


OFFICIAL_FIX = (
    "if you trust the file, load it in Python yourself and re-save only its tensors, "
    "torch.save({'state_dict': ckpt['state_dict']}, 'V02_05_epoch=13_weights.ckpt'), then pass that file"
)


def _torch_load(file: Path) -> object:
    """torch.load on CPU with ``weights_only=True``. The bookkeeping a Lightning checkpoint pickles
    besides its tensors (callback classes, OmegaConf hyper-parameters) is read as inert stand-ins
    (:func:`benchmark.core.safe_loading.is_lightning_bookkeeping`) and ignored; any other global is refused
    (:class:`benchmark.core.safe_loading.UnsafeFileError`)."""
    ckpt, stand_ins = torch_load_with_stand_ins(file, is_lightning_bookkeeping, OFFICIAL_FIX)
    if stand_ins:
        log.warning(
            "%s: holds Lightning bookkeeping that plain weights_only=True loading refuses (%s); read as inert "
            "stand-ins (never called) and ignored: only its state_dict tensors are used", file, ", ".join(stand_ins)
        )
    return ckpt


def _load_state(ckpt: object, file: Path, model: VPoser) -> tuple[list[str], list[str], str]:
    """Copy a checkpoint's tensors into ``model``, strictly (:func:`priors.checkpoints.load_state_strict`).

    Accepts the official Lightning checkpoint (``ckpt["state_dict"]``, keys ``vp_model.*``) and the
    project's file (``{"state_dict": {...unprefixed...}, "config": {...}}``). Returns (loaded keys,
    sorted ignored keys, format). Every required key must be present with the model's shape;
    anything else is ignored and listed.
    """
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt or not isinstance(ckpt["state_dict"], dict):
        top = sorted(ckpt)[:20] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(
            f"{file}: not a VPoser checkpoint: expected a dict with a 'state_dict' entry (Lightning .ckpt or "
            f"priors/weights/vposer.pt), found {top}"
        )
    raw = ckpt["state_dict"]
    official = any(k.startswith(OFFICIAL_PREFIX) for k in raw)
    fmt = "official-lightning" if official else "project"
    _check_any_key(raw, model, OFFICIAL_PREFIX if official else "", file)
    loaded, ignored = load_state_strict(
        model, raw, file, "VPoser V02_05", prefix=OFFICIAL_PREFIX if official else "", optional=_optional,
        ignore_unexpected=True,
        note=f"VPoser(hidden={model.hidden}, latent={model.latent}); is this the right size (paper: hidden 512, latent 32)?",
    )
    ignored += sorted(f"<top level>/{k}" for k in ckpt if k != "state_dict" and not (fmt == "project" and k == "config"))
    return loaded, ignored, fmt


def _check_any_key(raw: dict, model: VPoser, prefix: str, file: Path) -> None:
    """Refuse a file that holds none of VPoser's keys (another prior's checkpoint, another key prefix),
    naming what it holds and, where its keys end in VPoser's, the prefix to strip."""
    wanted = list(model.state_dict())
    if any(prefix + k in raw for k in wanted):
        return
    ends = next((k[: -len(w)] for k in raw for w in wanted if k.endswith("." + w)), None)
    hint = (f"; its keys end in VPoser's after the prefix {ends!r}: re-save them with the official prefix "
            f"{OFFICIAL_PREFIX!r} (or none)" if ends else "; is it another prior's checkpoint?")
    raise ValueError(f"{file}: holds none of VPoser's weights (e.g. {prefix}{wanted[0]}); its keys: "
                     f"{sorted(raw)[:6]}{' ...' if len(raw) > 6 else ''}{hint}")


def _project_config(ckpt: object, file: Path) -> dict:
    """The ``config`` entry ({"hidden", "latent"}) of a project checkpoint (priors/weights/vposer.pt)."""
    cfg = ckpt.get("config") if isinstance(ckpt, dict) else None
    fix = "give priors/weights/vposer.pt or a file written by `python -m benchmark train vposer-slerp`"
    if not isinstance(cfg, dict) or not {"hidden", "latent"} <= set(cfg):
        held = f"its 'config' holds {sorted(cfg)[:8]}" if isinstance(cfg, dict) else "it has no 'config'"
        raise ValueError(f"{file}: not a VPoser checkpoint of this project ({held}; a VPoser file's names hidden and "
                         f"latent): another prior's weights? {fix}")
    try:
        out = {"hidden": int(cfg["hidden"]), "latent": int(cfg["latent"])}
    except (TypeError, ValueError):
        out = None
    if out is None or min(out.values()) < 1:
        raise ValueError(f"{file}: field 'config' must give 'hidden' and 'latent' as positive integers, got "
                         f"hidden={cfg['hidden']!r}, latent={cfg['latent']!r}; {fix}")
    return out


def load(path: str | Path, size: str = "embedded") -> tuple[VPoser, CheckpointReport]:
    """The VPoser network of a checkpoint, strictly loaded, and what was read.

    size "paper": the official V02_05 release (a ``V02_05`` folder, whose snapshot with the highest
    epoch is taken, or a ``.ckpt`` file; a project-format file of the paper size loads too) into the
    paper-size network. size "embedded": the project's file (``priors/weights/vposer.pt``, written
    by :mod:`priors.vposer.train`), at the size its ``config`` says.
    """
    check_size("vposer-slerp", size)
    if size == "embedded":
        p = Path(path).expanduser()
        if p.is_dir() and not (any((p / "snapshots").glob("*.ckpt")) or any(p.glob("*.ckpt"))):
            raise FileNotFoundError(f"{path}: a folder with no VPoser checkpoint in it; give the project's file "
                                    "(priors/weights/vposer.pt) or, with --size paper, the official V02_05 folder")
        if p.is_dir() or p.suffix == ".ckpt":
            raise ValueError(
                f"{path} looks like the official VPoser release (a V02_05 folder or a .ckpt): load it with "
                "--size paper (size='paper'); the embedded size reads priors/weights/vposer.pt"
            )
        file, why = resolve_checkpoint(path)
        ckpt = torch_load_weights(file, "retrain with `python -m benchmark train vposer-slerp`")
        model = VPoser(**_project_config(ckpt, file))
    else:
        file, why = resolve_checkpoint(path)
        ckpt = _torch_load(file)
        model = VPoser(**PAPER_CONFIG)
    loaded, ignored, fmt = _load_state(ckpt, file, model)
    log.info("VPoser weights: %s (%s, %s); %d tensors loaded, ignored: %s", file, fmt, why, len(loaded), ignored or "nothing")
    return model, CheckpointReport(file=file, format=fmt, chosen_because=why, loaded=loaded, ignored=ignored, config=model.config)


V1_WHERE_TO_GET = (
    "VPoser v1.0 is distributed (registration required) as vposer_v1_0.zip on the SMPL-X download page "
    "https://smpl-x.is.tue.mpg.de/download.php; the weights are vposer_v1_0/snapshots/TR00_E096.pt"
)


def _v1_hint(missing: list[str], unexpected: list[str]) -> str:
    if any(k.startswith("encoder_net.") or k.startswith("vp_model.") for k in unexpected):
        return " (this looks like VPoser V02_05: Xu et al. need VPoser v1.0, TR00_E096.pt)"
    if any(k.startswith("module.") for k in unexpected):
        return " (keys start with 'module.': is this the motion prior pretrained_priorD.pth?)"
    return ""


def load_vposer_v1_state(state: object, model: VPoserV1, file: str | Path = "<state dict>", prefix: str = "") -> CheckpointReport:
    """Copy a VPoser v1.0 state dict into ``model``, strictly (:func:`priors.checkpoints.load_state_strict`).

    ``state``: the official ``TR00_E096.pt`` content (plain dict of tensors) or ``{"state_dict": {...}}``.
    ``prefix``: a key prefix to strip (e.g. ``"vposer."`` inside the project's checkpoint). Errors
    name ``file``, every missing / unexpected key and every shape mismatch.
    """
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict) or not all(isinstance(k, str) for k in state):
        raise ValueError(
            f"{file}: not a VPoser v1.0 checkpoint: expected a state dict (TR00_E096.pt) with "
            f"'bodyprior_*' keys, found {type(state).__name__}"
        )
    state = {k: v for k, v in state.items() if k.startswith(prefix)}
    loaded, _ = load_state_strict(
        model, state, file, "VPoser v1.0", prefix=prefix, optional=_optional, hint=_v1_hint,
        note=f"VPoserV1(hidden={model.hidden}, latent={model.latent}) (paper: hidden 512, latent 32). {V1_WHERE_TO_GET}",
    )
    return CheckpointReport(file=Path(str(file)), format="official-v1", loaded=loaded,
                            config={"hidden": model.hidden, "latent": model.latent})


def is_vposer_v1_state(state: object) -> bool:
    """Whether a loaded checkpoint looks like VPoser v1.0 (its encoder's first layer is present)."""
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    return isinstance(state, dict) and "bodyprior_enc_bn1.weight" in state
