"""VPoser checkpoints, read strictly: the official V02_05 Lightning checkpoint and the project's
``priors/weights/vposer.pt`` (:func:`load_vposer_checkpoint`), and the official v1.0 state dict
``TR00_E096.pt`` (:func:`load_vposer_v1_state`).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import torch

from benchmark.safe_loading import (
    STATE_DICT_FIX,
    is_lightning_bookkeeping,
    torch_load_weights,
    torch_load_with_stand_ins,
)
from priors.vposer.model import VPoser, VPoserV1

log = logging.getLogger(__name__)


DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "vposer.pt"
OFFICIAL_PREFIX = "vp_model."
WHERE_TO_GET = (
    "VPoser V02_05 is distributed (registration required) as V02_05.zip on the SMPL-X download page "
    "https://smpl-x.is.tue.mpg.de/download.php; unzip it and pass the folder (or its "
    "snapshots/*.ckpt file), e.g. `--weights vposer-slerp=/path/V02_05`"
)


# -- strict checkpoint loading ---------------------------------------------------------------
def expected_keys(model: VPoser) -> dict[str, tuple[int, ...]]:
    """The state-dict entries a VPoser checkpoint must hold, with their shapes (26 entries)."""
    return {k: tuple(v.shape) for k, v in model.state_dict().items()}


def optional_keys(model: VPoser) -> set[str]:
    """Entries loaded when present but not required: BatchNorm's ``num_batches_tracked`` counters
    (unused in eval mode; absent from checkpoints written by older torch versions)."""
    return {k for k in model.state_dict() if k.endswith("num_batches_tracked")}


@dataclass
class CheckpointReport:
    """What :func:`load_vposer_checkpoint` did."""

    file: Path
    format: str  # "official-lightning" or "project"
    chosen_because: str
    loaded: list[str] = field(default_factory=list)
    ignored: list[str] = field(default_factory=list)
    config: dict = field(default_factory=dict)


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
    (:func:`benchmark.safe_loading.is_lightning_bookkeeping`) and ignored; any other global is refused
    (:class:`benchmark.safe_loading.UnsafeFileError`)."""
    ckpt, stand_ins = torch_load_with_stand_ins(file, is_lightning_bookkeeping, OFFICIAL_FIX)
    if stand_ins:
        log.warning(
            "%s: holds Lightning bookkeeping that plain weights_only=True loading refuses (%s); read as inert "
            "stand-ins (never called) and ignored: only its state_dict tensors are used", file, ", ".join(stand_ins)
        )
    return ckpt


def read_state_dict(file: Path, model: VPoser) -> tuple[dict[str, torch.Tensor], list[str], str]:
    """Map a checkpoint's tensors onto ``model``'s keys, strictly.

    Accepts the official Lightning checkpoint (``ckpt["state_dict"]``, keys ``vp_model.*``) and the
    project's file (``{"state_dict": {...unprefixed...}, "config": {...}}``). Returns
    (mapped state dict, sorted ignored keys, format). Every required key must be present with the
    model's shape; anything else is ignored and listed.
    """
    ckpt = _torch_load(file)
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt or not isinstance(ckpt["state_dict"], dict):
        top = sorted(ckpt)[:20] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(
            f"{file}: not a VPoser checkpoint: expected a dict with a 'state_dict' entry (Lightning .ckpt or "
            f"priors/weights/vposer.pt), found {top}"
        )
    raw = ckpt["state_dict"]
    official = any(k.startswith(OFFICIAL_PREFIX) for k in raw)
    prefix = OFFICIAL_PREFIX if official else ""
    fmt = "official-lightning" if official else "project"
    expected = expected_keys(model)
    optional = optional_keys(model)
    mapped, used = {}, set()
    for key, shape in expected.items():
        src = prefix + key
        if src not in raw:
            if key in optional:
                continue
            raise KeyError(
                f"{file}: missing key {src!r} (expected shape {shape}); the VPoser V02_05 checkpoint must hold all of "
                f"{sorted(prefix + k for k in expected if k not in optional)}"
            )
        t = raw[src]
        if not torch.is_tensor(t) or tuple(t.shape) != shape:
            found = tuple(t.shape) if torch.is_tensor(t) else type(t).__name__
            raise ValueError(
                f"{file}: key {src!r} has shape {found}, expected {shape} for VPoser(hidden={model.hidden}, "
                f"latent={model.latent}); is this the right size (paper: hidden 512, latent 32)?"
            )
        mapped[key] = t
        used.add(src)
    ignored = sorted(k for k in raw if k not in used)
    ignored += sorted(f"<top level>/{k}" for k in ckpt if k != "state_dict" and not (fmt == "project" and k == "config"))
    return mapped, ignored, fmt


