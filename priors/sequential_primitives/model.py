"""Sequential latent primitives (Marsot, Wuhrer, Franco, Olivier 2022, HAL hal-03715820, paper 000).

A motion of any duration and frame rate is encoded into a sequence of m = 8 latent primitives
z_1..z_m (D = 256 in the paper); a temporally implicit decoder D(z_i, beta, tau) decodes each
primitive into a segment (pose, translation, duration, rigid transform) and the segments are
blended with Gaussian temporal masks into a motion that can be queried at any timestamp
(see /work/shared/priors.md section 5; paper sections 4 and 5).

Parts of this module
--------------------
- :class:`SequentialPrimitives`: the network (motion encoder, primitive decoder, point-cloud
  initialisation encoder). :class:`SequentialPrimitivesPrior`: the adapter (``sequential-primitives``).
- :func:`primitives_loss`: the training loss of Eqs. 3-8. :func:`train_sequential_primitives`:
  training of the embedded weights (motion VAE, then the initialisation encoder).

Representation (paper 4.1, 5.1)
-------------------------------
Per frame: 20 joints (SMPL-22 minus the feet 10 and 11) as 6D rotations relative to the parent,
root included, "columns" layout (first two columns of the matrix, Zhou et al.), and the root
translation gamma (3). The feet are identity in the output. Body shape beta: the shape vector of
the training data (our body: 6 Anny phenotypes in [0, 1], ``shape_dim = 6``; paper: 8 SMPL betas,
``shape_dim = 8`` at paper size). Only the decoder is shape-conditioned (CVAE, as in the paper's
[15]). Time: each window's timestamps are scaled to tau = t / window_s in [0, 1) (window_s = the
window's duration). Encoder inputs: 6D minus the identity 6D, translation normalised.

Canonical frame (paper silent; our choice). Every window is rotated about y so that the root's
heading (its +z axis projected on the ground) at the window's first frame faces +z, and its
translation has zero mean over the window's frames. Translation is then normalised per axis to
[-1, 1] with the training set's min/max (``trans_center`` / ``trans_scale`` in the checkpoint
config). The adapter is therefore ``heading_normalised``: the completion protocol frees a heading
and an offset per sequence (its offset starts at the observations' mean centroid, matching the
zero-mean translation).

Architecture (paper 4.2-4.3 and Figs. 1-3; sizes not in the paper are ours, configurable)
---------------------------------------------------------------------------------------
Encoder: per-frame one-layer perceptron Linear(20*6 + 3, d_model) ("one perceptron layer");
sinusoidal encoding of the timestamp added (position = tau * ``pe_scale`` with ``pe_scale = 100``,
i.e. frame-index units for n = 100 frames, standard 10000^(2k/d) frequencies); a transformer
encoder over the frames (pre-norm layers, key-padding mask for padded frames) and a transformer
decoder whose m inputs are m learned query tokens (the paper: a seq2seq transformer "similar to
the original transformer for translation" producing m outputs; learned queries are our reading);
a linear head gives (mu_i, log sigma_i^2) per primitive, z_i = mu_i + eps sigma_i.

Decoder D(z_i, beta, tau), weights shared over i:
- time-independent MLP [z_i, beta] -> (duration logit, yaw 2-vector, ground-plane translation 2).
  Durations delta = softmax over the m logits, so delta_i > 0 and sum_i delta_i = 1 covers the
  window; Delta_i = sum_{j<i} delta_j. The rigid transform rho_i is a yaw about y (angle from the
  normalised 2-vector (cos, sin), identity at initialisation) plus a translation (t_x, 0, t_z)
  (in units of the x/z translation scale): the paper's rho_i "rotates the root joint and rotates
  and translates gamma" without saying which rotations; a ground-plane rigid motion is what the
  invariance "w.r.t. the initial orientation and displacement of a segment" needs for a y-up body.
- time-dependent MLP [z_i, beta, f(tau - Delta_i)] -> theta_i(tau) (20 x 6D, as a residual on the
  identity 6D) and gamma_i(tau) (3, normalised units, segment space), with
  f(u) = [u, sin(2^k pi u), cos(2^k pi u), k = 0..time_freqs-1] (``time_freqs = 6``: the shortest
  period is 1/16 of the window, 0.25 s for 4 s; the third-party adaptation uses 8 on tau - Delta_i).
  SiLU activations (smooth in time). The first layer is split into a per-primitive part (z, beta)
  and a per-timestamp part (f), which is the same linear map on the concatenation, computed once
  per primitive.
- combination (Eqs. 1-2): G_i(tau) = exp(-((tau - (Delta_i + delta_i/2)) / (delta_i/2))^2);
  theta(tau) = sum_i G_i (rho_i * theta_i) / sum_i G_i (weights computed as a softmax of the log
  masks, the same numbers without underflow far from every segment), same for gamma. rho_i acts on
  the root's two 6D columns (a rotation commutes with Gram-Schmidt) and on gamma in metres
  (gamma_m = center + scale * gamma, then R_yaw gamma_m + t). Rotations are averaged in 6D and
  orthonormalised (Gram-Schmidt) at the output; translation is averaged.

Initialisation encoder (paper 5.5): the same encoder with the per-frame perceptron replaced by a
PointNet (shared MLP 3 -> point_hidden with ReLU, masked max-pool over each frame's points, then
Linear(point_hidden[-1], d_model)). Input points are centred by the mean over the observed frames
of the frame centroids. It is trained to regress the frozen motion encoder's posterior means (L2
on mu, summed over D, mean over primitives; our choice among the two options, cheaper than a loss
through the decoder) on point clouds of training windows under a random yaw (the target is the
canonical-frame latent, so the encoder learns yaw invariance and the protocol's heading search
finds the yaw).

Sizes
-----
=================  ====================================  ===================================
                   paper (``PAPER_CONFIG``)              embedded (``EMBEDDED_CONFIG``)
=================  ====================================  ===================================
latents m x D      8 x 256 (paper)                       8 x 64
shape_dim          8 (SMPL betas, paper)                 6 (Anny phenotypes)
transformer        d_model 256, 8 heads, 4 enc + 4 dec   d_model 128, 4 heads, 2 enc + 2 dec
                   layers, ff 1024, dropout 0.1          layers, ff 256, dropout 0
decoder MLPs       hidden 512; time-dependent 4 layers,  hidden 128; time-dependent 3 layers,
                   segment 2 hidden layers               segment 2 hidden layers
PointNet           3 -> 64 -> 128 -> 256, pool, -> 256  3 -> 32 -> 64, pool, -> 128
parameters         16,482,560: motion encoder            1,465,216: motion encoder 696,448,
                   7,539,200, decoder 1,394,304,         decoder 85,888, init encoder 682,880
                   init encoder 7,549,056
=================  ====================================  ===================================

Only m, D, the 20 joints, 8 betas and n = 100 come from the paper; the rest is our choice. The
embedded decoder is small because it runs B * m * n = 12,800 times per training step (its cost
dominates a step on a CPU).

Training (paper 4.4, 5.1) and what differs here
-----------------------------------------------
L = L_global + L_segment + lambda_KL (1/m) sum_j KL_j + lambda_reg sum_j (delta_j - 1/m)^2 with
lambda_KL = 1e-4, lambda_reg = 0.01 (paper), KL summed over the D dims; L_global = mean over the
n frames of |theta - theta_GT|^2 (6D, summed over the 120 numbers) + |gamma - gamma_GT|^2
(normalised units) + lambda_3D |M - M_GT|^2; L_segment = (1/mn) sum_i sum_j G_j(tau_i)
(|rho_j theta_j - theta_GT|^2 + |rho_j gamma_j - gamma_GT|^2). We have no SMPL mesh in
training: M is replaced by the 22 joint positions from forward kinematics on the fixed rest
skeleton (:func:`priors.training.fixed_rest_skeleton`, feet identity in both) plus the translation
in metres, summed over joints and weighted by 6890 / 22 (``joint_weight``: each joint stands for
the ~313 SMPL vertices the paper's per-vertex sum counts). lambda_3D = 0 for the first half of the
steps, then rises linearly to 1 over 5 % of the steps (paper: 0 for 500 epochs, then 1 for 500; the
ramp is ours, see :func:`lambda_3d_schedule`). Windows of 3-5 s (90-150 frames at 30 fps) are cropped
at random from the synthetic train split (window starts every 10 frames), with n = 100 sorted random
timestamps per window (SLERP / LERP between the 30 fps frames). Adam, batch 16 (paper), but lr 1e-3
with a cosine decay to 1e-4 (:func:`priors.training.train_loop`) instead of the paper's 1e-4 with a
plateau schedule, to converge in minutes on one CPU core. Default 1,500 steps (``DEFAULT_STEPS``).

Initialisation encoder training (paper 5.5: "trained using pointcloud representations of the
AMASS sequences"): windows of 3-5 s observed at a random 5-10 fps (keep every 3rd..6th frame from
the window start, as table1 does), P points per frame (log-uniform in [100, 1000]; one window
length, rate and P per batch), on the embedded Anny body posed by the window with each sequence's
own shape. Cheaper stand-in for area-uniform surface sampling (``sample_surface`` over the full
mesh costs seconds per batch on a CPU): per batch a pool of ``2 * P`` vertices is drawn with
probability proportional to their rest-mesh area (1/3 of the incident triangles' area), only those
vertices are skinned (``body.skin(..., vertex_indices=pool)``), each frame keeps an independent
random P of them, and Gaussian noise of 5 mm is added. The target mu is the motion encoder's
posterior mean on all the window's 30 fps frames. Batch 8, Adam lr 1e-3 cosine to 1e-4, default 600
steps (``DEFAULT_POINT_STEPS``).

Cost (one torch thread, CPU time measured on a heavily shared 2-core machine): ~0.4 s per VAE step
(batch 16, n = 100) and ~0.37 s per initialisation-encoder step, so the defaults take about
10 + 4 min (``python -m priors.latent_primitives --out priors/weights`` or
``python -m benchmark train sequential-primitives``; record in ``sequential_primitives.json``).

Checkpoint format
-----------------
``priors/weights/sequential_primitives.pt``: ``{"state_dict": {...}, "config": {...}}``
(:func:`priors.training.save_checkpoint`); the config holds the sizes above plus
``trans_center`` / ``trans_scale`` (3 each, metres) and ``shape_mean`` (S); the state dict's
buffers hold the same numbers. A JSON training record sits beside it. The official code
(gitlab.inria.fr/mmarsot/new_segmentation, research-only licence) and any official weights are
not reachable from here: ``size="paper"`` refuses a checkpoint that is not in this project's
format, naming the module names an official-key mapping would have to fill
(:data:`OFFICIAL_MAPPING_NEEDS`).

Adapter notes
-------------
Latents: ``{"z": (B, 8, D)}`` from the initialisation encoder. The prior term is
``sum |z - z_init|^2`` (B,) (paper Eq. 9, L_prior "close to its initialisation"). Every tensor in
the latents dict is optimised by the protocol and the conformance kit requires a non-zero
gradient on each, so z_init and the window duration are kept on the adapter
(``init_latents`` / ``encode_motion`` set them): an adapter instance serves one batch at a time, in
the order init_latents -> decode/prior_term (the protocol's order); prior_term raises if the
latents do not match the stored batch. ``decode`` scales timestamps by that window duration
(4.0 s if none was set).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import fields as dc_fields
from pathlib import Path

import roma
import torch
import torch.nn.functional as F
from torch import nn

from benchmark.body.lbs import forward_kinematics
from benchmark.rotations import matrix_to_sixd, slerp_matrices
from benchmark.skeleton import NUM_JOINTS
from priors.base import Decoded, ExportSpec, FitBatch, PriorAdapter, WindowSpec

log = logging.getLogger(__name__)

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
DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "sequential_primitives.pt"
DEFAULT_WINDOW_S = 4.0  # decode's time scale when no batch set one (table1's window)

LAMBDA_KL, LAMBDA_REG, LAMBDA_3D = 1e-4, 0.01, 1.0
JOINT_WEIGHT = SMPL_VERTICES / NUM_JOINTS
TRAIN_FPS = 30.0
WINDOW_FRAMES = (90, 150)  # 3-5 s at 30 fps
TRAIN_SAMPLES = 100  # n timestamps per training window
OBS_STRIDES = (3, 4, 5, 6)  # 10, 7.5, 6, 5 fps from 30 fps
OBS_POINTS = (100, 1000)
POINT_NOISE_M = 0.005
DEFAULT_STEPS = 1500  # motion VAE
DEFAULT_POINT_STEPS = 600  # initialisation encoder

NOT_PUBLIC = (
    "the official sequential-primitives code (gitlab.inria.fr/mmarsot/new_segmentation, research-only licence) and "
    "any official weights are not public/reachable from this project, so their checkpoint format is unknown"
)
OFFICIAL_MAPPING_NEEDS = (
    "motion_encoder.embed (Linear 123 -> d_model: per-frame perceptron on [20 joints 6D, gamma]), "
    "motion_encoder.core.encoder / .core.decoder / .core.queries (transformer over frames, m query tokens), "
    "motion_encoder.head (d_model -> 2D: mu, logvar), "
    "decoder.seg_mlp (time-independent MLP [z, beta] -> duration logit, yaw (cos, sin), t_x, t_z), "
    "decoder.in_z / decoder.in_t / decoder.body (time-dependent MLP [z, beta, f(tau - Delta)] -> 20x6D + gamma), "
    "decoder.trans_center / decoder.trans_scale (translation normalisation, metres), "
    "point_encoder.pointnet.mlp / .pointnet.out / .core / .head (initialisation encoder)"
)


# -- small tensor helpers -----------------------------------------------------------------------
def _identity6(dtype=torch.float32, device=None) -> torch.Tensor:
    return torch.eye(3, dtype=dtype, device=device)[:2].reshape(6)  # [1, 0, 0, 0, 1, 0]: columns of I


def gram_schmidt(x: torch.Tensor) -> torch.Tensor:
    """(..., 6) "columns" 6D -> (..., 3, 3); explicit ops only (ONNX-traceable, no linalg.cross)."""
    a1, a2 = x[..., 0:3], x[..., 3:6]
    b1 = a1 / a1.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    b2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = b2 / b2.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    b3 = torch.stack([
        b1[..., 1] * b2[..., 2] - b1[..., 2] * b2[..., 1],
        b1[..., 2] * b2[..., 0] - b1[..., 0] * b2[..., 2],
        b1[..., 0] * b2[..., 1] - b1[..., 1] * b2[..., 0],
    ], dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


def yaw_matrix(yaw: torch.Tensor) -> torch.Tensor:
    """(...,) angle about +y -> (..., 3, 3) (x' = cos x + sin z, z' = -sin x + cos z)."""
    c, s = torch.cos(yaw), torch.sin(yaw)
    o, z = torch.ones_like(c), torch.zeros_like(c)
    return torch.stack([c, z, s, z, o, z, -s, z, c], dim=-1).unflatten(-1, (3, 3))


def root_heading(R_root: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) root rotations -> (...) yaw of the body's +z axis projected on the ground."""
    f = R_root[..., :, 2]
    return torch.atan2(f[..., 0], f[..., 2])


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
    Y = yaw_matrix(-yaw)  # (B, 3, 3)
    root = Y[:, None] @ R[:, :, 0]
    R = torch.cat([root[:, :, None], R[:, :, 1:]], dim=2)
    trans = ((trans - mean[:, None]) @ Y.transpose(-1, -2))
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


