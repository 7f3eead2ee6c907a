"""Frequency-guided checkpoints, read strictly by :func:`load` (``load(path, size) -> (network,
CheckpointReport)``): the official ``pretrained_priorD.pth`` + VPoser v1.0 ``TR00_E096.pt`` pair
(paper size) and the project's ``priors/weights/frequency_guided.pt`` (embedded size), both through
:func:`priors.checkpoints.load_state_strict`.
"""

from __future__ import annotations

import logging
from pathlib import Path

from benchmark.core.safe_loading import STATE_DICT_FIX, is_lightning_bookkeeping, torch_load_weights, torch_load_with_stand_ins
from priors.checkpoints import CheckpointReport, check_size, load_state_strict
from priors.vposer.checkpoint import V1_WHERE_TO_GET as VPOSER_V1_WHERE, is_vposer_v1_state, load_vposer_v1_state
from priors.frequency_guided.model import FrequencyGuidedNetwork, MotionPrior, PAPER_CONFIG

log = logging.getLogger(__name__)


DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "frequency_guided.pt"
OFFICIAL_PRIOR_NAME = "pretrained_priorD.pth"
OFFICIAL_VPOSER_NAME = "TR00_E096.pt"
DDP_PREFIX = "module."
WHERE_TO_GET = (
    "the motion prior pretrained_priorD.pth (+ motion_prior_config.ini) is public on Google Drive, file id "
    "12LAlvHJ34qNkOqCVawSDjBquQH6MI2Ma (linked from JchenXu/human-motion-prior, action_recognition/README.md); "
    f"{VPOSER_V1_WHERE}. Pass both, e.g. `--weights /path/folder` (a folder holding "
    f"{OFFICIAL_PRIOR_NAME} and {OFFICIAL_VPOSER_NAME}) or `--weights /p/{OFFICIAL_PRIOR_NAME},/p/{OFFICIAL_VPOSER_NAME}` "
    "(prefixed `frequency-guided=` for run, fit-check and encoder-check, which take several priors)"
)
TRAIN_COMMAND = "python -m benchmark train frequency-guided  (or: python -m priors.frequency_guided.train --out priors/weights)"


# -- checkpoint loading ------------------------------------------------------------------------
def _motion_prior_hint(missing: list[str], unexpected: list[str]) -> str:
    if any("bodyprior_enc_bn1" in k for k in unexpected):
        return f" (this looks like VPoser v1.0 {OFFICIAL_VPOSER_NAME}, not the motion prior)"
    if any(k.endswith(".weight") and k.removeprefix(DDP_PREFIX)[:-7] + ".weight_v" in missing for k in unexpected):
        return " (plain 'weight' where weight_g/weight_v are expected: the file was saved without weight norm)"
    return ""


def load_motion_prior_state(state: object, model: MotionPrior, file="<state dict>") -> CheckpointReport:
    """Copy the official ``pretrained_priorD.pth`` content into ``model`` strictly
    (:func:`priors.checkpoints.load_state_strict`; every key carries the DDP prefix ``module.``).

    Every MotionPrior key (unused layers included; BatchNorm ``num_batches_tracked`` optional) must be
    present with its shape, and nothing else.
    """
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    if not isinstance(state, dict) or not state or not all(isinstance(k, str) for k in state):
        raise ValueError(f"{file}: not a state dict of Xu et al.'s MotionPrior (expected {OFFICIAL_PRIOR_NAME}); found {type(state).__name__}")
    pref = [k.startswith(DDP_PREFIX) for k in state]
    if any(pref) and not all(pref):
        raise KeyError(f"{file}: some keys start with {DDP_PREFIX!r} and some do not, e.g. "
                       f"{[k for k in state if not k.startswith(DDP_PREFIX)][:5]}: not a plain DDP state dict")
    loaded, _ = load_state_strict(
        model, state, file, "MotionPrior", prefix=DDP_PREFIX if all(pref) else "",
        optional=lambda k: k.endswith("num_batches_tracked"), hint=_motion_prior_hint,
        note=f"the paper network (config {PAPER_CONFIG}); expected the 'module.'-prefixed {OFFICIAL_PRIOR_NAME}; {WHERE_TO_GET}",
    )
    return CheckpointReport(file=Path(str(file)), format="official-motion-prior", loaded=loaded)


def _looks_like_motion_prior(state) -> bool:
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    return isinstance(state, dict) and any(k in state for k in ("module.dct_att.weight", "dct_att.weight"))


def resolve_paper_weights(weights) -> tuple[Path, Path]:
    """(motion prior file, VPoser v1 file) from a folder, ``"a,b"`` or a pair (see module docstring)."""
    if isinstance(weights, (tuple, list)):
        parts = [Path(str(w)).expanduser() for w in weights]
    else:
        s = str(weights)
        parts = [Path(p.strip()).expanduser() for p in s.split(",")] if "," in s else [Path(s).expanduser()]
    if len(parts) == 1:
        folder = parts[0]
        if not folder.exists():
            raise FileNotFoundError(f"frequency-guided weights: {folder} does not exist. {WHERE_TO_GET}")
        if not folder.is_dir():
            raise ValueError(
                f"frequency-guided size 'paper' needs two files (the motion prior and VPoser v1.0), got one file {folder}: "
                f"pass a folder or 'prior.pth,vposer.pt'. {WHERE_TO_GET}"
            )

        def find(name: str, pattern: str) -> Path:
            exact = sorted(folder.rglob(name))
            if len(exact) == 1:
                return exact[0]
            if len(exact) > 1:
                raise ValueError(f"several {name} under {folder}: {[str(p) for p in exact]}; pass the two files explicitly")
            loose = sorted(folder.rglob(pattern))
            if len(loose) == 1:
                return loose[0]
            raise FileNotFoundError(
                f"no {name} under {folder} (searched recursively; {len(loose)} '{pattern}' files: "
                f"{[str(p) for p in loose][:10]}). Expected layout: {folder}/{OFFICIAL_PRIOR_NAME} and "
                f"{folder}/vposer_v1_0/snapshots/{OFFICIAL_VPOSER_NAME}. {WHERE_TO_GET}"
            )

        return find(OFFICIAL_PRIOR_NAME, "*.pth"), find(OFFICIAL_VPOSER_NAME, "*.pt")
    if len(parts) != 2:
        raise ValueError(f"frequency-guided weights: expected a folder or two files 'prior.pth,vposer.pt', got {len(parts)} paths {parts}")
    for p in parts:
        if not p.is_file():
            raise FileNotFoundError(f"frequency-guided weights: {p} is not a file. {WHERE_TO_GET}")
    return parts[0], parts[1]


