"""Structured latent space checkpoints: the project format, read strictly by :func:`load`
(``load(path, size) -> (StructuredLatentCVAE, CheckpointReport)``; official weights: format unknown, see
``OFFICIAL_UNKNOWN``)."""

from __future__ import annotations

from pathlib import Path

from benchmark.core.safe_loading import UnsafeFileError, torch_load_weights
from priors.checkpoints import CheckpointReport, check_size, load_state_strict
from priors.structured_latent.model import StructuredLatentCVAE

CHECKPOINT_NAME = "structured_latent.pt"
DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / CHECKPOINT_NAME
CHECKPOINT_FORMAT = "structured-latent/1"
TRAIN_COMMAND = "python -m benchmark train structured-latent"
OFFICIAL_UNKNOWN = (
    "structured-latent size 'paper' has no loader for official weights: the authors' code and any checkpoint "
    "(gitlab.inria.fr/mmarsot/a-structured-latent-space; github.com/mmarsot/A_structured_latent_space is only a README "
    "pointer) were not reachable when this adapter was written, so these are unknown: the checkpoint file format and "
    "its state-dict key names, the encoder/decoder layer types and widths (the paper gives only dim(z) = 64, or 256 for "
    "its CHUM comparison, and 8 SMPL betas), the 6D layout, and the training-set normalisation statistics "
    "(translation min/max, timestamp max) that chi needs. Use size='embedded' (priors/weights/structured_latent.pt, "
    f"`{TRAIN_COMMAND}`), or add a loader to priors/structured_latent/checkpoint.py after inspecting the official files. "
    "`python -m benchmark describe structured-latent --size paper` prints the paper-size architecture assumed here."
)


# -- checkpoints ------------------------------------------------------------------------------
def load(path: str | Path, size: str = "embedded") -> tuple[StructuredLatentCVAE, CheckpointReport]:
    """Build and strictly load a project checkpoint ``{"state_dict", "config": {"network",
    "normalisation", "format"}}`` (written by :func:`priors.structured_latent.train.train_structured_latent`). Every tensor of the
    network must be present with its shape and nothing else may be (errors name the file and key).
    The report's ``config`` is the file's config. Size "paper": no official format is known
    (``OFFICIAL_UNKNOWN``)."""
    check_size("structured-latent", size)
    if size == "paper":
        raise ValueError(OFFICIAL_UNKNOWN + ("" if path is None else f" (weights given: {path})"))
    path = Path(path)
    try:
        ckpt = torch_load_weights(path, f"retrain with `{TRAIN_COMMAND}`")
    except UnsafeFileError:
        raise
    except Exception as exc:
        raise ValueError(f"{path}: not a readable structured-latent checkpoint ({type(exc).__name__}: {exc}); "
                         f"retrain with `{TRAIN_COMMAND}`") from exc
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), dict) or not isinstance(ckpt.get("config"), dict):
        top = sorted(ckpt)[:20] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(f"{path}: expected a dict with 'state_dict' and 'config' (priors/weights/{CHECKPOINT_NAME}), found {top}")
    cfg = ckpt["config"]
    if "network" not in cfg:
        raise ValueError(f"{path}: field 'config.network' is missing; retrain with `{TRAIN_COMMAND}`")
    try:
        net = StructuredLatentCVAE(**cfg["network"])
    except TypeError as exc:
        raise ValueError(f"{path}: field 'config.network' = {cfg['network']!r} does not describe a StructuredLatentCVAE ({exc})") from exc
    loaded, _ = load_state_strict(net, ckpt["state_dict"], path, "StructuredLatentCVAE", note=f"config {net.config}")
    return net, CheckpointReport(file=path, format="project", config=cfg, loaded=loaded)


__all__ = ["load", "DEFAULT_WEIGHTS", "CHECKPOINT_NAME", "CHECKPOINT_FORMAT", "OFFICIAL_UNKNOWN", "TRAIN_COMMAND"]
