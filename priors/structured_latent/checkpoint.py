"""Structured latent space checkpoints: the project format, read strictly (official weights: format unknown,
see ``OFFICIAL_UNKNOWN``)."""

from __future__ import annotations

from pathlib import Path

import torch

from benchmark.safe_loading import UnsafeFileError, torch_load_weights
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
def load_checkpoint(path: str | Path) -> tuple[StructuredLatentCVAE, dict]:
    """Build and strictly load a project checkpoint ``{"state_dict", "config": {"network",
    "normalisation", "format"}}`` (written by :func:`priors.structured_latent.train.train_structured_latent`). Every tensor of the
    network must be present with its shape and nothing else may be (errors name the file and key)."""
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
    raw = ckpt["state_dict"]
    expected = net.state_dict()
    for key, ref in expected.items():
        if key not in raw:
            raise KeyError(f"{path}: missing key {key!r} (shape {tuple(ref.shape)}); the checkpoint must hold all of {sorted(expected)}")
        if not torch.is_tensor(raw[key]) or raw[key].shape != ref.shape:
            found = tuple(raw[key].shape) if torch.is_tensor(raw[key]) else type(raw[key]).__name__
            raise ValueError(f"{path}: key {key!r} has shape {found}, expected {tuple(ref.shape)} for config {net.config}")
    extra = sorted(set(raw) - set(expected))
    if extra:
        raise ValueError(f"{path}: unexpected keys {extra[:10]} (not part of StructuredLatentCVAE with config {net.config})")
    net.load_state_dict(raw, strict=True)
    return net, cfg


__all__ = ["load_checkpoint", "DEFAULT_WEIGHTS", "CHECKPOINT_NAME", "CHECKPOINT_FORMAT", "OFFICIAL_UNKNOWN", "TRAIN_COMMAND"]