def _load_paper(weights) -> tuple[FrequencyGuidedNetwork, CheckpointReport]:
    """The official pair, read strictly into a paper-size network (the files are read first)."""
    a, b = resolve_paper_weights(weights)
    # a Lightning checkpoint's bookkeeping (VPoser V02_05's, given in place of v1.0) is read inert, so
    # that the key checks below can say what the file is instead of calling it unsafe
    sa, sb = (torch_load_with_stand_ins(f, is_lightning_bookkeeping, STATE_DICT_FIX)[0] for f in (a, b))
    if _looks_like_motion_prior(sb) and not _looks_like_motion_prior(sa):
        a, b, sa, sb = b, a, sb, sa
    if not _looks_like_motion_prior(sa):
        raise KeyError(
            f"frequency-guided: neither {a} nor {b} holds the motion prior (no 'module.dct_att.weight' key); "
            f"first keys: {a.name}: {list(sa)[:5] if isinstance(sa, dict) else type(sa).__name__}, "
            f"{b.name}: {list(sb)[:5] if isinstance(sb, dict) else type(sb).__name__}. {WHERE_TO_GET}"
        )
    if not is_vposer_v1_state(sb):
        inner = sb.get("state_dict") if isinstance(sb, dict) and isinstance(sb.get("state_dict"), dict) else sb
        keys = list(inner)[:8] if isinstance(inner, dict) else type(sb).__name__
        v2 = isinstance(inner, dict) and any(str(k).startswith(("vp_model.", "encoder_net.")) for k in inner)
        raise KeyError(f"{b}: not VPoser v1.0 (no 'bodyprior_enc_bn1.weight' key; first keys {keys})"
                       + ("; this is VPoser V02_05: Xu et al.'s prior needs VPoser v1.0, TR00_E096.pt" if v2 else "")
                       + f". {VPOSER_V1_WHERE}")
    network = FrequencyGuidedNetwork(PAPER_CONFIG)
    mp = load_motion_prior_state(sa, network.motion_prior, a)
    vp = load_vposer_v1_state(sb, network.vposer, b)
    log.info("frequency-guided paper weights: motion prior %s (%d tensors), VPoser v1 %s (%d tensors)", a, len(mp.loaded), b, len(vp.loaded))
    return network, CheckpointReport(file=a, files=[a, b], format="official-pair", config=dict(PAPER_CONFIG),
                                     loaded=[f"motion_prior.{k}" for k in mp.loaded] + [f"vposer.{k}" for k in vp.loaded],
                                     parts={"motion_prior": mp, "vposer": vp})


def _load_project(path: str | Path) -> tuple[FrequencyGuidedNetwork, CheckpointReport]:
    """The embedded network from ``priors/weights/frequency_guided.pt`` (strict)."""
    path = Path(path)
    if path.is_dir() or "," in str(path):
        raise ValueError(f"{path} looks like the official release: load it with size='paper'; size 'embedded' reads {DEFAULT_WEIGHTS.name}")
    ckpt = torch_load_weights(path, f"retrain: {TRAIN_COMMAND}")
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), dict) or not isinstance(ckpt.get("config"), dict):
        raise ValueError(f"{path}: expected {{'state_dict', 'config'}} written by priors.frequency_guided.train.train_frequency_guided; retrain: {TRAIN_COMMAND}")
    cfg = ckpt["config"]
    need = set(PAPER_CONFIG)
    if not need <= set(cfg):
        raise ValueError(f"{path}: field 'config' lacks {sorted(need - set(cfg))}; retrain: {TRAIN_COMMAND}")
    net = FrequencyGuidedNetwork({k: cfg[k] for k in PAPER_CONFIG})
    loaded, _ = load_state_strict(net, ckpt["state_dict"], path, "frequency-guided",
                                  optional=lambda k: k.endswith("num_batches_tracked"), note=f"its config {cfg}")
    return net, CheckpointReport(file=path, format="project", config=dict(cfg), loaded=loaded)


def load(path, size: str = "embedded") -> tuple[FrequencyGuidedNetwork, CheckpointReport]:
    """The frequency-guided network of a checkpoint, strictly loaded, and what was read.

    size "paper": the official pair (a folder holding ``pretrained_priorD.pth`` and ``TR00_E096.pt``,
    ``"prior.pth,vposer.pt"`` in either order, or a pair of paths; each file is recognised by its
    keys) into the paper-size network; size "embedded": the project's file
    (``priors/weights/frequency_guided.pt``) at the size its config says.
    """
    check_size("frequency-guided", size)
    return _load_paper(path) if size == "paper" else _load_project(path)