def load_vposer_checkpoint(path: str | Path, model: VPoser) -> CheckpointReport:
    """Load a VPoser checkpoint (file, or ``V02_05`` folder) into ``model`` strictly; see
    :func:`read_state_dict`. Logs and returns which file was chosen and what was ignored."""
    file, why = resolve_checkpoint(path)
    mapped, ignored, fmt = read_state_dict(file, model)
    model.load_state_dict(mapped, strict=False)  # every required key is checked above
    log.info("VPoser weights: %s (%s, %s); %d tensors loaded, ignored: %s", file, fmt, why, len(mapped), ignored or "nothing")
    return CheckpointReport(file=file, format=fmt, chosen_because=why, loaded=sorted(mapped), ignored=ignored, config=model.config)


def read_project_config(file: str | Path) -> dict:
    """The ``config`` entry ({"hidden", "latent"}) of a project checkpoint (priors/weights/vposer.pt)."""
    if Path(file).is_dir() or Path(file).suffix == ".ckpt":
        raise ValueError(
            f"{file} looks like the official VPoser release (a V02_05 folder or a .ckpt): load it with "
            "size='paper'; size 'embedded' reads priors/weights/vposer.pt"
        )
    ckpt = torch_load_weights(file, "retrain with `python -m benchmark train vposer-slerp`")
    cfg = ckpt.get("config") if isinstance(ckpt, dict) else None
    if not isinstance(cfg, dict) or not {"hidden", "latent"} <= set(cfg):
        raise ValueError(f"{file}: field 'config' with 'hidden' and 'latent' is missing; retrain with priors.vposer.train.train_vposer")
    return {"hidden": int(cfg["hidden"]), "latent": int(cfg["latent"])}


V1_WHERE_TO_GET = (
    "VPoser v1.0 is distributed (registration required) as vposer_v1_0.zip on the SMPL-X download page "
    "https://smpl-x.is.tue.mpg.de/download.php; the weights are vposer_v1_0/snapshots/TR00_E096.pt"
)


# -- strict loading --------------------------------------------------------------------------
def _is_optional(key: str) -> bool:
    return key.endswith("num_batches_tracked")


def torch_load_cpu(file: str | Path) -> object:
    """``torch.load`` on CPU with ``weights_only=True`` (plain state dicts, also the legacy pre-1.6
    serialisation); a file that pickles anything else is refused with
    :class:`benchmark.safe_loading.UnsafeFileError`."""
    return torch_load_weights(file, STATE_DICT_FIX)


def load_vposer_v1_state(state: object, model: VPoserV1, file: str | Path = "<state dict>", prefix: str = "") -> list[str]:
    """Copy a VPoser v1.0 state dict into ``model``, strictly; returns the loaded keys.

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
    raw = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    missing = [k for k in expected if k not in raw and not _is_optional(k)]
    unexpected = sorted(k for k in raw if k not in expected)
    if missing or unexpected:
        hint = ""
        if any(k.startswith("encoder_net.") or k.startswith("vp_model.") for k in unexpected):
            hint = " (this looks like VPoser V02_05: Xu et al. need VPoser v1.0, TR00_E096.pt)"
        elif any(k.startswith("module.") for k in unexpected):
            hint = " (keys start with 'module.': is this the motion prior pretrained_priorD.pth?)"
        raise KeyError(
            f"{file}: VPoser v1.0 state dict does not match VPoserV1(hidden={model.hidden}, latent={model.latent}): "
            f"missing keys {[prefix + k for k in missing]}, unexpected keys {[prefix + k for k in unexpected]}{hint}. "
            f"{V1_WHERE_TO_GET}"
        )
    bad = [
        f"{prefix + k}: file {tuple(raw[k].shape) if torch.is_tensor(raw[k]) else type(raw[k]).__name__}, expected {shape}"
        for k, shape in expected.items()
        if k in raw and (not torch.is_tensor(raw[k]) or tuple(raw[k].shape) != shape)
    ]
    if bad:
        raise ValueError(
            f"{file}: VPoser v1.0 shape mismatch for VPoserV1(hidden={model.hidden}, latent={model.latent}) "
            f"(paper: hidden 512, latent 32): {bad}"
        )
    mapped = {k: raw[k] for k in expected if k in raw}
    model.load_state_dict(mapped, strict=False)  # all required keys checked above
    return sorted(mapped)


def is_vposer_v1_state(state: object) -> bool:
    """Whether a loaded checkpoint looks like VPoser v1.0 (its encoder's first layer is present)."""
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    return isinstance(state, dict) and "bodyprior_enc_bn1.weight" in state