# -- the loss -----------------------------------------------------------------------------------
def primitives_loss(net: SequentialPrimitives, R: torch.Tensor, trans: torch.Tensor, tau: torch.Tensor,
                    shape: torch.Tensor, rest_joints: torch.Tensor, lambda_3d: float,
                    sample: bool = True) -> dict:
    """Eqs. 3-8 for canonical-frame windows: R (B, n, 22, 3, 3) (feet identity), trans (B, n, 3) m,
    tau (B, n), shape (B, S). Returns {"loss", "global", "segment", "kl", "reg", "pose", "trans",
    "joints" (unweighted mean over frames of the summed squared joint errors, m^2)}."""
    mu, logvar = net.encode(R, trans, tau)
    z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar) if sample else mu
    out = net.decoder(z, shape, tau, with_segments=True)
    m = z.shape[1]
    gt_six = matrix_to_sixd(R[:, :, list(MODEL_JOINTS)], "columns")  # (B, n, 20, 6)
    gt_g = (trans - net.decoder.trans_center) / net.decoder.trans_scale
    pose = (out["sixd"] - gt_six).square().sum((-1, -2)).mean()
    tr = (out["gamma"] - gt_g).square().sum(-1).mean()
    _, j_pred = forward_kinematics(out["rotations"], rest_joints)
    _, j_gt = forward_kinematics(R, rest_joints)
    joints = ((j_pred + out["trans"][..., None, :]) - (j_gt + trans[..., None, :])).square().sum((-1, -2)).mean()
    L_global = pose + tr + lambda_3d * JOINT_WEIGHT * joints
    G = out["masks"]  # (B, m, n)
    seg_pose = (out["seg_sixd"] - gt_six[:, None]).square().sum((-1, -2))
    seg_tr = (out["seg_gamma"] - gt_g[:, None]).square().sum(-1)
    L_segment = (G * (seg_pose + seg_tr)).sum(1).mean() / m
    kl = (0.5 * (mu.square() + logvar.exp() - 1.0 - logvar)).sum(-1).mean()  # (1/m) sum_j, mean over batch
    reg = (out["delta"] - 1.0 / m).square().sum(-1).mean()
    loss = L_global + L_segment + LAMBDA_KL * kl + LAMBDA_REG * reg
    return {"loss": loss, "global": L_global, "segment": L_segment, "kl": kl, "reg": reg, "pose": pose,
            "trans": tr, "joints": joints}


