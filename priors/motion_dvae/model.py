"""Motion-DVAE (Fiche et al., "Motion-DVAE: Unsupervised learning for fast human motion denoising",
ACM MIG 2023, arXiv 2306.05846; paper 003 in /work/shared/seeds, reference: priors.md section 6).

The formulas of our copy of the paper were lost in conversion; everything below that the text does
not state is marked **[inferred]** and is this project's reconstruction.

State (paper section 3.1)
-------------------------
One 138-D state per frame **[inferred dimension]**::

    x_t = [ trans (3) | root orientation axis-angle (3) | 21 body joints axis-angle (63)
            | their velocities (finite differences x 30 fps, 69) ]

Velocities: ``(p_t - p_{t-1}) * fps``; frame 0 copies frame 1's **[inferred]**. Axis-angle sequences
are unwrapped in time (a rotation vector is replaced by its equivalent ``v - 2 pi v/|v|`` when that
is closer to the previous frame's) so that finite differences stay small **[inferred]**. The network
sees the state standardised with per-dimension training mean/std (buffers ``state_mean`` /
``state_std``) **[inferred]**. Every window is canonicalised like HuMoR (A.4): at its first frame
the translation is zeroed in the ground plane (x, z; the height y is kept) and the heading (yaw of
the root about the world y axis; the body faces +z) is removed; the same rigid transform is
applied to every frame.

Network (paper section 3.2, Appendix A.1-A.2)
---------------------------------------------
Generative model, x_0 given (a parameter)::

    p(x_{1:T}, z_{1:T} | x_0) = prod_t p(x_t | x_0, z_{1:t}) p(z_t | x_0, z_{1:t-1})

- One LSTM (``gen_rnn``, paper hidden 1024) shared by the prior and the decoder. It consumes
  ``u_t = [z_t, x^_0]`` (x^_0 = standardised x_0, repeated at every step) with ``z_0 = 0``, from a
  zero state: ``h_0`` summarises x_0 and ``h_t`` summarises (x_0, z_{1:t}) **[inferred]**.
- Prior head on the previous state: ``p(z_t | x_0, z_{1:t-1}) = N(prior_mean(h_{t-1}),
  exp(prior_logvar(h_{t-1})))`` (two MLPs).
- Decoder head on the current state and the latent: ``d_t = decoder([h_t, z_t])`` is the increment
  of the standardised state, ``mean(x^_t) = x^_0 + sum_{s<=t} d_s`` (a deterministic function of
  x_0 and z_{1:t}, so the factorisation above holds) **[inferred]**; the decoder's last layer starts
  at zero (the untrained model holds x_0). ``p(x_t | x_0, z_{1:t})`` is Gaussian with a learned
  per-dimension variance ``exp(dec_logvar)`` in standardised units **[inferred]** (a fixed unit
  variance let the KL term switch the latents off in our trials). x_t does not depend on past x
  given z: no scheduled sampling, and for given latents the whole generative pass is one LSTM call
  over the sequence (plus a running sum), which is what ``decode`` and the ONNX export run.
- MLPs follow HuMoR's pattern (``davrempe/humor: humor/models/humor_model.py`` class MLP): Linear,
  then [GroupNorm(16) -> ReLU -> Linear] x 2 (2 hidden layers). Hidden width 1024 in the paper size
  (HuMoR's width; the paper does not give it **[inferred]**).
- Inference ``q(z_t | x_0, z_{1:t-1}, x_{t:T})`` (D-separation): an anti-causal LSTM over the
  standardised states ``b_t = LSTM_bwd(x^_t, b_{t+1})`` (``encoder.bwd_rnn``) and a forward
  recurrence over z ``f_t = LSTMCell([z_t, x^_0], f_{t-1})``, ``f_0`` from ``[0, x^_0]``
  (``encoder.fwd_cell``), heads ``post_mean([f_{t-1}, b_t])`` and ``post_logvar([f_{t-1}, b_t])``
  **[inferred wiring]**; the encoder LSTMs have the generative LSTM's width.
- Latent z_t in R^48.

Loss (A.3), per frame, mean over the batch: ``1/2 sum_d [(x^_t,d - mean_d)^2 / var_d + log var_d]``
(standardised state) ``+ beta * KL(q(z_t) || p(z_t))`` (48 dims) ``+ POINT_WEIGHT * sum over body
points of the squared error`` (metres^2). Body points: the 22 forward-kinematics joints on a fixed
rest skeleton (``priors.training.fixed_rest_skeleton``) and 2 virtual markers per joint
(``MARKER_OFFSET`` m along the joint frame's x and z axes). We do not ship SMPL meshes: the markers
stand in for the paper's mesh term, the joints for its joint term. beta (KL annealing) rises
linearly from 0 to 1 over the first ``KL_ANNEAL_FRACTION`` of the steps (paper: the first 50 of 200
epochs).

Denoising (section 4, Appendix E)
---------------------------------
Prior and decoder frozen; trained (unsupervised, on noisy copies of the training windows: Gaussian
noise sigma ~ U[0.05, 0.25] rad on every joint's axis-angle, root included, translation clean;
see :func:`noisy_poses` for the one approximation):

- ``denoise_encoder``: a copy of the DVAE encoder, fine-tuned (the clean ``encoder`` stays, for
  ``encode_motion``);
- ``init_state``: initial-state predictor ``q(x_0 | y) = N(mu, sigma)``: an anti-causal LSTM over
  the noisy states + two MLP heads; ``mu`` is a residual on the noisy first positions/orientations
  while its velocities start from the data mean (noisy finite differences are far off the data)
  **[inferred]**;
- ``noise``: per-frame variance ``q(v_t | y) = InvGamma(alpha_t, beta_t)`` from an MLP on the
  denoising encoder's anti-causal features (the paper's noise predictor re-uses the encoder's LSTM
  and adds its own MLP; one variance per frame instead of per joint and axis: a simplification).

Objective (per window, per frame): ``sum_t [ 1/2 E[1/v_t] |y_t - y^_t|^2 + (P/2) E[log v_t] ] +
beta * sum_t KL_z + sum_t KL(InvGamma(alpha_t, beta_t) || InvGamma(a0, b0))``, y the body points of
the noisy input (joints + markers as above, P = 198 coordinates), y^ those of the decoded motion
(frame 0 from the sampled x_0), ``E[1/v] = alpha/beta``, ``E[log v] = log beta - digamma(alpha)``:
marginally a Student-t likelihood. Noise prior: shape ``a0 = NOISE_PRIOR_SHAPE`` (large: nearly
Gaussian, as the paper does for AMASS), mean precision ``1/NOISE_PRIOR_SCALE_M^2``. The entropy of
q(x_0) is dropped as in the paper (C.2.2). The paper's observations are SMPL-H joints and mesh
markers; ours are the fixed-skeleton joints and the virtual markers. Regression mode = one forward
pass with posterior means; optimisation mode = a copy of the three denoising networks fine-tuned
for ``iterations`` Adam steps on the given batch with the same objective, then that forward pass
(:meth:`MotionDVAEPrior.denoise_motion`).

Sizes (``MotionDVAE(**cfg).parameter_counts()``)
------------------------------------------------
Paper (``PAPER_CONFIG``): z 48, LSTM hidden 1024 (generative, both encoder LSTMs, initial-state
LSTM), MLP hidden 1024: 27,697,620 parameters for the DVAE (generative 11,563,380 + encoder
16,134,240), 55,194,442 with the denoising networks. Embedded (``EMBEDDED_CONFIG``): z 48, LSTM
hidden 256, MLP hidden 256: DVAE 2,206,164 (generative 925,044 + encoder 1,281,120), 4,362,058 in
all (17.5 MB float32).

Embedded training (:func:`train_motion_dvae`, ``python -m benchmark train motion-dvae``)
---------------------------------------------------------------------------------------
30-frame windows every 10 frames of the synthetic train split at 30 fps (paper: 1 s windows),
batch 64, the shared loop ``priors.training.train_loop`` (Adam, cosine decay to 0.1 lr, one torch
thread): 1,800 DVAE steps at lr 1e-3, then 720 denoising steps at lr 1e-3. The paper uses Adamax
lr 1e-4 with HuMoR's decays for 200 epochs (far beyond an embedded CPU budget); a higher Adam lr
was chosen for the short run. Measured per step on this project's shared 2-core machine (other jobs
running; a VPoser step took 4-10x its documented idle time): 1.35 s (DVAE) and 1.64 s (denoising);
scaled by the VPoser reference, about 0.29 s and 0.35 s on an idle core, i.e. about 13 min for the
default steps (an estimate, +-50%). The record ``priors/weights/motion_dvae.json`` holds both
phases' losses, wall times and seconds per step.

Completion adapter (``MotionDVAEPrior``, registered as ``motion-dvae``)
-----------------------------------------------------------------------
Recurrent at a fixed 30 fps. ``window = WindowSpec("fixed", frames=30, fps=30)``: the protocol asks
``decode`` for ``ceil(window_s * 30 / 30) * 30`` grid frames from t = 0 (a 4 s window = 120 frames)
and the adapter runs ONE recurrence over the whole grid (30 frames is only the training length;
the model is recurrent, so grids longer than the training windows are extrapolation). Latents:
``x0`` (B, 138), the state of frame 0 in the canonical frame (raw units, not standardised), and
``z`` (B, T - 1, 48), one latent per frame after the first (frame 0 is x0 itself). Initialisation:
x0 = the mean canonical first-frame state of the training windows (buffer ``x0_mean``), z = an
ancestral sample of the learned prior. Prior term (``prior_term_kind``): ``"learned"`` (default)
``= -1/(T-1) sum_t log N(z_t; mu_p(h_{t-1}), sigma_p(h_{t-1}))`` (nats per frame, summed over the 48
dims; gradients reach z and x0), or ``"l2"`` = mean over frames of ``|z_t|^2``. Translation and root
orientation come from the decoded state (its positions and orientations, not integrated
velocities) in the canonical frame: ``heading_normalised = True``, the protocol frees a heading and
an offset per sequence. ``encode_motion`` and ``denoise_motion`` accept any timestamps (resampled
to 30 fps when they are not a 30 fps grid).

Checkpoints
-----------
Project file ``priors/weights/motion_dvae.pt``: ``{"state_dict": {...}, "config": {"z_dim",
"hidden", "mlp_hidden", "fps"}}`` with this module's key names (``gen_rnn.*``, ``prior_mean.net.*``,
``prior_logvar.net.*``, ``decoder.net.*``, ``dec_logvar``, ``encoder.*``, ``denoise_encoder.*``,
``init_state.*``, ``noise.*`` and the buffers ``state_mean``, ``state_std``, ``x0_mean``,
``rest_joints``), loaded strictly. The official release (presumably github.com/g-fiche/Motion-DVAE)
could not be reached, so its format is unknown: :func:`load_official` loads a file whose keys match
these names (or are mapped by a ``key_map``) and otherwise raises a NotImplementedError that says
what is expected.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F
from torch import nn

from benchmark.body.lbs import forward_kinematics
from benchmark.interpolate import lerp_frames, slerp_frames
from benchmark.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from benchmark.skeleton import NUM_JOINTS
from priors.base import Decoded, ExportSpec, FitBatch, PriorAdapter, WindowSpec

log = logging.getLogger(__name__)

FPS = 30.0
POSE_DIM = 3 + 3 + 3 * (NUM_JOINTS - 1)  # trans, root, 21 body joints = 69
STATE_DIM = 2 * POSE_DIM  # + velocities = 138
PAPER_CONFIG = {"z_dim": 48, "hidden": 1024, "mlp_hidden": 1024}
EMBEDDED_CONFIG = {"z_dim": 48, "hidden": 256, "mlp_hidden": 256}
DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "motion_dvae.pt"
TRAIN_COMMAND = "python -m benchmark train motion-dvae"

MARKER_OFFSET = 0.1  # metres, virtual markers along each joint frame's x and z axes
POINT_WEIGHT = 100.0  # weight of the squared point errors (metres^2) in the DVAE loss
KL_ANNEAL_FRACTION = 0.25  # paper: KL annealing over the first 50 of 200 epochs
DENOISE_SIGMA_RANGE = (0.05, 0.25)  # rad, axis-angle noise of the denoising training copies
NOISE_PRIOR_SHAPE = 100.0  # Inverse-Gamma shape a0 of the per-frame noise variance (large: ~Gaussian)
NOISE_PRIOR_SCALE_M = 0.1  # prior mean precision a0 / b0 = 1 / NOISE_PRIOR_SCALE_M^2
LOGVAR_RANGE = (-12.0, 8.0)
DEC_LOGVAR_RANGE = (-7.0, 2.0)  # decoder variance bounds (standardised units)
OFFICIAL_UNKNOWN = (
    "the official Motion-DVAE checkpoint format is unknown (the repository, presumably "
    "github.com/g-fiche/Motion-DVAE, could not be read when this adapter was written)"
)


# -- geometry: canonical frame, state vectors, body points -------------------------------------
def yaw_matrix(yaw: torch.Tensor) -> torch.Tensor:
    """(...,) angles about the world y axis -> (..., 3, 3); Ry(a) e_z = (sin a, 0, cos a)."""
    c, s = torch.cos(yaw), torch.sin(yaw)
    o, z = torch.ones_like(yaw), torch.zeros_like(yaw)
    return torch.stack([c, z, s, z, o, z, -s, z, c], -1).unflatten(-1, (3, 3))


def heading(root: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) root orientations -> (...,) yaw of the body's forward (+z) axis about world y."""
    fwd = root[..., :, 2]
    return torch.atan2(fwd[..., 0], fwd[..., 2])


