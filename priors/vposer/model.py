"""VPoser networks, layer for layer as the official code (so official keys map one to one), at any size:
:class:`VPoser` (V02_05) and :class:`VPoserV1` (v1.0, the pose code of Xu et al. 2021). Pure torch, no I/O.

See the package docstring (:mod:`priors.vposer`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from benchmark.core.rotations import sixd_to_matrix


NUM_BODY_JOINTS = 21  # SMPL joints 1..21
PAPER_CONFIG = {"hidden": 512, "latent": 32}
EMBEDDED_CONFIG = {"hidden": 256, "latent": 32}


# -- the network -----------------------------------------------------------------------------
class NormalDistDecoder(nn.Module):
    """Encoder head: ``Normal(mu(x), softplus(logvar(x)))``; the "logvar" head is a softplus scale."""

    def __init__(self, num_feat_in: int, latent: int):
        super().__init__()
        self.mu = nn.Linear(num_feat_in, latent)
        self.logvar = nn.Linear(num_feat_in, latent)

    def forward(self, x: torch.Tensor) -> torch.distributions.Normal:
        return torch.distributions.Normal(self.mu(x), F.softplus(self.logvar(x)))


class ContinousRotReprDecoder(nn.Module):
    """(B, 21*6) -> (B*21, 3, 3): VPoser's 6D decoder, "interleaved" layout (row-major 3x2)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return sixd_to_matrix(x.reshape(-1, 6), layout="interleaved")


class VPoser(nn.Module):
    """The VPoser V02_05 network; module indices match the official state-dict keys.

    ``encoder_net``: 0 flatten, 1 BatchNorm1d(63), 2 Linear(63, H), 3 LeakyReLU(0.01),
    4 BatchNorm1d(H), 5 Dropout(0.1), 6 Linear(H, H), 7 Linear(H, H) (no activation between 6 and
    7, as in the official code), 8 NormalDistDecoder(H, L).
    ``decoder_net``: 0 Linear(L, H), 1 LeakyReLU(0.01), 2 Dropout(0.1), 3 Linear(H, H),
    4 LeakyReLU(0.01), 5 Linear(H, 126), 6 ContinousRotReprDecoder.
    """

    def __init__(self, hidden: int = 512, latent: int = 32):
        super().__init__()
        self.hidden, self.latent = int(hidden), int(latent)
        n_in = NUM_BODY_JOINTS * 3
        H, L = self.hidden, self.latent
        self.encoder_net = nn.Sequential(
            nn.Flatten(),
            nn.BatchNorm1d(n_in),
            nn.Linear(n_in, H),
            nn.LeakyReLU(0.01),
            nn.BatchNorm1d(H),
            nn.Dropout(0.1),
            nn.Linear(H, H),
            nn.Linear(H, H),
            NormalDistDecoder(H, L),
        )
        self.decoder_net = nn.Sequential(
            nn.Linear(L, H),
            nn.LeakyReLU(0.01),
            nn.Dropout(0.1),
            nn.Linear(H, H),
            nn.LeakyReLU(0.01),
            nn.Linear(H, NUM_BODY_JOINTS * 6),
            ContinousRotReprDecoder(),
        )

    @property
    def config(self) -> dict:
        return {"hidden": self.hidden, "latent": self.latent}

    def encode(self, pose_body: torch.Tensor) -> torch.distributions.Normal:
        """(B, 21, 3) or (B, 63) axis-angle body pose (radians) -> Normal over z, loc/scale (B, L)."""
        return self.encoder_net(pose_body)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """(B, L) latents -> (B, 21, 3, 3) local rotations of SMPL joints 1..21."""
        return self.decoder_net(z).reshape(z.shape[0], NUM_BODY_JOINTS, 3, 3)

    def forward(self, pose_body: torch.Tensor) -> dict:
        q = self.encode(pose_body)
        z = q.rsample()
        return {"q_z": q, "z": z, "rotations": self.decode(z)}


def sixd_interleaved_to_matrix(x: torch.Tensor) -> torch.Tensor:
    """(..., 6) -> (..., 3, 3), VPoser's ``ContinousRotReprDecoder`` ("interleaved" layout).

    The 6 numbers are a row-major 3x2 matrix: a1 = x[..., (0, 2, 4)], a2 = x[..., (1, 3, 5)];
    b1 = a1/|a1|, b2 = normalised (a2 - (b1.a2) b1), b3 = b1 x b2; R = [b1 b2 b3] (columns). Norms
    are clamped at 1e-12 as ``F.normalize`` does in the official code. Same numbers as
    ``benchmark.core.rotations.sixd_to_matrix(x, "interleaved")``, but a 2-D input (N, 6) is handled with
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
