"""VPoser v1.0 (``nghorbani/human_body_prior``, branch ``cvpr19``), the pose code of Xu et al. 2021.

The frequency-guided motion prior (:mod:`priors.frequency_guided`) decodes a motion into one
32-D VPoser **v1.0** code per frame; the body pose is that code through the VPoser v1.0 decoder.
v1.0 differs from V02_05 (:mod:`priors.vposer`) in layer names, activations and layout, and the
two checkpoints are not interchangeable (/work/shared/priors.md section 1c, 1d).

Network (``human_body_prior@cvpr19: human_body_prior/train/vposer_smpl.py``; paper size
``hidden=512, latent=32``, 673,596 parameters), layers directly on the module (so the state-dict
keys are the layer names)::

    encoder  x (N, 63) axis-angle of SMPL joints 1..21
             bodyprior_enc_bn1 BatchNorm1d(63) -> bodyprior_enc_fc1 Linear(63, H) -> leaky_relu(0.2)
             -> bodyprior_enc_bn2 BatchNorm1d(H) -> dropout(0.1) -> bodyprior_enc_fc2 Linear(H, H)
             -> leaky_relu(0.2) -> Normal(bodyprior_enc_mu Linear(H, L), softplus(bodyprior_enc_logvar Linear(H, L)))
    decoder  z (N, L) -> bodyprior_dec_fc1 Linear(L, H) -> leaky_relu(0.2) -> dropout(0.1)
             -> bodyprior_dec_fc2 Linear(H, H) -> leaky_relu(0.2) -> bodyprior_dec_out Linear(H, 21*6)
             -> 6D "interleaved" (each 6 numbers a row-major 3x2 matrix; Gram-Schmidt) -> (N, 21, 3, 3)

The "logvar" head is used as a softplus *scale* (as in the official code). Dropout is inactive in
eval mode (the adapters keep the network in eval mode).

Checkpoint: the official ``vposer_v1_0/snapshots/TR00_E096.pt`` is a plain ``state_dict`` (an
``OrderedDict`` of the 16 parameter tensors above plus the BatchNorms' running statistics and, when
written by torch >= 0.4.1, ``num_batches_tracked``); a ``{"state_dict": ...}`` wrapper is accepted
too. :func:`load_vposer_v1_state` maps it strictly: every key present with its shape, no
leftovers (``num_batches_tracked`` is optional: unused in eval mode).
"""

from __future__ import annotations

import pickle
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

NUM_BODY_JOINTS = 21
PAPER_CONFIG = {"hidden": 512, "latent": 32}
WHERE_TO_GET = (
    "VPoser v1.0 is distributed (registration required) as vposer_v1_0.zip on the SMPL-X download page "
    "https://smpl-x.is.tue.mpg.de/download.php; the weights are vposer_v1_0/snapshots/TR00_E096.pt"
)


def sixd_interleaved_to_matrix(x: torch.Tensor) -> torch.Tensor:
    """(..., 6) -> (..., 3, 3), VPoser's ``ContinousRotReprDecoder`` ("interleaved" layout).

    The 6 numbers are a row-major 3x2 matrix: a1 = x[..., (0, 2, 4)], a2 = x[..., (1, 3, 5)];
    b1 = a1/|a1|, b2 = normalised (a2 - (b1.a2) b1), b3 = b1 x b2; R = [b1 b2 b3] (columns). Norms
    are clamped at 1e-12 as ``F.normalize`` does in the official code. Same numbers as
    ``benchmark.rotations.sixd_to_matrix(x, "interleaved")``, but a 2-D input (N, 6) is handled with
    ``reshape(-1, ...)`` only, so that an ONNX trace keeps N dynamic.
    """
    lead = x.shape[:-1]
    m = x.reshape(-1, 3, 2)
    b1 = F.normalize(m[:, :, 0], dim=1)
    a2 = m[:, :, 1]
    b2 = F.normalize(a2 - (b1 * a2).sum(dim=1, keepdim=True) * b1, dim=1)
    b3 = torch.cross(b1, b2, dim=1)
    R = torch.stack([b1, b2, b3], dim=-1)
    return R if x.dim() == 2 else R.reshape(*lead, 3, 3)