def canonicalise(rot: torch.Tensor, trans: torch.Tensor):
    """Remove the first frame's heading and ground-plane position (HuMoR's canonical frame, y up).

    rot (B, T, 22, 3, 3) local rotations (joint 0 = world root orientation), trans (B, T, 3).
    Returns (rot_c, trans_c, yaw (B,), origin (B, 3)) with ``R_root_c = Ry(-yaw) R_root`` and
    ``trans_c = Ry(-yaw) (trans - origin)``, origin = (x_0, 0, z_0): a rigid motion about a
    vertical axis, the same for every frame; :func:`uncanonicalise` inverts it.
    """
    yaw = heading(rot[:, 0, 0])
    origin = trans[:, 0] * trans.new_tensor([1.0, 0.0, 1.0])
    Rinv = yaw_matrix(-yaw)  # (B, 3, 3)
    root = Rinv[:, None] @ rot[:, :, 0]
    rot_c = torch.cat([root[:, :, None], rot[:, :, 1:]], dim=2)
    trans_c = ((trans - origin[:, None]) @ Rinv.transpose(-1, -2))
    return rot_c, trans_c, yaw, origin


def uncanonicalise(rot_c: torch.Tensor, trans_c: torch.Tensor, yaw: torch.Tensor, origin: torch.Tensor):
    """Inverse of :func:`canonicalise`."""
    R = yaw_matrix(yaw)
    root = R[:, None] @ rot_c[:, :, 0]
    rot = torch.cat([root[:, :, None], rot_c[:, :, 1:]], dim=2)
    return rot, trans_c @ R.transpose(-1, -2) + origin[:, None]


def unwrap_rotvec(aa: torch.Tensor) -> torch.Tensor:
    """(B, T, ..., 3) rotation vectors made continuous in time (dim 1).

    Each vector v (angle in [0, pi]) is replaced by its equivalent ``v - 2 pi v/|v|`` (angle - 2 pi)
    when that is closer to the previous frame's (already unwrapped) vector.
    """
    out = [aa[:, 0]]
    for t in range(1, aa.shape[1]):
        v = aa[:, t]
        n = v.norm(dim=-1, keepdim=True)
        alt = v - 2 * math.pi * v / n.clamp_min(1e-8)
        prev = out[-1]
        use_alt = ((alt - prev).norm(dim=-1, keepdim=True) < (v - prev).norm(dim=-1, keepdim=True)) & (n > 1e-8)
        out.append(torch.where(use_alt, alt, v))
    return torch.stack(out, dim=1)


def canonical_poses(windows: torch.Tensor, chunk: int = 2048) -> torch.Tensor:
    """(N, F, 69) raw windows (``priors.training.motion_windows``: axis-angle 22x3, translation) ->
    (N, F, 69) canonical pose sequences [trans (3), root aa (3), body aa (63)], unwrapped in time."""
    out = []
    for i in range(0, windows.shape[0], chunk):
        w = windows[i : i + chunk]
        poses = w[..., : NUM_JOINTS * 3].unflatten(-1, (NUM_JOINTS, 3))
        rot_c, trans_c, _, _ = canonicalise(axis_angle_to_matrix(poses), w[..., NUM_JOINTS * 3:])
        aa = unwrap_rotvec(matrix_to_axis_angle(rot_c))
        out.append(torch.cat([trans_c, aa.flatten(-2)], dim=-1))
    return torch.cat(out)


def pose_to_state(pos: torch.Tensor, fps: float = FPS) -> torch.Tensor:
    """(B, T, 69) pose sequences -> (B, T, 138) states (finite-difference velocities appended)."""
    vel = (pos[:, 1:] - pos[:, :-1]) * fps
    return torch.cat([pos, torch.cat([vel[:, :1], vel], dim=1)], dim=-1)


