"""Sequential latent primitives: the networks at any size (pure torch, no I/O) and their tensor helpers.

See the package docstring (:mod:`priors.sequential_primitives`) for the method and the sizes.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from benchmark.core.frames import (
    heading as root_heading,
    sixd_columns_to_matrix as gram_schmidt,
    to_heading_frame,
    yaw_matrix,
)
from benchmark.core.rotations import matrix_to_sixd
from benchmark.core.skeleton import NUM_JOINTS


FOOT_JOINTS = (10, 11)
MODEL_JOINTS = tuple(j for j in range(NUM_JOINTS) if j not in FOOT_JOINTS)  # 20 joints, root first
NUM_MODEL_JOINTS = len(MODEL_JOINTS)
POSE_DIM = NUM_MODEL_JOINTS * 6  # 120
FRAME_DIM = POSE_DIM + 3  # 123
SMPL_VERTICES = 6890
FORMAT = "sequential-primitives/project-v1"

PAPER_CONFIG = {
    "primitives": 8, "latent": 256, "shape_dim": 8, "d_model": 256, "heads": 8, "enc_layers": 4, "dec_layers": 4,
    "ff": 1024, "dropout": 0.1, "mlp_hidden": 512, "mlp_layers": 4, "seg_layers": 2, "time_freqs": 6,
    "pe_scale": 100.0, "point_hidden": [64, 128, 256],
}
EMBEDDED_CONFIG = {
    "primitives": 8, "latent": 64, "shape_dim": 6, "d_model": 128, "heads": 4, "enc_layers": 2, "dec_layers": 2,
    "ff": 256, "dropout": 0.0, "mlp_hidden": 128, "mlp_layers": 3, "seg_layers": 2, "time_freqs": 6,
    "pe_scale": 100.0, "point_hidden": [32, 64],
}
ARCH_KEYS = tuple(EMBEDDED_CONFIG)

TRAIN_FPS = 30.0


# -- small tensor helpers -----------------------------------------------------------------------
def _identity6(dtype=torch.float32, device=None) -> torch.Tensor:
    return torch.eye(3, dtype=dtype, device=device)[:2].reshape(6)  # [1, 0, 0, 0, 1, 0]: columns of I


def canonicalise(R: torch.Tensor, trans: torch.Tensor, mask: torch.Tensor | None = None):
    """Heading of frame 0 to +z, zero-mean translation (over ``mask``-ed frames).

    R (B, T, 22, 3, 3), trans (B, T, 3), mask (B, T) bool. Returns (R', trans', yaw (B,), mean (B, 3))
    with R'_root = R_y(-yaw) R_root and trans' = R_y(-yaw) (trans - mean).
    """
    if mask is None:
        mean = trans.mean(1)
    else:
        m = mask.to(trans.dtype)[..., None]
        mean = (trans * m).sum(1) / m.sum(1).clamp_min(1)
    yaw = root_heading(R[:, 0, 0])
    R, trans = to_heading_frame(R, trans, yaw_matrix(-yaw), mean)
    return R, trans, yaw, mean


def sinusoidal_encoding(pos: torch.Tensor, dim: int) -> torch.Tensor:
    """(..., ) positions -> (..., dim) [sin(pos w_k), cos(pos w_k)], w_k = 10000^(-2k/dim)."""
    half = dim // 2
    k = torch.arange(half, dtype=pos.dtype, device=pos.device)
    w = torch.exp(-math.log(10000.0) * 2 * k / dim)
    a = pos[..., None] * w
    enc = torch.cat([torch.sin(a), torch.cos(a)], dim=-1)
    if dim % 2:
        enc = F.pad(enc, (0, 1))
    return enc


def time_features(u: torch.Tensor, freqs: int) -> torch.Tensor:
    """(...) -> (..., 2*freqs + 1) [u, sin(2^k pi u), cos(2^k pi u)]."""
    k = torch.arange(freqs, dtype=u.dtype, device=u.device)
    a = u[..., None] * (math.pi * torch.pow(2.0, k))
    return torch.cat([u[..., None], torch.sin(a), torch.cos(a)], dim=-1)


def insert_feet(R20: torch.Tensor) -> torch.Tensor:
    """(..., 20, 3, 3) modelled joints -> (..., 22, 3, 3) with identity feet (10, 11)."""
    eye = torch.eye(3, dtype=R20.dtype, device=R20.device).expand(*R20.shape[:-3], 2, 3, 3)
    return torch.cat([R20[..., :10, :, :], eye, R20[..., 10:, :, :]], dim=-3)


# -- the network --------------------------------------------------------------------------------
class SeqCore(nn.Module):
    """Transformer: n frame tokens (+ timestamp encoding) -> m output tokens (learned queries)."""

    def __init__(self, cfg: dict):
        super().__init__()
        d, m = cfg["d_model"], cfg["primitives"]
        self.d_model, self.pe_scale = d, float(cfg["pe_scale"])
        enc = nn.TransformerEncoderLayer(d, cfg["heads"], cfg["ff"], cfg["dropout"], batch_first=True, norm_first=True)
        dec = nn.TransformerDecoderLayer(d, cfg["heads"], cfg["ff"], cfg["dropout"], batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(enc, cfg["enc_layers"], norm=nn.LayerNorm(d), enable_nested_tensor=False)
        self.decoder = nn.TransformerDecoder(dec, cfg["dec_layers"], norm=nn.LayerNorm(d))
        self.queries = nn.Parameter(torch.randn(m, d) * 0.02)

    def forward(self, tokens: torch.Tensor, tau: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """tokens (B, n, d), tau (B, n) in [0, 1], mask (B, n) True = real frame -> (B, m, d)."""
        x = tokens + sinusoidal_encoding(tau.to(tokens.dtype) * self.pe_scale, self.d_model)
        pad = None if mask is None else ~mask
        mem = self.encoder(x, src_key_padding_mask=pad)
        q = self.queries.expand(tokens.shape[0], -1, -1)
        return self.decoder(q, mem, memory_key_padding_mask=pad)


class MotionEncoder(nn.Module):
    """[20 x 6D - identity, gamma (normalised)] per frame -> (mu, logvar) (B, m, D) each."""

    def __init__(self, cfg: dict):
        super().__init__()
        self.embed = nn.Linear(FRAME_DIM, cfg["d_model"])
        self.core = SeqCore(cfg)
        self.head = nn.Linear(cfg["d_model"], 2 * cfg["latent"])

    def forward(self, frames: torch.Tensor, tau: torch.Tensor, mask: torch.Tensor | None = None):
        h = self.head(self.core(self.embed(frames), tau, mask))
        mu, logvar = h.chunk(2, dim=-1)
        return mu, logvar.clamp(-20.0, 10.0)


class PointNetEmbed(nn.Module):
    """PointNet frame embedding: a shared MLP 3 -> hidden[0] -> ... -> hidden[-1] (ReLU after each
    layer), a masked max-pool over each frame's points, then Linear(hidden[-1], d_model)."""

    def __init__(self, hidden: list, d_model: int):
        super().__init__()
        dims = [3, *[int(h) for h in hidden]]
        layers = []
        for a, b in zip(dims[:-1], dims[1:]):
            layers += [nn.Linear(a, b), nn.ReLU()]
        self.mlp = nn.Sequential(*layers)
        self.out = nn.Linear(dims[-1], d_model)

    def forward(self, points: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """points (B, n, N, 3), lengths (B, n) -> (B, n, d_model); frames without points pool to 0."""
        f = self.mlp(points)  # >= 0 after the ReLU, so masking with 0 is a masked max
        valid = torch.arange(points.shape[2], device=points.device) < lengths[..., None]
        f = (f * valid[..., None].to(f.dtype)).amax(2)
        return self.out(f)


class PointEncoder(nn.Module):
    """The initialisation encoder: PointNet frame embedding + the same transformer -> mu (B, m, D)."""

    def __init__(self, cfg: dict):
        super().__init__()
        self.pointnet = PointNetEmbed(cfg["point_hidden"], cfg["d_model"])
        self.core = SeqCore(cfg)
        self.head = nn.Linear(cfg["d_model"], cfg["latent"])

    def forward(self, points: torch.Tensor, lengths: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
        """points (B, n, N, 3) metres (any heading), lengths (B, n), tau (B, n) -> mu (B, m, D)."""
        lengths = lengths.to(points.device)
        valid = torch.arange(points.shape[2], device=points.device) < lengths[..., None]
        w = valid.to(points.dtype)[..., None]
        cen = (points * w).sum(2) / w.sum(2).clamp_min(1)  # (B, n, 3)
        has = (lengths > 0).to(points.dtype)[..., None]
        centre = (cen * has).sum(1) / has.sum(1).clamp_min(1)  # (B, 3)
        x = (points - centre[:, None, None]) * w
        return self.head(self.core(self.pointnet(x, lengths), tau, lengths > 0))


class PrimitiveDecoder(nn.Module):
    """D(z_i, beta, tau) and the Gaussian-mask combination (Eqs. 1-2); see the module docstring."""

    def __init__(self, cfg: dict):
        super().__init__()
        D, S, H = cfg["latent"], cfg["shape_dim"], cfg["mlp_hidden"]
        self.freqs = int(cfg["time_freqs"])
        self.shape_dim = S
        seg = []
        for i in range(int(cfg["seg_layers"])):
            seg += [nn.Linear(D + S if i == 0 else H, H), nn.SiLU()]
        self.seg_mlp = nn.Sequential(*seg, nn.Linear(H, 5))
        self.in_z = nn.Linear(D + S, H)
        self.in_t = nn.Linear(2 * self.freqs + 1, H, bias=False)
        body = []
        for _ in range(int(cfg["mlp_layers"]) - 1):
            body += [nn.SiLU(), nn.Linear(H, H)]
        self.body = nn.Sequential(*body, nn.SiLU(), nn.Linear(H, FRAME_DIM))
        with torch.no_grad():  # start near identity rotations and identity rigid transforms
            last = self.body[-1]
            last.weight.mul_(0.1)
            last.bias.zero_()
            self.seg_mlp[-1].weight.mul_(0.1)
            self.seg_mlp[-1].bias.copy_(torch.tensor([0.0, 1.0, 0.0, 0.0, 0.0]))
        self.register_buffer("trans_center", torch.zeros(3))
        self.register_buffer("trans_scale", torch.ones(3))
        self.register_buffer("shape_mean", torch.full((S,), 0.5))

    def segments(self, z: torch.Tensor, shape: torch.Tensor):
        """Time-independent part: durations (B, m), starts Delta (B, m), yaw (cos, sin) (B, m, 2), t (B, m, 2)."""
        zb = torch.cat([z, shape[:, None].expand(-1, z.shape[1], -1)], dim=-1)
        out = self.seg_mlp(zb)
        delta = torch.softmax(out[..., 0], dim=-1)
        start = torch.cumsum(delta, dim=-1) - delta
        cs = out[..., 1:3] / out[..., 1:3].norm(dim=-1, keepdim=True).clamp_min(1e-6)
        return delta, start, cs, out[..., 3:5], zb

    def forward(self, z: torch.Tensor, shape: torch.Tensor, tau: torch.Tensor, with_segments: bool = False) -> dict:
        """z (B, m, D), shape (B, S), tau (B, T) -> dict:

        ``sixd`` (B, T, 20, 6) averaged 6D (Eq. 1), ``gamma`` (B, T, 3) normalised (Eq. 2),
        ``rotations`` (B, T, 22, 3, 3) (Gram-Schmidt, feet identity), ``trans`` (B, T, 3) metres,
        ``delta`` (B, m); with_segments adds ``seg_sixd`` (B, m, T, 20, 6), ``seg_gamma``
        (B, m, T, 3) (after rho_i) and ``masks`` G (B, m, T).
        """
        delta, start, cs, t_xz, zb = self.segments(z, shape)
        u = tau[:, None, :] - start[..., None]  # (B, m, T)
        h = self.in_z(zb)[:, :, None] + self.in_t(time_features(u, self.freqs))
        out = self.body(h)  # (B, m, T, 123)
        B, m, T = out.shape[:3]
        sixd = out[..., :POSE_DIM].unflatten(-1, (NUM_MODEL_JOINTS, 6)) + _identity6(out.dtype, out.device)
        cos, sin = cs[..., 0][..., None, None], cs[..., 1][..., None, None]  # (B, m, 1, 1)

        def rot_y(v):  # v (B, m, T, 3)
            return torch.stack([cos[..., 0] * v[..., 0] + sin[..., 0] * v[..., 2], v[..., 1],
                                -sin[..., 0] * v[..., 0] + cos[..., 0] * v[..., 2]], dim=-1)

        root = torch.cat([rot_y(sixd[..., 0, 0:3]), rot_y(sixd[..., 0, 3:6])], dim=-1)
        sixd = torch.cat([root[..., None, :], sixd[..., 1:, :]], dim=-2)
        c, s = self.trans_center, self.trans_scale
        g_m = c + s * out[..., POSE_DIM:]
        shift = torch.stack([t_xz[..., 0] * s[0], torch.zeros_like(t_xz[..., 0]), t_xz[..., 1] * s[2]], dim=-1)
        g_m = rot_y(g_m) + shift[:, :, None]
        gamma_seg = (g_m - c) / s  # (B, m, T, 3)

        half = (delta / 2)[..., None]
        centre = (start + delta / 2)[..., None]
        logG = -((tau[:, None, :] - centre) / half).square()  # (B, m, T)
        w = torch.softmax(logG, dim=1)
        sixd_avg = (w[..., None, None] * sixd).sum(1)  # (B, T, 20, 6)
        gamma = (w[..., None] * gamma_seg).sum(1)  # (B, T, 3)
        result = {
            "sixd": sixd_avg, "gamma": gamma, "delta": delta, "start": start,
            "rotations": insert_feet(gram_schmidt(sixd_avg)), "trans": c + s * gamma,
        }
        if with_segments:
            result.update(seg_sixd=sixd, seg_gamma=gamma_seg, masks=torch.exp(logG))
        return result


class SequentialPrimitives(nn.Module):
    """Motion encoder, primitive decoder and point-cloud initialisation encoder (module docstring)."""

    def __init__(self, **cfg):
        super().__init__()
        unknown = set(cfg) - set(ARCH_KEYS)
        missing = set(ARCH_KEYS) - set(cfg)
        if unknown or missing:
            raise ValueError(f"SequentialPrimitives config: unknown keys {sorted(unknown)}, missing {sorted(missing)}")
        if cfg["d_model"] % cfg["heads"]:
            raise ValueError(f"d_model {cfg['d_model']} must be divisible by heads {cfg['heads']}")
        self.cfg = {k: (list(v) if isinstance(v, (list, tuple)) else v) for k, v in cfg.items()}
        self.motion_encoder = MotionEncoder(cfg)
        self.decoder = PrimitiveDecoder(cfg)
        self.point_encoder = PointEncoder(cfg)

    @property
    def config(self) -> dict:
        out = dict(self.cfg)
        out["trans_center"] = [float(x) for x in self.decoder.trans_center]
        out["trans_scale"] = [float(x) for x in self.decoder.trans_scale]
        out["shape_mean"] = [float(x) for x in self.decoder.shape_mean]
        out["format"] = FORMAT
        return out

    @property
    def primitives(self) -> int:
        return int(self.cfg["primitives"])

    @property
    def latent(self) -> int:
        return int(self.cfg["latent"])

    @property
    def shape_dim(self) -> int:
        return int(self.cfg["shape_dim"])

    def set_normalisation(self, trans_center, trans_scale, shape_mean=None) -> None:
        with torch.no_grad():
            self.decoder.trans_center.copy_(torch.as_tensor(trans_center, dtype=torch.float32))
            self.decoder.trans_scale.copy_(torch.as_tensor(trans_scale, dtype=torch.float32).clamp_min(1e-3))
            if shape_mean is not None:
                self.decoder.shape_mean.copy_(torch.as_tensor(shape_mean, dtype=torch.float32))

    def frame_features(self, R: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
        """R (B, T, 22, 3, 3), trans (B, T, 3) canonical metres -> encoder input (B, T, 123)."""
        six = matrix_to_sixd(R[:, :, list(MODEL_JOINTS)], "columns") - _identity6(R.dtype, R.device)
        g = (trans - self.decoder.trans_center) / self.decoder.trans_scale
        return torch.cat([six.flatten(-2), g], dim=-1)

    def encode(self, R: torch.Tensor, trans: torch.Tensor, tau: torch.Tensor, mask: torch.Tensor | None = None):
        """Canonical-frame motion -> (mu, logvar) (B, m, D)."""
        return self.motion_encoder(self.frame_features(R, trans), tau, mask)
