"""The CVAE of Marsot et al. (3DV 2022, paper 001 §3.2): E(chi) -> (mu, sigma), D(z, beta) -> chi_hat.

The paper gives the CVAE structure (encoder not conditioned on beta, decoder conditioned on beta,
z = mu + eps * sigma), dim(z) = 64 (256 for its CHUM comparison) and dim(beta) = 8, but no layer
types or widths. Chosen here (a temporal convolutional CVAE over the 100 anchors; widths
configurable, sizes in :data:`PAPER_CONFIG` / :data:`EMBEDDED_CONFIG`):

Encoder, chi (B, 100, 124) (anchors x features):
    per-anchor Linear(124, C)                 100   LeakyReLU(0.2)
    Conv1d(C, C, 4, stride 2, pad 1)           50   LeakyReLU      (over time, channels = features)
    Conv1d(C, 2C, 4, stride 2, pad 1)          25   LeakyReLU
    Conv1d(2C, 2C, 3, stride 2, pad 1)         13   LeakyReLU
    Flatten -> Linear(2C*13, H) -> LeakyReLU -> mu = Linear(H, L), sigma = softplus(Linear(H, L))
Decoder, [z, (beta - shape_center) * shape_scale] (B, L + S):
    Linear(L + S, H) -> LeakyReLU -> Linear(H, 2C*13) -> LeakyReLU -> (B, 2C, 13)
    ConvTranspose1d(2C, 2C, 3, stride 2, pad 1)    25   LeakyReLU
    ConvTranspose1d(2C, C, 4, stride 2, pad 1)     50   LeakyReLU
    ConvTranspose1d(C, C, 4, stride 2, pad 1)     100   LeakyReLU   <- last shared representation (GradNorm)
    per-anchor Linear(C, 124)                     100               <- output head (one unit per chi feature)
(Per-anchor linear layers instead of full-resolution convolutions: the same receptive field
from the strided convolutions, 1.5x faster on one CPU core.)
Output chi_hat (B, 100, 124): pose and translation channels as they come; with
``monotone_time`` (default) the timestamp channel r becomes tau_hat_0 = 0,
tau_hat_i = sum_{j=1..i} softplus(r_j) / (n - 1): non-decreasing by construction (the paper's
decoder outputs T_hat directly; a monotone head keeps anchors in time order, which interpolating
between them needs).

The network also carries the normalisation of chi (buffers ``trans_min``, ``trans_max``,
``tau_max``: training-set min-max, see representation.py), so a checkpoint is self-contained.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from priors.structured_latent.representation import ANCHORS, FEATURES, TIME, chi_to_motion

PAPER_CONFIG = {"latent": 64, "shape_dim": 8, "channels": 128, "hidden": 1024, "anchors": ANCHORS, "features": FEATURES,
                "monotone_time": True, "shape_center": 0.0, "shape_scale": 1.0}
"""Paper-size network (sizes beyond latent 64 / beta 8 inferred): 8 SMPL betas, used as they come."""
PAPER_CHUM_CONFIG = {**PAPER_CONFIG, "latent": 256}
"""The variant retrained with dim(z) = 256 for the CHUM completion comparison (001 §5.3)."""
EMBEDDED_CONFIG = {"latent": 64, "shape_dim": 6, "channels": 64, "hidden": 256, "anchors": ANCHORS, "features": FEATURES,
                   "monotone_time": True, "shape_center": 0.5, "shape_scale": 2.0}
"""The embedded network: the Anny body's 6 phenotype numbers in [0, 1] mapped to [-1, 1]."""

_BOTTOM = 13  # anchors after three stride-2 convolutions of 100 (100 -> 50 -> 25 -> 13)