def motion_state(rot_c: torch.Tensor, trans_c: torch.Tensor, fps: float = FPS) -> torch.Tensor:
    """Canonical rotations (B, T, 22, 3, 3) and translation (B, T, 3) -> states (B, T, 138)."""
    if rot_c.shape[1] < 2:
        raise ValueError(f"motion-dvae: a motion needs at least 2 frames, got {rot_c.shape[1]}")
    aa = unwrap_rotvec(matrix_to_axis_angle(rot_c))  # (B, T, 22, 3)
    return pose_to_state(torch.cat([trans_c, aa.flatten(-2)], dim=-1), fps)


def windows_to_state(windows: torch.Tensor, fps: float = FPS) -> torch.Tensor:
    """(N, F, 69) raw windows -> (N, F, 138) canonical states."""
    return pose_to_state(canonical_poses(windows), fps)


def noisy_poses(pos: torch.Tensor, generator: torch.Generator | None = None,
                sigma_range=DENOISE_SIGMA_RANGE) -> tuple[torch.Tensor, torch.Tensor]:
    """Noisy copies of canonical pose sequences (N, F, 69) for the denoising phase.

    sigma ~ U(sigma_range) per sequence, times N(0, 1) on every joint's axis-angle (root included;
    translation clean), then re-canonicalised at the noisy first frame (its heading), as a noisy
    input is at test time. The noise is added to the canonical root rotation vector (the denoise
    table adds it to the world one: the same noise law up to the heading, a documented
    approximation that avoids a per-step conversion of all 22 joints). Returns (noisy, sigma (N,)).
    """
    N = pos.shape[0]
    lo, hi = sigma_range
    sigma = lo + (hi - lo) * torch.rand(N, generator=generator)
    noise = torch.randn(pos[..., 3:].shape, generator=generator) * sigma[:, None, None]
    aa = pos[..., 3:] + noise.to(pos.device)
    root = axis_angle_to_matrix(aa[..., :3])  # (N, F, 3, 3)
    Rinv = yaw_matrix(-heading(root[:, 0]))  # (N, 3, 3)
    root_aa = unwrap_rotvec(matrix_to_axis_angle(Rinv[:, None] @ root))
    trans = pos[..., :3] @ Rinv.transpose(-1, -2)  # frame 0 is at the origin of the ground plane already
    return torch.cat([trans, root_aa, aa[..., 3:]], dim=-1), sigma