# -- checkpoints --------------------------------------------------------------------------------
def read_checkpoint(file: str | Path) -> dict:
    """The project checkpoint ``{"state_dict", "config"}``; clear errors for anything else."""
    file = Path(file)
    if not file.exists():
        raise FileNotFoundError(f"sequential-primitives weights not found: {file}")
    try:
        ckpt = torch.load(file, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise ValueError(
            f"{file}: not readable as a sequential-primitives project checkpoint ({type(exc).__name__}: "
            f"{str(exc).splitlines()[0] if str(exc) else ''}); {NOT_PUBLIC}. A loader for official weights would "
            f"have to map their keys onto: {OFFICIAL_MAPPING_NEEDS}"
        ) from exc
    cfg = ckpt.get("config") if isinstance(ckpt, dict) else None
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), dict) or not isinstance(cfg, dict) \
            or cfg.get("format") != FORMAT:
        found = sorted(ckpt)[:20] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(
            f"{file}: not a sequential-primitives project checkpoint (expected a dict with 'state_dict' and a "
            f"'config' whose 'format' is {FORMAT!r}; found top-level {found}). {NOT_PUBLIC}: pass a checkpoint "
            "written by priors.latent_primitives.train_sequential_primitives, or write a key mapping from the "
            f"official files onto: {OFFICIAL_MAPPING_NEEDS}"
        )
    missing = [k for k in ARCH_KEYS if k not in cfg]
    if missing:
        raise ValueError(f"{file}: field 'config' lacks {missing}; retrain with train_sequential_primitives")
    return ckpt