class VPoserV1(nn.Module):
    """The VPoser v1.0 network (module docstring); attribute names are the official keys."""

    def __init__(self, hidden: int = 512, latent: int = 32):
        super().__init__()
        self.hidden, self.latent = int(hidden), int(latent)
        n_in, H, L = NUM_BODY_JOINTS * 3, self.hidden, self.latent
        self.bodyprior_enc_bn1 = nn.BatchNorm1d(n_in)
        self.bodyprior_enc_fc1 = nn.Linear(n_in, H)
        self.bodyprior_enc_bn2 = nn.BatchNorm1d(H)
        self.bodyprior_enc_fc2 = nn.Linear(H, H)
        self.bodyprior_enc_mu = nn.Linear(H, L)
        self.bodyprior_enc_logvar = nn.Linear(H, L)
        self.dropout = nn.Dropout(p=0.1)
        self.bodyprior_dec_fc1 = nn.Linear(L, H)
        self.bodyprior_dec_fc2 = nn.Linear(H, H)
        self.bodyprior_dec_out = nn.Linear(H, NUM_BODY_JOINTS * 6)

    @property
    def config(self) -> dict:
        return {"hidden": self.hidden, "latent": self.latent}

    def encode(self, pose_body: torch.Tensor) -> torch.distributions.Normal:
        """(N, 21, 3), (N, 1, 21, 3) or (N, 63) axis-angle (rad) -> Normal over z, loc/scale (N, L)."""
        x = pose_body.reshape(pose_body.shape[0], -1)
        if x.shape[1] != NUM_BODY_JOINTS * 3:
            raise ValueError(f"VPoser v1 encodes 21 body joints (63 axis-angle values), got {tuple(pose_body.shape)}")
        x = self.bodyprior_enc_bn1(x)
        x = F.leaky_relu(self.bodyprior_enc_fc1(x), negative_slope=0.2)
        x = self.bodyprior_enc_bn2(x)
        x = self.dropout(x)
        x = F.leaky_relu(self.bodyprior_enc_fc2(x), negative_slope=0.2)
        return torch.distributions.Normal(self.bodyprior_enc_mu(x), F.softplus(self.bodyprior_enc_logvar(x)))

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """(N, L) codes -> (N, 21, 3, 3) local rotations of SMPL joints 1..21 (traceable, dynamic N)."""
        x = F.leaky_relu(self.bodyprior_dec_fc1(z), negative_slope=0.2)
        x = self.dropout(x)
        x = F.leaky_relu(self.bodyprior_dec_fc2(x), negative_slope=0.2)
        x = self.bodyprior_dec_out(x)
        return sixd_interleaved_to_matrix(x.reshape(-1, 6)).reshape(-1, NUM_BODY_JOINTS, 3, 3)

    def forward(self, pose_body: torch.Tensor) -> dict:
        q = self.encode(pose_body)
        z = q.rsample()
        return {"q_z": q, "z": z, "rotations": self.decode(z)}


# -- strict loading --------------------------------------------------------------------------
def _is_optional(key: str) -> bool:
    return key.endswith("num_batches_tracked")


def torch_load_cpu(file: str | Path) -> object:
    """``torch.load`` on CPU, ``weights_only=True`` first (plain state dicts, also the legacy
    pre-1.6 serialisation), then the project's tolerant full unpickler (see priors.vposer)."""
    try:
        return torch.load(file, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        from priors.vposer import _torch_load

        return _torch_load(Path(file))


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
            f"{WHERE_TO_GET}"
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


__all__ = [
    "VPoserV1",
    "sixd_interleaved_to_matrix",
    "load_vposer_v1_state",
    "is_vposer_v1_state",
    "torch_load_cpu",
    "PAPER_CONFIG",
    "WHERE_TO_GET",
]