def rotvec_to_matrix(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) rotation vectors -> (..., 3, 3) by Rodrigues' formula, written without reshapes to
    fixed batch sizes (ONNX-traceable with a dynamic batch) and smooth at 0 (angle sqrt(|v|^2 + 1e-12))."""
    theta = torch.sqrt((v * v).sum(-1, keepdim=True) + 1e-12)
    k = v / theta
    x, y, z = k[..., 0], k[..., 1], k[..., 2]
    o = x * 0.0  # not zeros_like: the ONNX exporter folds that into a constant of the example's batch
    K = torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).unflatten(-1, (3, 3))
    s, c = torch.sin(theta)[..., None], torch.cos(theta)[..., None]
    eye = torch.eye(3, dtype=v.dtype, device=v.device)
    return eye + s * K + (1 - c) * (K @ K)


def state_to_motion(state: torch.Tensor):
    """States (..., 138) -> local rotations (..., 22, 3, 3) and translation (..., 3) (positions and
    orientations of the state; its velocities are not used)."""
    trans = state[..., :3]
    aa = state[..., 3:POSE_DIM].unflatten(-1, (NUM_JOINTS, 3))
    return rotvec_to_matrix(aa), trans


def body_points(rot: torch.Tensor, trans: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """(..., 66, 3) body points: 22 FK joints on ``rest`` (22, 3) + 2 virtual markers per joint
    (``MARKER_OFFSET`` along the joint frame's x and z axes), translated by ``trans``."""
    g_rot, joints = forward_kinematics(rot, rest)
    joints = joints + trans[..., None, :]
    mx = joints + MARKER_OFFSET * g_rot[..., :, 0]
    mz = joints + MARKER_OFFSET * g_rot[..., :, 2]
    return torch.cat([joints, mx, mz], dim=-2)


# -- the network -------------------------------------------------------------------------------
class MLP(nn.Module):
    """HuMoR's MLP pattern: Linear, then [GroupNorm(16) -> ReLU -> Linear] for each further layer.

    ``sizes = [in, h1, h2, out]`` gives 2 hidden layers. Works on (..., in) (flattened for the norm).
    """

    def __init__(self, sizes: list[int], groups: int = 16):
        super().__init__()
        layers: list[nn.Module] = [nn.Linear(sizes[0], sizes[1])]
        for i in range(2, len(sizes)):
            layers += [nn.GroupNorm(groups, sizes[i - 1]), nn.ReLU(), nn.Linear(sizes[i - 1], sizes[i])]
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        lead = x.shape[:-1]
        return self.net(x.reshape(-1, x.shape[-1])).reshape(*lead, -1)


def _zero_last(mlp: MLP) -> None:
    """Zero the last Linear of an MLP whose output is a residual (training starts from identity) [inferred]."""
    with torch.no_grad():
        mlp.net[-1].weight.zero_()
        mlp.net[-1].bias.zero_()


class Encoder(nn.Module):
    """q(z_t | x_0, z_{1:t-1}, x_{t:T}): anti-causal LSTM over states + forward recurrence over z."""

    def __init__(self, z_dim: int, hidden: int, mlp_hidden: int):
        super().__init__()
        self.z_dim = z_dim
        self.bwd_rnn = nn.LSTM(STATE_DIM, hidden, batch_first=True)
        self.fwd_cell = nn.LSTMCell(z_dim + STATE_DIM, hidden)
        self.post_mean = MLP([2 * hidden, mlp_hidden, mlp_hidden, z_dim])
        self.post_logvar = MLP([2 * hidden, mlp_hidden, mlp_hidden, z_dim])

    def backward_features(self, xn: torch.Tensor) -> torch.Tensor:
        """(B, T, S) standardised states -> (B, T, H) anti-causal features b_t (summary of x_{t:T})."""
        out, _ = self.bwd_rnn(torch.flip(xn, [1]))
        return torch.flip(out, [1])

    def forward(self, xn: torch.Tensor, x0n: torch.Tensor, sample: bool, generator=None, b=None):
        """Posterior over z_{1:T-1} for standardised states xn (B, T, S) and x^_0 (B, S).

        sample: draw z_t from q (reparameterised; ``generator`` for the noise) and feed it back,
        else feed back the posterior mean. Returns (z, q_mean, q_logvar), each (B, T-1, Z).
        """
        B, T, _ = xn.shape
        if b is None:
            b = self.backward_features(xn)
        z_prev = xn.new_zeros(B, self.z_dim)
        state = self.fwd_cell(torch.cat([z_prev, x0n], -1))
        # The heads' first Linear acts on [f_{t-1}, b_t]: its b-part is computed for all t at once
        # (the same maths as post_mean([f, b]), fewer sequential operations).
        Hf = state[0].shape[-1]
        lin_m, lin_v = self.post_mean.net[0], self.post_logvar.net[0]
        pre_m = F.linear(b[:, 1:], lin_m.weight[:, Hf:], lin_m.bias)
        pre_v = F.linear(b[:, 1:], lin_v.weight[:, Hf:], lin_v.bias)
        rest_m, rest_v = self.post_mean.net[1:], self.post_logvar.net[1:]
        w_m, w_v = lin_m.weight[:, :Hf], lin_v.weight[:, :Hf]
        zs, means, logvars = [], [], []
        for t in range(1, T):
            f = state[0]
            mu = rest_m(F.linear(f, w_m) + pre_m[:, t - 1])
            lv = rest_v(F.linear(f, w_v) + pre_v[:, t - 1]).clamp(*LOGVAR_RANGE)
            if sample:
                z = mu + torch.exp(0.5 * lv) * _randn(mu, generator)
            else:
                z = mu
            zs.append(z)
            means.append(mu)
            logvars.append(lv)
            state = self.fwd_cell(torch.cat([z, x0n], -1), state)
        if not zs:
            empty = xn.new_zeros(B, 0, self.z_dim)
            return empty, empty, empty
        return torch.stack(zs, 1), torch.stack(means, 1), torch.stack(logvars, 1)


class InitialStatePredictor(nn.Module):
    """q(x_0 | y): anti-causal LSTM over the noisy states, MLP heads at frame 0 (residual mean)."""

    def __init__(self, hidden: int, mlp_hidden: int):
        super().__init__()
        self.bwd_rnn = nn.LSTM(STATE_DIM, hidden, batch_first=True)
        self.mean = MLP([hidden, mlp_hidden, mlp_hidden, STATE_DIM])
        self.logvar = MLP([hidden, mlp_hidden, mlp_hidden, STATE_DIM])
        _zero_last(self.mean)

    def forward(self, yn: torch.Tensor):
        out, _ = self.bwd_rnn(torch.flip(yn, [1]))
        b0 = out[:, -1]  # the anti-causal summary of frames 0..T-1, at frame 0
        # residual on the noisy first positions/orientations; velocities (finite differences of
        # noisy rotations, far off the data distribution) start from the data mean (0 standardised)
        base = torch.cat([yn[:, 0, :POSE_DIM], torch.zeros_like(yn[:, 0, POSE_DIM:])], -1)
        return base + self.mean(b0), self.logvar(b0).clamp(*LOGVAR_RANGE)


class NoisePredictor(nn.Module):
    """q(v_t | y) = InvGamma(alpha_t, beta_t), one variance per frame, from the denoising encoder's
    anti-causal features (the paper's noise predictor re-uses the encoder's LSTM + its own MLP)."""

    def __init__(self, hidden: int, mlp_hidden: int):
        super().__init__()
        self.head = MLP([hidden, mlp_hidden, mlp_hidden, 2])
        with torch.no_grad():  # start at the prior: alpha = a0, beta = a0 * s0^2
            self.head.net[-1].weight.zero_()
            self.head.net[-1].bias.copy_(torch.tensor([math.log(math.expm1(NOISE_PRIOR_SHAPE)),
                                                        math.log(math.expm1(NOISE_PRIOR_SHAPE * NOISE_PRIOR_SCALE_M ** 2))]))

    def forward(self, b: torch.Tensor):
        out = self.head(b)
        return F.softplus(out[..., 0]) + 1e-3, F.softplus(out[..., 1]) + 1e-6


def _randn(like: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """Standard normal noise shaped like ``like``, drawn on the generator's device, moved to like's."""
    dev = generator.device if generator is not None else like.device
    return torch.randn(like.shape, generator=generator, device=dev, dtype=like.dtype).to(like.device)


def gaussian_kl(mq, lq, mp, lp):
    """KL(N(mq, e^lq) || N(mp, e^lp)) per element."""
    return 0.5 * (lp - lq + (torch.exp(lq) + (mq - mp) ** 2) * torch.exp(-lp) - 1.0)


class MotionDVAE(nn.Module):
    """The Motion-DVAE network with its denoising networks (module docstring for the wiring)."""

    def __init__(self, z_dim: int = 48, hidden: int = 1024, mlp_hidden: int = 1024, fps: float = FPS):
        super().__init__()
        self.z_dim, self.hidden, self.mlp_hidden, self.fps = int(z_dim), int(hidden), int(mlp_hidden), float(fps)
        Z, H, M = self.z_dim, self.hidden, self.mlp_hidden
        # generative model (prior + decoder share gen_rnn)
        self.gen_rnn = nn.LSTM(Z + STATE_DIM, H, batch_first=True)
        self.prior_mean = MLP([H, M, M, Z])
        self.prior_logvar = MLP([H, M, M, Z])
        self.decoder = MLP([H + Z, M, M, STATE_DIM])
        _zero_last(self.decoder)  # the untrained decoder repeats x_0 (a residual starts at identity)
        # log-variance of p(x_t | x_0, z_{1:t}) per state dimension (standardised units), learned
        self.dec_logvar = nn.Parameter(torch.zeros(STATE_DIM))
        # inference model (clean data) and the denoising networks
        self.encoder = Encoder(Z, H, M)
        self.denoise_encoder = Encoder(Z, H, M)
        self.init_state = InitialStatePredictor(H, M)
        self.noise = NoisePredictor(H, M)
        # data statistics and the skeleton of the point losses (set by training, saved with the weights)
        self.register_buffer("state_mean", torch.zeros(STATE_DIM))
        self.register_buffer("state_std", torch.ones(STATE_DIM))
        self.register_buffer("x0_mean", torch.zeros(STATE_DIM))
        self.register_buffer("rest_joints", torch.zeros(NUM_JOINTS, 3))

    @property
    def config(self) -> dict:
        return {"z_dim": self.z_dim, "hidden": self.hidden, "mlp_hidden": self.mlp_hidden, "fps": self.fps}

    def parameter_counts(self) -> dict:
        def n(*mods):
            return sum(p.numel() for m in mods for p in m.parameters())

        gen = n(self.gen_rnn, self.prior_mean, self.prior_logvar, self.decoder) + self.dec_logvar.numel()
        return {"generative (prior + decoder)": gen, "encoder": n(self.encoder),
                "dvae (generative + encoder)": gen + n(self.encoder), "denoise_encoder": n(self.denoise_encoder),
                "init_state": n(self.init_state), "noise": n(self.noise), "total": n(self)}

    # standardisation
    def normalise(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.state_mean) / self.state_std

    def unnormalise(self, xn: torch.Tensor) -> torch.Tensor:
        return xn * self.state_std + self.state_mean

    # generative model
    def gen_features(self, x0n: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """h_{0..T-1} (B, T, H) for x^_0 (B, S) and z_{1..T-1} (B, T-1, Z): one LSTM call."""
        zz = torch.cat([z[:, :1] * 0.0 if z.shape[1] else x0n.new_zeros(x0n.shape[0], 1, self.z_dim), z], 1)
        u = torch.cat([zz, x0n[:, None].expand(-1, zz.shape[1], -1)], -1)
        # explicit zero initial state built from the input, so that an ONNX export keeps the batch dynamic
        h0 = (x0n[:, :1] * 0.0).expand(-1, self.hidden)[None].contiguous()
        h, _ = self.gen_rnn(u, (h0, h0))
        return h

    def prior_params(self, h_prev: torch.Tensor):
        return self.prior_mean(h_prev), self.prior_logvar(h_prev).clamp(*LOGVAR_RANGE)

    def decode_normalised(self, x0n: torch.Tensor, z: torch.Tensor, h: torch.Tensor | None = None) -> torch.Tensor:
        """Standardised states of frames 0..T-1 (B, T, S); frame 0 is x^_0."""
        if h is None:
            h = self.gen_features(x0n, z)
        # the decoder head gives the per-frame increment of the standardised state; the mean of
        # x_t is x^_0 plus their running sum (a deterministic function of x_0, z_{1:t}) [inferred]
        inc = self.decoder(torch.cat([h[:, 1:], z], -1))
        return torch.cat([x0n[:, None], x0n[:, None] + torch.cumsum(inc, dim=1)], 1)

    def generate(self, x0: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Raw states (B, T, 138) of the motion from x0 (B, 138) raw and z (B, T-1, Z)."""
        return self.unnormalise(self.decode_normalised(self.normalise(x0), z))

    def prior_nll(self, x0: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """(B,) -1/(T-1) sum_t log N(z_t; prior(h_{t-1})), nats per frame (sum over dims)."""
        if z.shape[1] == 0:
            return x0.new_zeros(x0.shape[0])
        x0n = self.normalise(x0)
        h = self.gen_features(x0n, z)
        mu, lv = self.prior_params(h[:, :-1])
        nll = 0.5 * (lv + (z - mu) ** 2 * torch.exp(-lv) + math.log(2 * math.pi))
        return nll.sum(-1).mean(-1)

    def sample_prior(self, x0: torch.Tensor, steps: int, generator: torch.Generator | None = None,
                     temperature: float = 1.0) -> torch.Tensor:
        """Ancestral sample z_{1..steps} (B, steps, Z) of p(z_t | x_0, z_{1:t-1})."""
        x0n = self.normalise(x0)
        B = x0.shape[0]
        z_prev = x0.new_zeros(B, 1, self.z_dim)
        h, state = self.gen_rnn(torch.cat([z_prev, x0n[:, None]], -1))
        zs = []
        for _ in range(steps):
            mu, lv = self.prior_params(h[:, -1])
            z = mu + temperature * torch.exp(0.5 * lv) * _randn(mu, generator)
            zs.append(z)
            h, state = self.gen_rnn(torch.cat([z, x0n], -1)[:, None], state)
        return torch.stack(zs, 1) if zs else x0.new_zeros(B, 0, self.z_dim)

    # losses
    def dvae_loss(self, states: torch.Tensor, points: torch.Tensor, beta: float) -> dict:
        """Clean-data loss for canonical states (B, T, 138) and their body points (B, T, P, 3)."""
        xn = self.normalise(states)
        x0n = xn[:, 0]
        z, qm, qlv = self.encoder(xn, x0n, sample=True)
        h = self.gen_features(x0n, z)
        pm, plv = self.prior_params(h[:, :-1])
        rec_n = self.decode_normalised(x0n, z, h)
        lv = self.dec_logvar.clamp(*DEC_LOGVAR_RANGE)
        sq = (rec_n[:, 1:] - xn[:, 1:]).square()
        rec = 0.5 * (sq * torch.exp(-lv) + lv).sum(-1).mean()
        kl = gaussian_kl(qm, qlv, pm, plv).sum(-1).mean()
        rot, trans = state_to_motion(self.unnormalise(rec_n[:, 1:]))
        pts = (body_points(rot, trans, self.rest_joints) - points[:, 1:]).square().sum(-1)
        point_sq = pts.sum(-1).mean()
        loss = rec + beta * kl + POINT_WEIGHT * point_sq
        return {"loss": loss, "rec": rec, "kl": kl, "state_mse": sq.mean().detach(), "point_sq_m2": point_sq,
                "point_rmse_m": (pts.mean()).sqrt().detach(), "beta": torch.tensor(float(beta))}

    def denoise_forward(self, noisy_states: torch.Tensor, sample: bool, generator=None, nets=None):
        """Denoising inference on noisy canonical states (B, T, 138).

        nets: (encoder, init_state, noise) to use (default: this model's denoising networks).
        Returns dict with x0 (raw, B x 138), z, q_mean, q_logvar, x0 mean/logvar (standardised),
        noise alpha/beta (B, T), decoded standardised states (B, T, S) and features h.
        """
        enc, init, noise = nets if nets is not None else (self.denoise_encoder, self.init_state, self.noise)
        yn = self.normalise(noisy_states)
        m0, lv0 = init(yn)
        if sample:
            x0n = m0 + torch.exp(0.5 * lv0) * _randn(m0, generator)
        else:
            x0n = m0
        b = enc.backward_features(yn)
        z, qm, qlv = enc(yn, x0n, sample=sample, generator=generator, b=b)
        alpha, beta_ = noise(b)
        h = self.gen_features(x0n, z)
        xn = self.decode_normalised(x0n, z, h)
        return {"x0n": x0n, "x0": self.unnormalise(x0n), "z": z, "q_mean": qm, "q_logvar": qlv, "alpha": alpha,
                "beta": beta_, "h": h, "xn": xn}

    def denoise_loss(self, noisy_states: torch.Tensor, observed_points: torch.Tensor, beta: float,
                     nets=None, generator=None) -> dict:
        """Unsupervised denoising objective (module docstring) per frame, mean over the batch."""
        out = self.denoise_forward(noisy_states, sample=True, generator=generator, nets=nets)
        pm, plv = self.prior_params(out["h"][:, :-1])
        kl_z = gaussian_kl(out["q_mean"], out["q_logvar"], pm, plv).sum(-1)  # (B, T-1)
        rot, trans = state_to_motion(self.unnormalise(out["xn"]))
        sq = (body_points(rot, trans, self.rest_joints) - observed_points).square().sum((-1, -2))  # (B, T)
        P = observed_points.shape[-2] * 3
        alpha, b = out["alpha"], out["beta"]
        e_prec = alpha / b
        e_logv = torch.log(b) - torch.digamma(alpha)
        data = 0.5 * e_prec * sq + 0.5 * P * e_logv
        a0 = torch.full_like(alpha, NOISE_PRIOR_SHAPE)
        b0 = a0 * NOISE_PRIOR_SCALE_M ** 2
        # KL(InvGamma(a, b) || InvGamma(a0, b0)) = KL(Gamma(a, rate b) || Gamma(a0, rate b0)) (precisions)
        kl_v = torch.distributions.kl_divergence(torch.distributions.Gamma(alpha, b), torch.distributions.Gamma(a0, b0))
        T = noisy_states.shape[1]
        data_t, kl_v_t = data.sum(1).mean() / T, kl_v.sum(1).mean() / T
        kl_z_t = kl_z.sum(1).mean() / T
        loss = data_t + beta * kl_z_t + kl_v_t
        return {"loss": loss, "data": data_t, "kl_z": kl_z_t, "kl_noise": kl_v_t,
                "point_rmse_m": (sq.mean() / P).sqrt().detach(), "noise_std_m": (b / (alpha - 1).clamp_min(1e-3)).sqrt().mean().detach(),
                "beta": torch.tensor(float(beta))}


# -- checkpoints -----------------------------------------------------------------------------
def read_project_checkpoint(path: str | Path) -> tuple[dict, dict]:
    """(state_dict, config) of a project checkpoint ``priors/weights/motion_dvae.pt``, strictly checked."""
    path = Path(path)
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), dict) or not isinstance(ckpt.get("config"), dict):
        top = sorted(ckpt)[:20] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(f"{path}: not a motion-dvae project checkpoint: expected {{'state_dict', 'config'}}, found {top}; "
                         f"retrain with `{TRAIN_COMMAND}`")
    cfg = ckpt["config"]
    missing = {"z_dim", "hidden", "mlp_hidden"} - set(cfg)
    if missing:
        raise ValueError(f"{path}: field 'config' lacks {sorted(missing)}; retrain with `{TRAIN_COMMAND}`")
    return ckpt["state_dict"], {"z_dim": int(cfg["z_dim"]), "hidden": int(cfg["hidden"]),
                                "mlp_hidden": int(cfg["mlp_hidden"]), "fps": float(cfg.get("fps", FPS))}


def load_state_strict(model: MotionDVAE, state_dict: dict, source: str) -> None:
    """Copy ``state_dict`` into ``model``: every key present with the model's shape, no extra key."""
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state_dict))
    if missing:
        raise KeyError(f"{source}: missing {len(missing)} key(s), e.g. {missing[:5]}; a motion-dvae checkpoint holds "
                       f"{len(expected)} tensors (module names: {expected_modules()})")
    extra = sorted(set(state_dict) - set(expected))
    if extra:
        raise KeyError(f"{source}: unexpected key(s) {extra[:5]} (total {len(extra)}); expected module names: {expected_modules()}")
    for k, v in expected.items():
        t = state_dict[k]
        if not torch.is_tensor(t) or tuple(t.shape) != tuple(v.shape):
            found = tuple(t.shape) if torch.is_tensor(t) else type(t).__name__
            raise ValueError(f"{source}: key {k!r} has shape {found}, expected {tuple(v.shape)} for config {model.config}")
    model.load_state_dict(state_dict, strict=True)


def expected_modules() -> list[str]:
    return ["gen_rnn (nn.LSTM)", "prior_mean.net", "prior_logvar.net", "decoder.net", "encoder.{bwd_rnn,fwd_cell,post_mean,post_logvar}",
            "denoise_encoder.{...same as encoder}", "init_state.{bwd_rnn,mean,logvar}", "noise.head",
            "buffers state_mean, state_std, x0_mean, rest_joints"]


def load_official(path: str | Path, model: MotionDVAE | None = None,
                  key_map: dict | Callable[[str], str | None] | None = None) -> MotionDVAE:
    """Hook for the official Motion-DVAE weights, whose format is unknown.

    Reads ``path`` (a torch file: a state dict, or a dict with ``state_dict`` / ``model``), renames
    its keys with ``key_map`` (a dict official-name -> our name, or a function returning our name
    or None to drop the key) and loads them strictly into ``model`` (default: the paper-size
    :class:`MotionDVAE`). Without a ``key_map`` the file's keys must already be ours. When the keys
    do not match, raises NotImplementedError naming what is unknown and what is expected: our module
    names are ``gen_rnn`` (the LSTM shared by prior and decoder, input [z_t, x^_0], hidden 1024),
    ``prior_mean``/``prior_logvar``/``decoder`` (HuMoR-style MLPs), ``encoder`` (``bwd_rnn``
    anti-causal LSTM over states, ``fwd_cell`` forward recurrence over z, ``post_mean`` /
    ``post_logvar``), ``denoise_encoder``, ``init_state`` and ``noise``; plus the buffers
    ``state_mean``/``state_std`` (data standardisation), ``x0_mean`` and ``rest_joints``, which
    an official file would not hold (set them from the official normalisation statistics / the
    SMPL-H neutral joints). The official wiring may also differ from ours (it is inferred).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"motion-dvae official weights: {path} does not exist ({OFFICIAL_UNKNOWN})")
    model = model if model is not None else MotionDVAE(**PAPER_CONFIG)
    try:
        raw = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise NotImplementedError(f"{path}: cannot read it as a torch weights file ({type(exc).__name__}: {exc}); "
                                  f"{OFFICIAL_UNKNOWN}") from exc
    sd = raw
    if isinstance(raw, dict):
        for key in ("state_dict", "model", "model_state_dict"):
            if isinstance(raw.get(key), dict):
                sd = raw[key]
                break
    if not isinstance(sd, dict) or not all(torch.is_tensor(v) for v in sd.values()):
        raise NotImplementedError(f"{path}: no tensor state dict found (top level {type(raw).__name__}); {OFFICIAL_UNKNOWN}")
    if key_map is not None:
        mapper = key_map.get if isinstance(key_map, dict) else key_map
        sd = {mapper(k): v for k, v in sd.items() if mapper(k) is not None}
    expected = model.state_dict()
    if set(sd) != set(expected):
        found = sorted(sd)[:8]
        raise NotImplementedError(
            f"{path}: its keys (e.g. {found}, {len(sd)} in all) do not match this implementation's "
            f"({len(expected)} tensors; modules {expected_modules()}): {OFFICIAL_UNKNOWN}. Write a key map "
            "(official name -> ours) and call priors.motion_dvae.load_official(path, key_map=...), checking "
            "the wiring in this module's docstring against the official code."
        )
    load_state_strict(model, sd, str(path))
    return model


# -- the adapter -----------------------------------------------------------------------------
def _regular_30fps(timestamps: torch.Tensor, fps: float = FPS, tol: float = 1e-4) -> bool:
    t = timestamps.to(torch.float64)
    if t.shape[1] < 2:
        return False
    return bool(((t[:, 1:] - t[:, :-1]) - 1.0 / fps).abs().max() < tol)


def _grid_frames(window_s: float, frames: int = 30, fps: float = FPS) -> int:
    """Grid length the completion protocol asks for (mirrors benchmark.protocols.completion._grid)."""
    return max(1, math.ceil(window_s * fps / frames - 1e-9)) * frames


class _DecoderExport(nn.Module):
    """(x0 (B, 138), z (B, T, 48)) -> (rotations (B, T+1, 22, 3, 3), trans (B, T+1, 3)) canonical."""

    def __init__(self, model: MotionDVAE):
        super().__init__()
        self.model = model

    def forward(self, x0: torch.Tensor, z: torch.Tensor):
        states = self.model.generate(x0, z)
        rot, trans = state_to_motion(states)
        return rot, trans


class MotionDVAEPrior(PriorAdapter):
    """Motion-DVAE as a completion prior (module docstring: latents, prior term, frames)."""

    name = "motion-dvae"
    paper = "Fiche et al., Motion-DVAE: Unsupervised learning for fast human motion denoising (MIG 2023)"
    window = WindowSpec(kind="fixed", frames=30, fps=FPS)
    encodes_translation = True
    encodes_root_orientation = True
    heading_normalised = True
    joints = tuple(range(1, NUM_JOINTS))
    shape_conditioned = False
    has_encoder = True
    sixd_layout = None
    prior_term_kind = "learned"  # or "l2"

    def __init__(self, size: str = "embedded", weights: str | None = None, device: str | torch.device = "cpu"):
        super().__init__(size=size, weights=weights, device=device)
        if size == "paper":
            if weights is None:
                raise ValueError(f"motion-dvae size 'paper' needs official weights, and none are known: {OFFICIAL_UNKNOWN}. "
                                 "Use size='embedded' (the project's weights), or map an official file with "
                                 "priors.motion_dvae.load_official(path, key_map=...)")
            self.net = load_official(weights)
        elif size == "embedded":
            path = Path(weights) if weights is not None else DEFAULT_WEIGHTS
            if not path.exists():
                raise FileNotFoundError(f"embedded motion-dvae weights not found: {path}. Train them with `{TRAIN_COMMAND}`")
            sd, cfg = read_project_checkpoint(path)
            self.net = MotionDVAE(**cfg)
            load_state_strict(self.net, sd, str(path))
            self.weights_path = str(path)
        else:
            raise ValueError(f"motion-dvae: unknown size {size!r}; expected 'embedded' or 'paper'")
        self._freeze()
        self.to(device)

    @classmethod
    def from_network(cls, net: MotionDVAE, device="cpu") -> "MotionDVAEPrior":
        """An adapter around an in-memory network (tests, freshly trained models)."""
        self = cls.__new__(cls)
        PriorAdapter.__init__(self, size="embedded", weights=None)
        self.net = net
        self._freeze()
        return self.to(device)

    def _freeze(self):
        for p in self.net.parameters():
            p.requires_grad_(False)
        self.net.eval()

    @property
    def device(self) -> torch.device:
        return self.net.state_mean.device

    @property
    def z_dim(self) -> int:
        return self.net.z_dim

    def train(self, mode: bool = True):
        super().train(mode)
        self.net.eval()
        return self

    @classmethod
    def paper_network(cls) -> MotionDVAE:
        """The paper-size network (z 48, LSTM hidden 1024, MLP hidden 1024) with random weights."""
        return MotionDVAE(**PAPER_CONFIG).eval()

    # -- completion API
    def init_latents(self, batch: FitBatch, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """x0 = the training mean first-frame state; z = an ancestral sample of the learned prior
        over the protocol's grid (``ceil(window_s) * 30`` frames, so T - 1 latents)."""
        T = _grid_frames(batch.window_s, self.window.frames, self.window.fps)
        B = batch.batch_size
        with torch.no_grad():
            x0 = self.net.x0_mean.expand(B, -1).clone()
            z = self.net.sample_prior(x0, T - 1, generator=generator)
        return {"x0": x0, "z": z}

    def _check_latents(self, latents: dict, where: str):
        if "x0" not in latents or "z" not in latents:
            raise ValueError(f"motion-dvae.{where}: latents must hold 'x0' (B, {STATE_DIM}) and 'z' (B, T-1, {self.z_dim}); "
                             f"got keys {sorted(latents)}")
        x0, z = latents["x0"], latents["z"]
        if x0.dim() != 2 or x0.shape[1] != STATE_DIM:
            raise ValueError(f"motion-dvae.{where}: latents['x0'] must be (B, {STATE_DIM}), got {tuple(x0.shape)}")
        if z.dim() != 3 or z.shape[0] != x0.shape[0] or z.shape[2] != self.z_dim:
            raise ValueError(f"motion-dvae.{where}: latents['z'] must be (B, T-1, {self.z_dim}) with B = {x0.shape[0]}, got {tuple(z.shape)}")
        return x0, z

    def decode(self, latents: dict[str, torch.Tensor], timestamps: torch.Tensor, shape: torch.Tensor | None = None) -> Decoded:
        """Motion at the 30 fps grid ``timestamps`` (B, T) with T = z.shape[1] + 1 (frame 0 = x0):
        rotations (B, T, 22, 3, 3) and translation (B, T, 3) in the canonical frame."""
        x0, z = self._check_latents(latents, "decode")
        B, T = timestamps.shape
        if B != x0.shape[0] or T != z.shape[1] + 1:
            raise ValueError(f"motion-dvae.decode: timestamps {tuple(timestamps.shape)} must be (B, T) = "
                             f"({x0.shape[0]}, {z.shape[1] + 1}) (one frame per latent z_t plus frame 0)")
        if T > 1 and not _regular_30fps(timestamps, self.window.fps):
            raise ValueError("motion-dvae.decode: timestamps must be a regular 30 fps grid (the model is recurrent at 30 fps); "
                             "the protocol interpolates to other times")
        states = self.net.generate(x0, z)
        rot, trans = state_to_motion(states)
        return Decoded(rotations=rot, trans=trans, extra={"state": states})

    def prior_term(self, latents: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B,) learned: -1/(T-1) sum_t log N(z_t; prior(h_{t-1})); l2: mean over frames of |z_t|^2."""
        x0, z = self._check_latents(latents, "prior_term")
        if self.prior_term_kind == "learned":
            return self.net.prior_nll(x0, z)
        if self.prior_term_kind == "l2":
            return z.square().sum(-1).mean(-1)
        raise ValueError(f"motion-dvae: prior_term_kind must be 'learned' or 'l2', got {self.prior_term_kind!r}")

    # -- encoders
    def _prepare(self, rotations, trans, timestamps, where: str):
        if rotations.dim() != 5 or rotations.shape[2:] != (NUM_JOINTS, 3, 3):
            raise ValueError(f"motion-dvae.{where}: rotations must be (B, T, {NUM_JOINTS}, 3, 3), got {tuple(rotations.shape)}")
        B, T = rotations.shape[:2]
        if trans is None or tuple(trans.shape) != (B, T, 3):
            raise ValueError(f"motion-dvae.{where}: trans must be (B, T, 3) = {(B, T, 3)} (the model encodes translation), "
                             f"got {None if trans is None else tuple(trans.shape)}")
        if tuple(timestamps.shape) != (B, T):
            raise ValueError(f"motion-dvae.{where}: timestamps must be (B, T) = {(B, T)}, got {tuple(timestamps.shape)}")
        dev = self.device
        rot, tr, ts = rotations.to(dev, torch.float32), trans.to(dev, torch.float32), timestamps.to(dev, torch.float64)
        grid = None
        if not _regular_30fps(ts):
            span = float((ts[:, -1] - ts[:, 0]).max())
            n = int(math.floor(span * FPS + 1e-6)) + 1
            if n < 2:
                raise ValueError(f"motion-dvae.{where}: the motion spans {span:.3f} s, less than one 30 fps frame")
            grid = ts[:, :1] + torch.arange(n, device=dev, dtype=torch.float64) / FPS
            rot, tr = slerp_frames(rot, ts, grid), lerp_frames(tr, ts, grid)
        rot_c, tr_c, yaw, origin = canonicalise(rot, tr)
        return motion_state(rot_c, tr_c), rot_c, tr_c, yaw, origin, grid

    @torch.no_grad()
    def encode_motion(self, rotations: torch.Tensor, trans: torch.Tensor, timestamps: torch.Tensor) -> dict[str, torch.Tensor]:
        """Posterior means ``{"x0": (B, 138), "z": (B, T-1, 48)}`` of a clean motion.

        The motion is canonicalised at its first frame (decode returns the canonical frame: the
        caller aligns heading and ground-plane offset) and, if its timestamps are not a 30 fps grid,
        resampled to one from its first timestamp (then T is the grid's length). x0 is the observed
        first state (x_0 is given in the DVAE); z_t the clean encoder's posterior means, fed back.
        """
        states, *_ = self._prepare(rotations, trans, timestamps, "encode_motion")
        xn = self.net.normalise(states)
        z, _, _ = self.net.encoder(xn, xn[:, 0], sample=False)
        return {"x0": states[:, 0].clone(), "z": z}

    def denoise_motion(self, rotations: torch.Tensor, trans: torch.Tensor, timestamps: torch.Tensor,
                       mode: str = "regression", iterations: int = 50, lr: float = 3e-4, seed: int = 0) -> Decoded:
        """Denoise noisy motions (paper section 4): rotations (B, T, 22, 3, 3), trans (B, T, 3),
        timestamps (B, T) -> Decoded (world frame, same timestamps).

        mode "regression": one forward pass (initial-state predictor mean, denoising-encoder
        posterior means, decoder). "optimisation": a copy of the denoising encoder, initial-state and
        noise predictors is fine-tuned on this batch with the unsupervised objective for
        ``iterations`` Adam steps (``lr``; the noise of the reparameterised samples drawn from
        ``seed``), then the same forward pass with the copy; the adapter's own weights are unchanged.
        Non-30 fps input is resampled to 30 fps and the result interpolated back.
        """
        if mode not in ("regression", "optimisation"):
            raise ValueError(f"motion-dvae.denoise_motion: mode must be 'regression' or 'optimisation', got {mode!r}")
        with torch.no_grad():
            states, rot_c, tr_c, yaw, origin, grid = self._prepare(rotations, trans, timestamps, "denoise_motion")
        net = self.net
        nets = (net.denoise_encoder, net.init_state, net.noise)
        info = {"mode": mode}
        if mode == "optimisation" and iterations > 0:
            nets = tuple(copy.deepcopy(m) for m in nets)
            params = [p for m in nets for p in m.parameters()]
            for p in params:
                p.requires_grad_(True)
            with torch.no_grad():
                obs = body_points(rot_c, tr_c, net.rest_joints)
            opt = torch.optim.Adam(params, lr=lr)
            gen = torch.Generator(device=states.device).manual_seed(seed)
            losses = []
            with torch.enable_grad():
                for _ in range(int(iterations)):
                    parts = net.denoise_loss(states, obs, beta=1.0, nets=nets, generator=gen)
                    opt.zero_grad(set_to_none=True)
                    parts["loss"].backward()
                    opt.step()
                    losses.append(float(parts["loss"].detach()))
            info["losses"] = losses
        with torch.no_grad():
            out = net.denoise_forward(states, sample=False, nets=nets)
            rot, tr = state_to_motion(net.unnormalise(out["xn"]))
            rot, tr = uncanonicalise(rot, tr, yaw, origin)
            if grid is not None:
                ts = timestamps.to(rot.device, torch.float64)
                rot, tr = slerp_frames(rot, grid, ts), lerp_frames(tr, grid, ts)
        return Decoded(rotations=rot, trans=tr, extra={"x0": out["x0"], "z": out["z"], **info})

    # -- export
    def export_decoder(self) -> ExportSpec:
        """ONNX: (x0 (B, 138), z (B, T, 48)) -> (rotations (B, T+1, 22, 3, 3), trans (B, T+1, 3)).

        The canonical-frame decode path of :meth:`decode` (one LSTM over the sequence, MLP heads,
        axis-angle -> matrices). Batch is dynamic; T is the example's (29 latents, a 1 s window)
        and should be taken as fixed in the exported graph. Example latents: the training mean x0
        and an ancestral prior sample (seed 0).
        """
        g = torch.Generator().manual_seed(0)
        with torch.no_grad():
            x0 = self.net.x0_mean.expand(2, -1).clone()
            z = self.net.sample_prior(x0, self.window.frames - 1, generator=g)
        return ExportSpec(module=_DecoderExport(self.net).eval(), example_inputs=(x0, z),
                          input_names=["x0", "z"], output_names=["rotations", "trans"])

    @classmethod
    def train_embedded(cls, out_dir=None, steps=None, seed: int = 0, overwrite: bool = False) -> dict:
        """``python -m benchmark train motion-dvae``: retrain the embedded weights (train_motion_dvae).

        ``steps`` is the DVAE phase's step count; the denoising phase gets 2/5 as many."""
        out = Path(out_dir) if out_dir is not None else DEFAULT_WEIGHTS.parent
        target = out / DEFAULT_WEIGHTS.name
        if target.exists() and not overwrite:
            raise FileExistsError(f"{target} exists: pass --force to overwrite it, or --out DIR to write elsewhere")
        kw = {}
        if steps:
            kw = {"steps": int(steps), "denoise_steps": max(1, 2 * int(steps) // 5)}
        _, record = train_motion_dvae(out, seed=seed, **kw)
        return record


# -- training --------------------------------------------------------------------------------
def compute_statistics(poses: torch.Tensor, max_windows: int = 20000, seed: int = 0) -> dict:
    """Standardisation statistics of the states of canonical pose windows (N, F, 69), and the mean
    first-frame state (a seeded subset of ``max_windows`` windows)."""
    if poses.shape[0] > max_windows:
        g = torch.Generator().manual_seed(seed)
        poses = poses[torch.randperm(poses.shape[0], generator=g)[:max_windows]]
    states = pose_to_state(poses)
    flat = states.reshape(-1, STATE_DIM)
    return {"state_mean": flat.mean(0), "state_std": flat.std(0).clamp_min(1e-3), "x0_mean": states[:, 0].mean(0)}


def _check_windows(w: torch.Tensor, what: str) -> torch.Tensor:
    w = torch.as_tensor(w, dtype=torch.float32)
    if w.dim() != 3 or w.shape[-1] != NUM_JOINTS * 3 + 3 or w.shape[1] < 2:
        raise ValueError(f"{what} must be (N, F >= 2, 69) windows (priors.training.motion_windows), got {tuple(w.shape)}")
    return w.contiguous()


def train_motion_dvae(
    out_dir: str | Path | None = None,
    steps: int = 1800,
    denoise_steps: int = 720,
    seed: int = 0,
    *,
    config: dict | None = None,
    batch_size: int = 64,
    lr: float = 1e-3,
    denoise_lr: float = 1e-3,
    windows: torch.Tensor | None = None,
    val_windows: torch.Tensor | None = None,
    rest_joints: torch.Tensor | None = None,
    frames: int = 30,
    stride: int = 10,
    log_every: int = 200,
    val_max_windows: int = 512,
) -> tuple[MotionDVAE, dict]:
    """Train the embedded Motion-DVAE (phase 1: DVAE on clean windows; phase 2: denoising networks on
    noisy copies, prior and decoder frozen) and write ``motion_dvae.pt`` + ``motion_dvae.json``.

    windows / val_windows: (N, F, 69) raw windows (default: ``priors.training.motion_windows`` of the
    synthetic train / val splits, ``frames`` frames every ``stride`` at 30 fps). rest_joints: the
    skeleton of the point losses (default ``priors.training.fixed_rest_skeleton``). The shared loop
    ``priors.training.train_loop`` is used (Adam, cosine decay to 0.1 lr, one thread); the paper
    (HuMoR settings) uses Adamax lr 1e-4 for 200 epochs, too slow for the embedded CPU budget.
    ``out_dir=None`` writes nothing. Returns (model in eval mode, record).
    """
    from priors import training

    cfg = dict(EMBEDDED_CONFIG, **(config or {}))
    data_info: dict = {}
    if windows is None:
        motions = training.load_split_motions("train")
        windows = training.motion_windows(motions, frames, stride, fps=FPS)
        data_info["train"] = {"source": "benchmark.synthetic.splits.build_split('train')", "motions": len(motions),
                              "frames": frames, "stride": stride, "windows": int(windows.shape[0])}
        if val_windows is None:
            try:
                vm = training.load_split_motions("val")
                val_windows = training.motion_windows(vm, frames, frames, fps=FPS, max_windows=val_max_windows, seed=seed)
                data_info["val"] = {"source": "benchmark.synthetic.splits.build_split('val')", "motions": len(vm),
                                    "frames": frames, "stride": frames, "windows": int(val_windows.shape[0])}
            except Exception as exc:
                log.warning("no validation split (%s); training without a validation loss", exc)
                data_info["val"] = {"source": None, "error": f"{type(exc).__name__}: {exc}"}
    else:
        data_info["train"] = {"source": "windows given", "windows": int(windows.shape[0])}
        if val_windows is not None:
            data_info["val"] = {"source": "windows given", "windows": int(val_windows.shape[0])}
    windows = _check_windows(windows, "windows")
    val_windows = _check_windows(val_windows, "val_windows") if val_windows is not None else None
    if rest_joints is None:
        rest_joints, rest_source = training.fixed_rest_skeleton()
    else:
        rest_source = "given"

    training.seed_everything(seed)
    model = MotionDVAE(**cfg)
    t_prep = time.perf_counter()
    poses = canonical_poses(windows)  # the training data: canonical, unwrapped pose sequences
    del windows
    val_poses = canonical_poses(val_windows) if val_windows is not None else None
    stats = compute_statistics(poses, seed=seed)
    prep_wall = time.perf_counter() - t_prep
    with torch.no_grad():
        for k, v in stats.items():
            getattr(model, k).copy_(v)
        model.rest_joints.copy_(torch.as_tensor(rest_joints, dtype=torch.float32))

    # phase 1: the DVAE on clean canonical windows, KL annealing
    anneal = max(1, int(KL_ANNEAL_FRACTION * steps))
    counter = {"dvae": 0, "denoise": 0}

    def dvae_loss(m: MotionDVAE, batch: torch.Tensor) -> dict:
        if m.training:
            counter["dvae"] += 1
            beta = min(1.0, counter["dvae"] / anneal)
        else:
            beta = 1.0
        with torch.no_grad():
            states = pose_to_state(batch)
            pts = body_points(*state_to_motion(states), m.rest_joints)
        return m.dvae_loss(states, pts, beta)

    for p in model.parameters():
        p.requires_grad_(False)
    gen_modules = [model.gen_rnn, model.prior_mean, model.prior_logvar, model.decoder, model.encoder]
    for mod in gen_modules:
        for p in mod.parameters():
            p.requires_grad_(True)
    model.dec_logvar.requires_grad_(True)
    t0 = time.perf_counter()
    r1 = training.train_loop(model, dvae_loss, poses, steps=steps, batch_size=batch_size, seed=seed, lr=lr,
                             log_every=log_every, val_data=val_poses, val_batch=256)
    phase1_wall = time.perf_counter() - t0

    # phase 2: denoising networks on noisy copies; prior, decoder and clean encoder frozen
    with torch.no_grad():
        model.denoise_encoder.load_state_dict(model.encoder.state_dict())
    for p in model.parameters():
        p.requires_grad_(False)
    for mod in (model.denoise_encoder, model.init_state, model.noise):
        for p in mod.parameters():
            p.requires_grad_(True)
    anneal2 = max(1, int(KL_ANNEAL_FRACTION * denoise_steps))

    def denoise_loss(m: MotionDVAE, batch: torch.Tensor) -> dict:
        if m.training:
            counter["denoise"] += 1
            beta, g = min(1.0, counter["denoise"] / anneal2), None
        else:
            beta, g = 1.0, torch.Generator().manual_seed(seed + 1)
        with torch.no_grad():
            noisy, _ = noisy_poses(batch, g)
            states = pose_to_state(noisy)
            obs = body_points(*state_to_motion(states), m.rest_joints)
        return m.denoise_loss(states, obs, beta, generator=g)

    t0 = time.perf_counter()
    r2 = training.train_loop(model, denoise_loss, poses, steps=denoise_steps, batch_size=batch_size, seed=seed + 1,
                             lr=denoise_lr, log_every=log_every, val_data=val_poses, val_batch=256)
    phase2_wall = time.perf_counter() - t0
    for p in model.parameters():
        p.requires_grad_(False)
    model.eval()

    record = {
        "prior": MotionDVAEPrior.name,
        "network": "Motion-DVAE (priors/motion_dvae.py MotionDVAE), embedded size",
        "config": model.config,
        "parameters": model.parameter_counts(),
        "paper_parameters": MotionDVAE(**PAPER_CONFIG).parameter_counts(),
        "data": data_info,
        "rest_skeleton": rest_source,
        "state": "138-D: trans, root aa, 21 body aa, finite-difference velocities x30; canonical first frame (HuMoR)",
        "phase_dvae": {
            "loss": f"Gaussian NLL of the standardised state (learned per-dim variance) + beta*KL(q||p) + {POINT_WEIGHT}*sum squared point errors (m^2; "
                    "22 FK joints + 44 virtual markers), per frame; beta 0->1 over the first "
                    f"{KL_ANNEAL_FRACTION:.0%} of steps",
            "optimiser": {"name": "Adam (shared train_loop)", "lr": lr, "schedule": "cosine to 0.1*lr", "batch_size": batch_size},
            "steps": steps, "train_wall_s": round(phase1_wall, 2), "s_per_step": round(r1.wall_s / steps, 4),
            "final_train": r1.final_train, "final_val": r1.final_val, "history": r1.history,
        },
        "phase_denoise": {
            "loss": "Student-t (Inverse-Gamma per-frame variance) data term on body points + beta*KL_z + KL_noise, per frame",
            "noise": f"axis-angle sigma ~ U{DENOISE_SIGMA_RANGE} rad on all 22 joints; noise prior InvGamma(a0={NOISE_PRIOR_SHAPE}, "
                     f"mean precision 1/{NOISE_PRIOR_SCALE_M}^2)",
            "trained": ["denoise_encoder (initialised from encoder)", "init_state", "noise"],
            "optimiser": {"name": "Adam (shared train_loop)", "lr": denoise_lr, "schedule": "cosine to 0.1*lr", "batch_size": batch_size},
            "steps": denoise_steps, "train_wall_s": round(phase2_wall, 2), "s_per_step": round(r2.wall_s / denoise_steps, 4),
            "final_train": r2.final_train, "final_val": r2.final_val, "history": r2.history,
        },
        "paper_settings_not_used": "Adamax lr 1e-4 (HuMoR), batch 64, 200 epochs, KL annealing over 50 epochs",
        "data_preparation_wall_s": round(prep_wall, 2),
        "seed": seed,
        "torch_threads_training": 1,
        "train_wall_s": round(phase1_wall + phase2_wall, 2),
        **training.environment_record(),
    }
    if out_dir is not None:
        training.save_trained(out_dir, DEFAULT_WEIGHTS.name, model.state_dict(), model.config, record)
    return model, record


def main(argv: list[str] | None = None) -> None:
    """``python -m priors.motion_dvae --out priors/weights``: train the embedded weights."""
    import argparse

    ap = argparse.ArgumentParser(description="Train the embedded Motion-DVAE on the synthetic training split.")
    ap.add_argument("--out", default=str(DEFAULT_WEIGHTS.parent))
    ap.add_argument("--steps", type=int, default=1800)
    ap.add_argument("--denoise-steps", type=int, default=720)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    _, rec = train_motion_dvae(args.out, steps=args.steps, denoise_steps=args.denoise_steps, seed=args.seed)
    print({k: rec[k] for k in ("train_wall_s", "checkpoint_bytes")})


__all__ = [
    "MotionDVAE", "MotionDVAEPrior", "MLP", "Encoder", "InitialStatePredictor", "NoisePredictor",
    "canonicalise", "uncanonicalise", "motion_state", "windows_to_state", "state_to_motion", "body_points",
    "load_official", "read_project_checkpoint", "load_state_strict", "train_motion_dvae", "noisy_poses",
    "canonical_poses", "pose_to_state",
    "PAPER_CONFIG", "EMBEDDED_CONFIG",
]


if __name__ == "__main__":
    main()