def load_into(net: SequentialPrimitives, ckpt: dict, file: str | Path) -> None:
    """Strict load: every key with the network's shape; extra keys are an error too."""
    sd = ckpt["state_dict"]
    expected = net.state_dict()
    for k, v in expected.items():
        if k not in sd:
            raise KeyError(f"{file}: missing key {k!r} (shape {tuple(v.shape)}); the checkpoint must hold all "
                           f"{len(expected)} entries of SequentialPrimitives")
        if tuple(sd[k].shape) != tuple(v.shape):
            raise ValueError(f"{file}: key {k!r} has shape {tuple(sd[k].shape)}, expected {tuple(v.shape)} for config "
                             f"{ {a: net.cfg[a] for a in ('latent', 'd_model', 'mlp_hidden', 'shape_dim')} }")
    extra = sorted(set(sd) - set(expected))
    if extra:
        raise KeyError(f"{file}: unexpected keys {extra[:10]} (not SequentialPrimitives entries)")
    net.load_state_dict(sd, strict=True)


def network_from_checkpoint(file: str | Path) -> SequentialPrimitives:
    ckpt = read_checkpoint(file)
    net = SequentialPrimitives(**{k: ckpt["config"][k] for k in ARCH_KEYS})
    load_into(net, ckpt, file)
    return net


# -- export ------------------------------------------------------------------------------------
class DecoderExport(nn.Module):
    """(z (B, m, D), shape (B, S), tau (B, T) normalised time) -> (rotations (B, T, 22, 3, 3), trans (B, T, 3))."""

    def __init__(self, decoder: PrimitiveDecoder):
        super().__init__()
        self.decoder = decoder

    def forward(self, z: torch.Tensor, shape: torch.Tensor, tau: torch.Tensor):
        out = self.decoder(z, shape, tau)
        return out["rotations"], out["trans"]