class StructuredLatentCVAE(nn.Module):
    """Encoder / decoder of the structured latent space (module docstring)."""

    def __init__(self, latent: int = 64, shape_dim: int = 6, channels: int = 64, hidden: int = 256,
                 anchors: int = ANCHORS, features: int = FEATURES, monotone_time: bool = True,
                 shape_center: float = 0.5, shape_scale: float = 2.0):
        super().__init__()
        if int(anchors) != ANCHORS:
            raise ValueError(f"StructuredLatentCVAE: the convolution stack is built for {ANCHORS} anchors, got {anchors}")
        if int(features) != FEATURES:
            raise ValueError(f"StructuredLatentCVAE: chi has {FEATURES} features per anchor, got {features}")
        self.latent, self.shape_dim = int(latent), int(shape_dim)
        self.channels, self.hidden = int(channels), int(hidden)
        self.anchors, self.features = ANCHORS, FEATURES
        self.monotone_time = bool(monotone_time)
        self.shape_center, self.shape_scale = float(shape_center), float(shape_scale)
        C, H, L, S = self.channels, self.hidden, self.latent, self.shape_dim
        act = lambda: nn.LeakyReLU(0.2)  # noqa: E731
        self.enc_in = nn.Linear(FEATURES, C)
        self.encoder = nn.Sequential(
            act(),
            nn.Conv1d(C, C, 4, stride=2, padding=1), act(),
            nn.Conv1d(C, 2 * C, 4, stride=2, padding=1), act(),
            nn.Conv1d(2 * C, 2 * C, 3, stride=2, padding=1), act(),
            nn.Flatten(), nn.Linear(2 * C * _BOTTOM, H), act(),
        )
        self.enc_mu = nn.Linear(H, L)
        self.enc_sigma = nn.Linear(H, L)
        self.dec_in = nn.Sequential(nn.Linear(L + S, H), act(), nn.Linear(H, 2 * C * _BOTTOM), act())
        self.dec_up = nn.Sequential(
            nn.ConvTranspose1d(2 * C, 2 * C, 3, stride=2, padding=1), act(),
            nn.ConvTranspose1d(2 * C, C, 4, stride=2, padding=1), act(),
            nn.ConvTranspose1d(C, C, 4, stride=2, padding=1), act(),
        )
        self.dec_out = nn.Linear(C, FEATURES)
        self.register_buffer("trans_min", torch.full((3,), -1.0))
        self.register_buffer("trans_max", torch.full((3,), 1.0))
        self.register_buffer("tau_max", torch.tensor(1.0))

    @property
    def config(self) -> dict:
        return {"latent": self.latent, "shape_dim": self.shape_dim, "channels": self.channels, "hidden": self.hidden,
                "anchors": self.anchors, "features": self.features, "monotone_time": self.monotone_time,
                "shape_center": self.shape_center, "shape_scale": self.shape_scale}

    def set_normalisation(self, trans_min, trans_max, tau_max) -> None:
        with torch.no_grad():
            self.trans_min.copy_(torch.as_tensor(trans_min, dtype=torch.float32))
            self.trans_max.copy_(torch.as_tensor(trans_max, dtype=torch.float32))
            self.tau_max.copy_(torch.as_tensor(tau_max, dtype=torch.float32))

    def normalisation(self) -> dict:
        return {"trans_min": self.trans_min.tolist(), "trans_max": self.trans_max.tolist(), "tau_max": float(self.tau_max)}

    # -- encoder / decoder -----------------------------------------------------------------
    def encode(self, chi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """chi (B, 100, 124) -> (mu, sigma), each (B, L)."""
        if chi.dim() != 3 or chi.shape[1:] != (self.anchors, self.features):
            raise ValueError(f"chi must be (B, {self.anchors}, {self.features}), got {tuple(chi.shape)}")
        h = self.encoder(self.enc_in(chi).transpose(1, 2))
        return self.enc_mu(h), F.softplus(self.enc_sigma(h)) + 1e-6

    def decode(self, z: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
        """z (B, L), shape (B, S) -> chi_hat (B, 100, 124) (pose channels raw 6D minus identity)."""
        return self.decode_with_shared(z, shape)[0]

    def decode_with_shared(self, z: torch.Tensor, shape: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(chi_hat, the last shared representation (B, 100, C)): GradNorm measures the loss terms'
        gradients there."""
        b = (shape - self.shape_center) * self.shape_scale
        h = self.dec_in(torch.cat([z, b.to(z.dtype)], dim=-1)).unflatten(-1, (2 * self.channels, _BOTTOM))
        shared = self.dec_up(h).transpose(1, 2)  # (B, 100, C)
        out = self.dec_out(shared)  # (B, 100, 124)
        if not self.monotone_time:
            return out, shared
        inc = F.softplus(out[:, 1:, TIME]) / (self.anchors - 1)  # (B, 99)
        tau = torch.cat([inc[:, :1] * 0, torch.cumsum(inc, dim=1)], dim=1)  # (x * 0: a dynamic batch when traced)
        return torch.cat([out[..., :TIME], tau[..., None]], dim=-1), shared

    def forward(self, chi: torch.Tensor, shape: torch.Tensor, sample: bool = True) -> dict:
        """{"mu", "sigma", "z", "chi" (chi_hat), "shared" (see :meth:`decode_with_shared`)}."""
        mu, sigma = self.encode(chi)
        z = mu + torch.randn_like(mu) * sigma if sample else mu
        out, shared = self.decode_with_shared(z, shape)
        return {"mu": mu, "sigma": sigma, "z": z, "chi": out, "shared": shared}

    def decode_motion(self, z: torch.Tensor, shape: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """z, shape -> anchor rotations (B, 100, 22, 3, 3), translation (B, 100, 3) m, tau_hat (B, 100) s."""
        return chi_to_motion(self.decode(z, shape), self.trans_min, self.trans_max, self.tau_max)


def kl_divergence(mu: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """KL(N(mu, sigma^2) || N(0, I)) summed over latent dims, (B,)."""
    return 0.5 * (mu.square() + sigma.square() - 1.0 - 2.0 * torch.log(sigma)).sum(-1)


__all__ = ["StructuredLatentCVAE", "kl_divergence", "PAPER_CONFIG", "PAPER_CHUM_CONFIG", "EMBEDDED_CONFIG"]