# -- the adapter --------------------------------------------------------------------------------
class SequentialPrimitivesPrior(PriorAdapter):
    """Sequential latent primitives (Marsot et al. 2022) as a continuous-time prior (module docstring).

    Latents ``{"z": (B, 8, D)}`` from the PointNet initialisation encoder; decode at any timestamps;
    prior term ``sum |z - z_init|^2``. The decoder outputs a canonical heading and zero-mean
    translation: the protocol frees a heading and an offset.
    """

    name = "sequential-primitives"
    paper = "Marsot, Wuhrer, Franco, Olivier 2022, Representing motion as a sequence of latent primitives (hal-03715820)"
    window = WindowSpec(kind="continuous")
    encodes_translation = True
    encodes_root_orientation = True
    heading_normalised = True
    joints = MODEL_JOINTS
    shape_conditioned = True
    has_encoder = True
    sixd_layout = "columns"

    def __init__(self, size: str = "embedded", weights: str | None = None, device: str | torch.device = "cpu"):
        super().__init__(size=size, weights=weights, device=device)
        if size == "paper":
            if weights is None:
                raise ValueError(
                    f"sequential-primitives size 'paper' needs weights, but {NOT_PUBLIC}. Use size='embedded' "
                    "(python -m benchmark train sequential-primitives), or pass a paper-size checkpoint in this "
                    f"project's format; an official-weights loader would have to map onto: {OFFICIAL_MAPPING_NEEDS}"
                )
            ckpt = read_checkpoint(weights)
            arch = {k: ckpt["config"][k] for k in ARCH_KEYS}
            diff = {k: (arch[k], PAPER_CONFIG[k]) for k in ARCH_KEYS
                    if (list(arch[k]) if isinstance(arch[k], (list, tuple)) else arch[k]) != PAPER_CONFIG[k]}
            if diff:
                raise ValueError(f"{weights}: not a paper-size checkpoint; config differs (found, paper): {diff}")
            self.net = SequentialPrimitives(**arch)
            load_into(self.net, ckpt, weights)
            path = Path(weights)
        elif size == "embedded":
            path = Path(weights) if weights is not None else DEFAULT_WEIGHTS
            if not path.exists():
                raise FileNotFoundError(
                    f"embedded sequential-primitives weights not found: {path}. Train them with "
                    "`python -m benchmark train sequential-primitives` (or "
                    "`python -m priors.latent_primitives --out priors/weights`)."
                )
            self.net = network_from_checkpoint(path)
        else:
            raise ValueError(f"sequential-primitives: unknown size {size!r}; expected 'embedded' or 'paper'")
        self.weights_path = str(path)
        for p in self.net.parameters():
            p.requires_grad_(False)
        self.to(device)
        self.net.eval()
        self._z_init: torch.Tensor | None = None
        self._window_s: float = DEFAULT_WINDOW_S
        self._warned_shape = False

    # -- plumbing
    @property
    def device(self) -> torch.device:
        return next(self.net.parameters()).device

    def train(self, mode: bool = True):
        super().train(mode)
        self.net.eval()
        return self

    @classmethod
    def paper_network(cls) -> nn.Module:
        """The paper-size network (D = 256, m = 8, 8 betas) with random weights."""
        return SequentialPrimitives(**PAPER_CONFIG)

    def _shape(self, shape: torch.Tensor | None, B: int) -> torch.Tensor:
        S = self.net.shape_dim
        mean = self.net.decoder.shape_mean
        if shape is None:
            return mean.expand(B, S)
        shape = shape.to(self.device, mean.dtype)
        if shape.dim() != 2 or shape.shape[0] != B:
            raise ValueError(f"sequential-primitives: shape must be (B, {S}) = ({B}, {S}), got {tuple(shape.shape)}")
        if shape.shape[1] != S:
            if not self._warned_shape:
                log.warning("sequential-primitives: the body's shape vector has %d entries but the prior was trained "
                            "on %d-entry shapes; its decoder is conditioned on the training-mean shape instead "
                            "(the body's own shape still shapes the mesh)", shape.shape[1], S)
                self._warned_shape = True
            return mean.expand(B, S)
        return shape

    # -- the three adapter functions
    @torch.no_grad()
    def init_latents(self, batch: FitBatch, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """``{"z": (B, 8, D)}``: the initialisation encoder on the observed point clouds (deterministic;
        ``generator`` is unused). Stores z_init and the window duration for prior_term / decode."""
        window_s = float(batch.window_s)
        if not window_s > 0:
            raise ValueError(f"sequential-primitives: FitBatch.window_s must be > 0 seconds, got {batch.window_s}")
        dev = self.device
        pts = batch.points.to(dev, torch.float32)
        tau = batch.timestamps.to(dev, torch.float64).div(window_s).to(torch.float32)
        z = self.net.point_encoder(pts, batch.lengths.to(dev), tau)
        self._z_init = z.detach().clone()
        self._window_s = window_s
        return {"z": z}

    def decode(self, latents: dict[str, torch.Tensor], timestamps: torch.Tensor, shape: torch.Tensor | None = None) -> Decoded:
        """z (B, 8, D) at timestamps (B, T) seconds from the window start -> rotations (B, T, 22, 3, 3)
        (feet identity) and trans (B, T, 3) in the canonical frame; latents "heading" (B, 1) /
        "offset" (B, 3), when present (from encode_motion), are applied on top."""
        z = latents["z"]
        m, D = self.net.primitives, self.net.latent
        if z.dim() != 3 or z.shape[1:] != (m, D):
            raise ValueError(f"sequential-primitives: latents['z'] must be (B, {m}, {D}), got {tuple(z.shape)}")
        if timestamps.dim() != 2 or timestamps.shape[0] != z.shape[0]:
            raise ValueError(f"sequential-primitives: timestamps must be (B, T) with B = {z.shape[0]}, got {tuple(timestamps.shape)}")
        tau = (timestamps.to(z.device, torch.float64) / self._window_s).to(z.dtype)
        out = self.net.decoder(z, self._shape(shape, z.shape[0]), tau)
        rot, trans = out["rotations"], out["trans"]
        if "heading" in latents:
            H = yaw_matrix(latents["heading"][:, 0])[:, None]  # (B, 1, 3, 3)
            rot = torch.cat([(H[:, :, None] @ rot[:, :, :1]), rot[:, :, 1:]], dim=2)
            trans = (H @ trans[..., None])[..., 0]
        if "offset" in latents:
            trans = trans + latents["offset"][:, None]
        return Decoded(rotations=rot, trans=trans)

    def prior_term(self, latents: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B,) sum over primitives and dims of |z - z_init|^2 (paper Eq. 9's L_prior)."""
        z = latents["z"]
        if self._z_init is None or self._z_init.shape != z.shape:
            have = None if self._z_init is None else tuple(self._z_init.shape)
            raise ValueError(
                f"sequential-primitives: prior_term needs the initial latents of this batch (have {have}, latents "
                f"{tuple(z.shape)}): call init_latents (or encode_motion) for the batch first; one adapter serves "
                "one batch at a time"
            )
        return (z - self._z_init.to(z)).square().sum((1, 2))

    @torch.no_grad()
    def encode_motion(self, rotations: torch.Tensor, trans: torch.Tensor, timestamps: torch.Tensor) -> dict[str, torch.Tensor]:
        """Posterior means of whole motions: ``{"z": (B, 8, D), "heading": (B, 1), "offset": (B, 3)}``.

        rotations (B, T, 22, 3, 3), trans (B, T, 3), timestamps (B, T) s. The window duration is
        t_last + the median frame interval (120 frames at 30 fps -> 4 s) and is stored, with z as
        z_init. heading/offset map the canonical frame back to the input's, so decode reproduces
        the input's world placement.
        """
        if rotations.dim() != 5 or rotations.shape[2:] != (NUM_JOINTS, 3, 3):
            raise ValueError(f"encode_motion: rotations must be (B, T, 22, 3, 3), got {tuple(rotations.shape)}")
        B, T = rotations.shape[:2]
        if trans.shape != (B, T, 3) or timestamps.shape != (B, T):
            raise ValueError(f"encode_motion: trans must be {(B, T, 3)} and timestamps {(B, T)}, got "
                             f"{tuple(trans.shape)}, {tuple(timestamps.shape)}")
        dev = self.device
        ts = timestamps.to(dev, torch.float64)
        dt = (ts[:, 1:] - ts[:, :-1]).median() if T > 1 else torch.tensor(1.0 / TRAIN_FPS, dtype=torch.float64)
        window_s = float(ts[:, -1].max() + dt)
        R = insert_feet(rotations.to(dev, torch.float32)[:, :, list(MODEL_JOINTS)])
        Rc, tc, yaw, mean = canonicalise(R, trans.to(dev, torch.float32))
        tau = (ts / window_s).to(torch.float32)
        mu, _ = self.net.encode(Rc, tc, tau)
        self._z_init = mu.clone()
        self._window_s = window_s
        return {"z": mu, "heading": yaw[:, None], "offset": mean}

    def export_decoder(self) -> ExportSpec:
        """(z (B, 8, D), shape (B, S), tau (B, T) = seconds / window_s) -> (rotations, trans) canonical frame."""
        module = DecoderExport(self.net.decoder).eval()
        g = torch.Generator().manual_seed(0)
        B, T = 2, 16
        z = torch.randn(B, self.net.primitives, self.net.latent, generator=g)
        shape = torch.rand(B, self.net.shape_dim, generator=g)
        tau = torch.linspace(0.0, 1.0, T).expand(B, T).contiguous()
        dev = self.device
        return ExportSpec(module=module, example_inputs=(z.to(dev), shape.to(dev), tau.to(dev)),
                          input_names=["z", "shape", "tau"], output_names=["rotations", "trans"])

    @classmethod
    def train_embedded(cls, out_dir=None, steps=None, seed: int = 0, overwrite: bool = False) -> dict:
        """``python -m benchmark train sequential-primitives``: the embedded weights (see
        :func:`train_sequential_primitives`). ``steps`` sets the motion-VAE steps; the initialisation
        encoder gets steps * DEFAULT_POINT_STEPS / DEFAULT_STEPS."""
        out = Path(out_dir) if out_dir is not None else DEFAULT_WEIGHTS.parent
        target = out / DEFAULT_WEIGHTS.name
        if target.exists() and not overwrite:
            raise FileExistsError(f"{target} exists: pass --force to overwrite it, or --out DIR to write elsewhere")
        kw = {}
        if steps:
            kw = {"steps": int(steps), "point_steps": max(1, round(int(steps) * DEFAULT_POINT_STEPS / DEFAULT_STEPS))}
        _, record = train_sequential_primitives(out, seed=seed, **kw)
        return record


# -- training data ------------------------------------------------------------------------------
class WindowBank:
    """Frames of many motions in one tensor, and the starts of the windows that fit in them.

    frames (M, 69 + S): [axis-angle 22 x 3, trans 3, shape S] per 30 fps frame; starts (N,) long:
    frame indices where a window of ``max_frames`` frames lies inside one motion.
    """

    def __init__(self, frames: torch.Tensor, starts: torch.Tensor, max_frames: int, min_frames: int):
        self.frames, self.starts = frames, starts.long()
        self.max_frames, self.min_frames = int(max_frames), int(min_frames)
        if self.starts.numel() < 2:
            raise ValueError(f"need at least 2 training windows of {max_frames} frames, got {self.starts.numel()}")

    @classmethod
    def from_motions(cls, motions, shape_dim: int, stride: int = 10, frames=WINDOW_FRAMES, fps=TRAIN_FPS):
        lo, hi = frames
        chunks, starts, pos = [], [], 0
        for i, m in enumerate(motions):
            if abs(m.fps - fps) > 1e-6:
                m = m.resample_fps(fps)
            T = m.poses.shape[0]
            s = getattr(m, "shape", None)
            if s is None or torch.as_tensor(s).numel() == 0:
                s = torch.full((shape_dim,), 0.5)
            s = torch.as_tensor(s, dtype=torch.float32).reshape(-1)
            if s.numel() != shape_dim:
                raise ValueError(f"motion {i} ({getattr(m, 'name', '?')}): shape vector of size {s.numel()}, the "
                                 f"network takes shape_dim = {shape_dim}")
            x = torch.cat([torch.as_tensor(m.poses, dtype=torch.float32).reshape(T, -1),
                           torch.as_tensor(m.trans, dtype=torch.float32), s.expand(T, -1)], dim=1)
            chunks.append(x)
            if T >= hi:
                starts.append(pos + torch.arange(0, T - hi + 1, stride))
            pos += T
        if not starts:
            raise ValueError(f"no motion has {hi} frames at {fps} fps")
        return cls(torch.cat(chunks), torch.cat(starts), hi, lo)

    @classmethod
    def from_windows(cls, windows: torch.Tensor, shapes: torch.Tensor | None, shape_dim: int, frames=WINDOW_FRAMES):
        """windows (N, F, 69) as :func:`priors.training.motion_windows` gives; shapes (N, S) or None (0.5)."""
        windows = torch.as_tensor(windows, dtype=torch.float32)
        if windows.dim() != 3 or windows.shape[-1] != NUM_JOINTS * 3 + 3:
            raise ValueError(f"windows must be (N, F, 69) [axis-angle 66, trans 3], got {tuple(windows.shape)}")
        N, Fw = windows.shape[:2]
        if shapes is None:
            shapes = torch.full((N, shape_dim), 0.5)
        shapes = torch.as_tensor(shapes, dtype=torch.float32)
        if shapes.shape != (N, shape_dim):
            raise ValueError(f"window shapes must be (N, {shape_dim}) = ({N}, {shape_dim}), got {tuple(shapes.shape)}")
        hi = min(frames[1], Fw)
        lo = min(frames[0], hi)
        x = torch.cat([windows, shapes[:, None].expand(-1, Fw, -1)], dim=-1).reshape(N * Fw, -1)
        return cls(x, torch.arange(N) * Fw, hi, lo)

    def crop(self, starts: torch.Tensor, lengths: torch.Tensor, g: torch.Generator):
        """Random crops: (R (B, L, 22, 3, 3) feet identity, trans (B, L, 3), mask (B, L), shape (B, S)),
        L = max_frames, frames past each crop's length repeat its last frame; canonicalised."""
        B, L = starts.shape[0], self.max_frames
        off = (torch.rand(B, generator=g) * (L - lengths + 1).float()).long().clamp(max=L - 1)
        k = torch.arange(L)
        idx = starts[:, None] + off[:, None] + torch.minimum(k[None], lengths[:, None] - 1)
        x = self.frames[idx]  # (B, L, 69 + S)
        aa = x[..., : NUM_JOINTS * 3].unflatten(-1, (NUM_JOINTS, 3))
        R = roma.rotvec_to_rotmat(aa)
        R = insert_feet(R[:, :, list(MODEL_JOINTS)])
        mask = k[None] < lengths[:, None]
        Rc, tc, _, _ = canonicalise(R, x[..., NUM_JOINTS * 3: NUM_JOINTS * 3 + 3], mask)
        return Rc, tc, mask, x[:, 0, NUM_JOINTS * 3 + 3:]

    def random_lengths(self, B: int, g: torch.Generator) -> torch.Tensor:
        return torch.randint(self.min_frames, self.max_frames + 1, (B,), generator=g)

    def sample(self, starts: torch.Tensor, g: torch.Generator, n: int = TRAIN_SAMPLES):
        """Training samples: n sorted random timestamps per random 3-5 s crop, SLERP/LERP between frames.
        Returns R (B, n, 22, 3, 3), trans (B, n, 3), tau (B, n) in [0, 1), shape (B, S)."""
        lengths = self.random_lengths(starts.shape[0], g)
        R, tr, _, shape = self.crop(starts, lengths, g)
        t = torch.rand(starts.shape[0], n, generator=g).sort(-1).values * (lengths[:, None] - 1).float()
        k0 = t.floor().long().clamp(max=(lengths[:, None] - 2).clamp_min(0))
        w = (t - k0.float()).clamp(0, 1)
        k1 = torch.minimum(k0 + 1, lengths[:, None] - 1)
        b = torch.arange(starts.shape[0])[:, None]
        Rt = slerp_matrices(R[b, k0], R[b, k1], w[..., None])
        trt = tr[b, k0] + w[..., None] * (tr[b, k1] - tr[b, k0])
        return Rt, trt, t / lengths[:, None].float(), shape

    def trans_stats(self, stride: int = 5):
        """Per-axis (center, half-range) of canonical translation over full-length windows."""
        lo, hi = None, None
        starts = self.starts[::stride]
        for i in range(0, starts.numel(), 512):
            s = starts[i: i + 512]
            _, tc, _, _ = self.crop(s, torch.full_like(s, self.max_frames), torch.Generator().manual_seed(0))
            a, b = tc.amin((0, 1)), tc.amax((0, 1))
            lo = a if lo is None else torch.minimum(lo, a)
            hi = b if hi is None else torch.maximum(hi, b)
        return (hi + lo) / 2, ((hi - lo) / 2).clamp_min(1e-2)

    def shape_mean(self) -> torch.Tensor:
        return self.frames[self.starts][:, NUM_JOINTS * 3 + 3:].mean(0)


def _vertex_areas(body) -> torch.Tensor:
    """(V,) rest-mesh (default shape) area per vertex (1/3 of the incident triangles' area)."""
    with torch.no_grad():
        rest = body.prepare(body.default_shape(1))
        eye = torch.eye(3).expand(1, 1, NUM_JOINTS, 3, 3)
        v = body.skin(rest, eye, torch.zeros(1, 1, 3)).vertices[0, 0]
        f = body.faces.long()
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        area = torch.linalg.cross(b - a, c - a).norm(dim=-1) / 2
        out = torch.zeros(v.shape[0])
        for k in range(3):
            out.index_add_(0, f[:, k], area / 3)
    return out


class PointCloudMaker:
    """Point clouds of canonical windows on the body (the documented cheap stand-in for surface sampling)."""

    def __init__(self, body, bank: WindowBank):
        self.body = body
        self.areas = _vertex_areas(body)
        shapes = bank.frames[bank.starts][:, NUM_JOINTS * 3 + 3:]
        self.unique, self.inverse = torch.unique(shapes, dim=0, return_inverse=True)
        self.shape_of_start = dict(zip(bank.starts.tolist(), self.inverse.tolist()))
        with torch.no_grad():
            self.rests = [body.prepare(s[None]) for s in self.unique]

    def _rest(self, ids: torch.Tensor):
        first = self.rests[0]
        out = {}
        for f in dc_fields(first):
            vals = [getattr(self.rests[i], f.name) for i in ids.tolist()]
            if torch.is_tensor(vals[0]):
                out[f.name] = torch.cat(vals)
            elif isinstance(vals[0], dict):
                out[f.name] = {k: (torch.cat([v[k] for v in vals]) if torch.is_tensor(vals[0][k]) else vals[0][k]) for k in vals[0]}
            else:
                out[f.name] = vals[0]
        return type(first)(**out)

    @torch.no_grad()
    def make(self, starts, R, trans, points: int, g: torch.Generator):
        """R (B, T, 22, 3, 3), trans (B, T, 3) canonical -> points (B, T, P, 3) under a random yaw."""
        B, T = R.shape[:2]
        ids = torch.tensor([self.shape_of_start.get(int(s), 0) for s in starts])
        yaw = torch.rand(B, generator=g) * 2 * math.pi
        Y = yaw_matrix(yaw)[:, None]
        R = torch.cat([Y[:, :, None] @ R[:, :, :1], R[:, :, 1:]], dim=2)
        trans = (Y @ trans[..., None])[..., 0]
        pool = torch.multinomial(self.areas, min(2 * points, self.areas.numel()), replacement=False, generator=g)
        verts = self.body.skin(self._rest(ids), R, trans, vertex_indices=pool).vertices  # (B, T, K, 3)
        pick = torch.rand(B, T, pool.numel(), generator=g).argsort(-1)[..., :points]
        pts = verts.gather(2, pick[..., None].expand(-1, -1, -1, 3))
        return pts + POINT_NOISE_M * torch.randn(pts.shape, generator=g)


# -- training -----------------------------------------------------------------------------------
LAMBDA_3D_RAMP = 0.05  # fraction of the steps over which lambda_3D rises from 0 to 1 after the first half


def lambda_3d_schedule(step: int, steps: int) -> float:
    """0 for steps 1..steps//2 (paper: lambda_3D = 0 for the first phase), then a linear rise to 1
    over LAMBDA_3D_RAMP * steps steps (ours: the joint term is ~1000x the first-phase loss, and a
    jump would make Adam's first updates ~10x too large while its second moment catches up)."""
    half = steps // 2
    if step <= half:
        return 0.0
    ramp = max(1.0, LAMBDA_3D_RAMP * steps)
    return min(1.0, (step - half) / ramp)


def train_sequential_primitives(
    out_dir: str | Path | None = None,
    steps: int = DEFAULT_STEPS,
    point_steps: int = DEFAULT_POINT_STEPS,
    seed: int = 0,
    *,
    config: dict | None = None,
    motions: list | None = None,
    val_motions: list | None = None,
    windows: torch.Tensor | None = None,
    window_shapes: torch.Tensor | None = None,
    val_windows: torch.Tensor | None = None,
    val_window_shapes: torch.Tensor | None = None,
    body=None,
    rest_joints: torch.Tensor | None = None,
    batch_size: int = 16,
    point_batch_size: int = 8,
    lr: float = 1e-3,
    log_every: int = 100,
    max_val_windows: int = 256,
) -> tuple[SequentialPrimitives, dict]:
    """Train the motion VAE (``steps``) then the initialisation encoder (``point_steps``); write
    ``sequential_primitives.pt`` + ``.json`` into ``out_dir`` (None writes nothing).

    Data: by default the synthetic train / val splits; or ``motions`` / ``val_motions`` (Motion
    lists); or ``windows`` (N, F, 69) (+ ``window_shapes`` (N, S)) for tests (crops of
    min(90, F)..min(150, F) frames). ``body``: the body that poses the initialisation encoder's point
    clouds (default: the embedded Anny body; only built when point_steps > 0). ``rest_joints``
    (22, 3): the FK skeleton of the 3D term (default :func:`priors.training.fixed_rest_skeleton`).
    Returns (network in eval mode, training record).
    """
    from priors import training

    cfg = dict(EMBEDDED_CONFIG if config is None else config)
    S = int(cfg["shape_dim"])
    data_info: dict = {}
    if windows is not None:
        bank = WindowBank.from_windows(windows, window_shapes, S)
        data_info["train"] = {"source": "windows given", "windows": int(bank.starts.numel())}
        val_bank = WindowBank.from_windows(val_windows, val_window_shapes, S) if val_windows is not None else None
    else:
        if motions is None:
            motions = training.load_split_motions("train")
            data_info["train"] = {"source": "benchmark.synthetic.splits.build_split('train')"}
            if val_motions is None:
                try:
                    val_motions = training.load_split_motions("val")
                    data_info["val"] = {"source": "benchmark.synthetic.splits.build_split('val')"}
                except Exception as exc:
                    log.warning("no validation split (%s); training without a validation loss", exc)
                    data_info["val"] = {"source": None, "error": f"{type(exc).__name__}: {exc}"}
        bank = WindowBank.from_motions(motions, S)
        data_info.setdefault("train", {"source": "motions given"})
        data_info["train"].update(motions=len(motions), windows=int(bank.starts.numel()), window_stride_frames=10)
        val_bank = WindowBank.from_motions(val_motions, S, stride=30) if val_motions else None
        if val_bank is not None:
            data_info.setdefault("val", {"source": "motions given"})
            data_info["val"].update(motions=len(val_motions), windows=int(val_bank.starts.numel()))
    if rest_joints is None:
        rest_joints, rest_source = training.fixed_rest_skeleton()
    else:
        rest_source = "given"
    rest_joints = torch.as_tensor(rest_joints, dtype=torch.float32)

    training.seed_everything(seed)
    net = SequentialPrimitives(**cfg)
    center, scale = bank.trans_stats()
    net.set_normalisation(center, scale, bank.shape_mean())
    val_starts = None
    if val_bank is not None:
        gv = torch.Generator().manual_seed(seed + 7)
        val_starts = val_bank.starts[torch.randperm(val_bank.starts.numel(), generator=gv)[:max_val_windows]]

    # phase 1: the motion VAE --------------------------------------------------------------
    for p in net.point_encoder.parameters():
        p.requires_grad_(False)
    gen = torch.Generator().manual_seed(seed + 1)
    counter = {"step": 0}
    half = steps // 2

    def vae_loss(model, starts):
        if model.training and torch.is_grad_enabled():
            counter["step"] += 1
            src, g = bank, gen
        else:  # validation: fixed crops and timestamps, posterior means, lambda_3D on
            src, g = val_bank, torch.Generator().manual_seed(seed + 11)
        R, tr, tau, shape = src.sample(starts, g)
        lam = LAMBDA_3D * lambda_3d_schedule(counter["step"], steps) if model.training else LAMBDA_3D
        return primitives_loss(model, R, tr, tau, shape, rest_joints, lam, sample=model.training)

    t0 = time.perf_counter()
    res1 = training.train_loop(net, vae_loss, bank.starts, steps=steps, batch_size=batch_size, seed=seed, lr=lr,
                               final_lr_ratio=0.1, log_every=log_every, val_data=val_starts, val_batch=64)

    # phase 2: the initialisation encoder ---------------------------------------------------
    for p in net.parameters():
        p.requires_grad_(False)
    for p in net.point_encoder.parameters():
        p.requires_grad_(True)
    res2 = None
    if point_steps > 0:
        if body is None:
            from benchmark.body.anny_body import load_anny_body

            body = load_anny_body("cpu")
        if body.shape_dim != S:
            raise ValueError(f"body {body.name!r} takes {body.shape_dim} shape numbers, the network shape_dim is {S}")
        maker = PointCloudMaker(body, bank)
        val_maker = PointCloudMaker(body, val_bank) if val_bank is not None else None
        gen2 = torch.Generator().manual_seed(seed + 2)
        lo, hi = math.log(OBS_POINTS[0]), math.log(OBS_POINTS[1])

        def point_loss(model, starts):
            if model.training and torch.is_grad_enabled():
                src, mk, g = bank, maker, gen2
            else:
                src, mk, g = val_bank, val_maker, torch.Generator().manual_seed(seed + 12)
            B = starts.shape[0]
            L = int(torch.randint(src.min_frames, src.max_frames + 1, (1,), generator=g))
            stride = OBS_STRIDES[int(torch.randint(len(OBS_STRIDES), (1,), generator=g))]
            P = int(round(math.exp(lo + (hi - lo) * float(torch.rand(1, generator=g)))))
            R, tr, _, shape = src.crop(starts, torch.full((B,), L), g)
            R, tr = R[:, :L], tr[:, :L]
            tau_all = (torch.arange(L, dtype=torch.float32) / L).expand(B, L)
            with torch.no_grad():
                target, _ = model.encode(R, tr, tau_all)
            obs = torch.arange(0, L, stride)
            pts = mk.make(starts, R[:, obs], tr[:, obs], P, g)
            lengths = torch.full(pts.shape[:2], P, dtype=torch.long)
            pred = model.point_encoder(pts, lengths, tau_all[:, obs])
            mse = (pred - target).square().sum(-1).mean()
            return {"loss": mse, "latent_mse": mse, "target_norm2": target.square().sum(-1).mean()}

        res2 = training.train_loop(net, point_loss, bank.starts, steps=point_steps, batch_size=point_batch_size,
                                   seed=seed + 1, lr=lr, final_lr_ratio=0.1, log_every=log_every,
                                   val_data=val_starts[:64] if val_starts is not None else None, val_batch=16)
    wall = time.perf_counter() - t0
    for p in net.parameters():
        p.requires_grad_(False)
    net.eval()

    n_params = {k: sum(p.numel() for p in getattr(net, k).parameters())
                for k in ("motion_encoder", "decoder", "point_encoder")}
    record = {
        "prior": SequentialPrimitivesPrior.name,
        "network": "priors/latent_primitives.py SequentialPrimitives",
        "config": net.config,
        "parameters": sum(n_params.values()),
        "parameters_by_part": n_params,
        "data": data_info,
        "rest_skeleton": rest_source,
        "loss": (f"L_global (6D pose + normalised translation + lambda_3D*{JOINT_WEIGHT:.1f}*sum of squared FK joint "
                 f"errors, m^2) + L_segment + {LAMBDA_KL}*KL + {LAMBDA_REG}*sum(delta-1/m)^2; lambda_3D 0 for the "
                 f"first {half} steps, then a linear rise to {LAMBDA_3D} over {max(1, round(LAMBDA_3D_RAMP * steps))} steps"),
        "point_loss": "L2 between the initialisation encoder's output and the frozen motion encoder's mu",
        "optimiser": {"name": "Adam", "lr": lr, "schedule": "cosine to 0.1*lr", "batch_size": batch_size,
                      "point_batch_size": point_batch_size},
        "steps": steps,
        "point_steps": point_steps,
        "seed": seed,
        "torch_threads_training": 1,
        "train_wall_s": round(wall, 2),
        "vae_wall_s": round(res1.wall_s, 2),
        "point_wall_s": round(res2.wall_s, 2) if res2 else 0.0,
        "final_train": res1.final_train,
        "final_val": res1.final_val,
        "point_final_train": res2.final_train if res2 else None,
        "point_final_val": res2.final_val if res2 else None,
        "history": res1.history,
        "point_history": res2.history if res2 else [],
        **training.environment_record(),
    }
    if out_dir is not None:
        training.save_trained(out_dir, DEFAULT_WEIGHTS.name, net.state_dict(), net.config, record)
    return net, record


def main(argv: list[str] | None = None) -> None:
    """``python -m priors.latent_primitives --out priors/weights``: train the embedded weights."""
    import argparse

    ap = argparse.ArgumentParser(description="Train the embedded sequential-primitives prior on the synthetic split.")
    ap.add_argument("--out", default=str(DEFAULT_WEIGHTS.parent))
    ap.add_argument("--steps", type=int, default=DEFAULT_STEPS)
    ap.add_argument("--point-steps", type=int, default=DEFAULT_POINT_STEPS)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--force", action="store_true", help="overwrite existing weights")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    target = Path(args.out) / DEFAULT_WEIGHTS.name
    if target.exists() and not args.force:
        raise SystemExit(f"{target} exists: pass --force to overwrite it")
    _, rec = train_sequential_primitives(args.out, steps=args.steps, point_steps=args.point_steps, seed=args.seed)
    print({k: rec[k] for k in ("train_wall_s", "final_train", "final_val", "point_final_val", "checkpoint_bytes")})


__all__ = [
    "SequentialPrimitives", "MotionEncoder", "PointEncoder", "PrimitiveDecoder", "DecoderExport",
    "SequentialPrimitivesPrior", "primitives_loss", "train_sequential_primitives", "WindowBank",
    "PointCloudMaker", "read_checkpoint", "network_from_checkpoint", "canonicalise", "gram_schmidt",
    "PAPER_CONFIG", "EMBEDDED_CONFIG", "OFFICIAL_MAPPING_NEEDS",
]


if __name__ == "__main__":
    main()
