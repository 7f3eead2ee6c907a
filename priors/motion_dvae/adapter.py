"""Motion-DVAE as a :class:`~priors.base.PriorAdapter` (and its ONNX decoder wrapper)."""

from __future__ import annotations

import contextlib
import copy
import math

import torch
from torch import nn

from benchmark.core.interpolate import lerp_frames, slerp_frames
from benchmark.core.skeleton import NUM_JOINTS
from priors.base import (
    Decoded, ExportableDecoder, ExportSpec, FitBatch, MotionDenoiser, MotionEncoder, PaperNetwork, PriorAdapter,
    Trainable, WindowSpec,
)
from priors.motion_dvae import checkpoint
from priors.motion_dvae.model import (
    DENOISE_INPUT_CLIP,
    STATE_STD_FLOOR,
    MotionDVAE,
    PAPER_CONFIG,
)
from priors.motion_dvae.states import (
    FPS,
    STATE_DIM,
    body_points,
    canonicalise,
    motion_state,
    state_to_motion,
    uncanonicalise,
)
from priors.motion_dvae.checkpoint import DEFAULT_WEIGHTS, OFFICIAL_UNKNOWN
from priors.training import embedded_out_dir


# -- the adapter -----------------------------------------------------------------------------
# What the encoder reads of a motion is held to what the training data covers. The dimensions at the
# deviation floor (joint axes the training data never turns: 48 of the embedded model's 138) are set
# to their training mean in every frame, and the decoder's first state is held within X0_HOLD
# deviations (translation excepted), the bound the model's noisy-input training holds x_0 to. A
# per-frame fit a degree off turns those axes 35 deviations out, and the decoder fed that diverged
# (encoder-check at 2 degrees: 525.6 mm unheld, 245.2 with x_0 held, 183.9 with the floor axes at
# their mean too; clean 47.5 -> 46.8).
X0_HOLD = DENOISE_INPUT_CLIP


def hold_to_training_support(xn: torch.Tensor, state_std: torch.Tensor, bound: float = X0_HOLD) -> tuple[torch.Tensor, torch.Tensor]:
    """(xn, x0n): standardised states (B, T, 138) with the floor dimensions at their mean (0), and
    their first frame with every dimension but the translation clamped to +-bound."""
    xn = torch.where(state_std <= STATE_STD_FLOOR * (1 + 1e-6), torch.zeros_like(xn), xn)
    x0n = torch.cat([xn[:, 0, :3], xn[:, 0, 3:].clamp(-bound, bound)], -1)
    return xn, x0n


def _regular_30fps(timestamps: torch.Tensor, fps: float = FPS, tol: float = 1e-4) -> bool:
    t = timestamps.to(torch.float64)
    if t.shape[1] < 2:
        return False
    return bool(((t[:, 1:] - t[:, :-1]) - 1.0 / fps).abs().max() < tol)


def _grid_frames(window_s: float, frames: int = 30, fps: float = FPS) -> int:
    """Grid length the completion protocol asks for (mirrors benchmark.protocols.fit_state.decode_grid)."""
    return max(1, math.ceil(window_s * fps / frames - 1e-9)) * frames


class _DecoderExport(nn.Module):
    """(x0n (B, 138) standardised, z (B, T, 48)) -> (rotations (B, T+1, 22, 3, 3), trans (B, T+1, 3)) canonical."""

    def __init__(self, model: MotionDVAE):
        super().__init__()
        self.model = model

    def forward(self, x0n: torch.Tensor, z: torch.Tensor):
        states = self.model.unnormalise(self.model.decode_normalised(x0n, z))
        rot, trans = state_to_motion(states)
        return rot, trans


class MotionDVAEPrior(MotionEncoder, MotionDenoiser, ExportableDecoder, PaperNetwork, Trainable, PriorAdapter):
    """Motion-DVAE as a completion prior (module docstring: latents, prior term, frames)."""

    name = "motion-dvae"
    paper = "Fiche et al., Motion-DVAE: Unsupervised learning for fast human motion denoising (MIG 2023)"
    window = WindowSpec(kind="fixed", frames=30, fps=FPS)
    encodes_translation = True
    encodes_root_orientation = True
    heading_normalised = True
    joints = tuple(range(1, NUM_JOINTS))
    shape_conditioned = False
    sixd_layout = None
    frozen_network = "net"
    default_weights = DEFAULT_WEIGHTS
    prior_term_kind = "learned"  # or "l2"
    # 2: the first state is a latent in standardised units ("x0n", was raw "x0"), and an encoded
    # motion is held to the training data's support (hold_to_training_support; docs/priors.md)
    adapter_revision = 2

    def __init__(self, size: str = "embedded", weights: str | None = None, device: str | torch.device = "cpu"):
        super().__init__(size=size, weights=weights, device=device)
        if size == "paper":
            if weights is None:
                raise ValueError(f"motion-dvae size 'paper' needs official weights, and none are known: {OFFICIAL_UNKNOWN}. "
                                 "Use size='embedded' (the project's weights), or map an official file with "
                                 "priors.motion_dvae.checkpoint.load_official(path, key_map=...)")
            self.net, self.checkpoint = checkpoint.load(weights, "paper")
        elif size == "embedded":
            self.net, self.checkpoint = checkpoint.load(self.embedded_weights(weights), "embedded")
            self.weights_path = str(self.checkpoint.file)
        else:
            raise ValueError(f"motion-dvae: unknown size {size!r}; expected 'embedded' or 'paper'")
        self.freeze_network(device)

    @classmethod
    def from_network(cls, net: MotionDVAE, device="cpu") -> "MotionDVAEPrior":
        """An adapter around an in-memory network (tests, freshly trained models)."""
        self = cls.__new__(cls)
        PriorAdapter.__init__(self, size="embedded", weights=None)
        self.net = net
        self.freeze_network(device)
        return self

    @property
    def z_dim(self) -> int:
        return self.net.z_dim

    @classmethod
    def paper_network(cls) -> MotionDVAE:
        """The paper-size network (z 48, LSTM hidden 1024, MLP hidden 1024) with random weights."""
        return MotionDVAE(**PAPER_CONFIG).eval()

    # -- completion API
    def init_latents(self, batch: FitBatch, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """x0n = the training mean first-frame state (standardised); z = an ancestral sample of the
        learned prior over the protocol's grid (``ceil(window_s) * 30`` frames, so T - 1 latents)."""
        T = _grid_frames(batch.window_s, self.window.frames, self.window.fps)
        B = batch.batch_size
        with torch.no_grad():
            x0 = self.net.x0_mean.expand(B, -1).clone()
            z = self.net.sample_prior(x0, T - 1, generator=generator)
        return {"x0n": self.net.normalise(x0), "z": z}

    def mean_latents(self, batch: FitBatch) -> dict[str, torch.Tensor]:
        """x0n = the training mean first-frame state (standardised); z = the learned prior's mean path: the ancestral
        pass of :meth:`init_latents` with every step at its conditional mean (temperature 0)."""
        T = _grid_frames(batch.window_s, self.window.frames, self.window.fps)
        with torch.no_grad():
            x0 = self.net.x0_mean.expand(batch.batch_size, -1).clone()
            # temperature 0: z_t = the conditional mean (the noise drawn is multiplied by 0; a private
            # generator keeps the global random state untouched)
            z = self.net.sample_prior(x0, T - 1, generator=torch.Generator(x0.device).manual_seed(0), temperature=0.0)
        return {"x0n": self.net.normalise(x0), "z": z}

    def _check_latents(self, latents: dict, where: str):
        """(x0n, z) of ``latents``: the standardised first state (B, 138) and the latents (B, T-1, Z)."""
        if "x0n" not in latents or "z" not in latents:
            hint = (" ('x0' is the raw first state of adapter revision 1; standardise it with net.normalise and "
                    "pass it as 'x0n')" if "x0" in latents else "")
            raise ValueError(f"motion-dvae.{where}: latents must hold 'x0n' (B, {STATE_DIM}, the first state standardised) "
                             f"and 'z' (B, T-1, {self.z_dim}); got keys {sorted(latents)}{hint}")
        x0, z = latents["x0n"], latents["z"]
        if x0.dim() != 2 or x0.shape[1] != STATE_DIM:
            raise ValueError(f"motion-dvae.{where}: latents['x0n'] must be (B, {STATE_DIM}), got {tuple(x0.shape)}")
        if z.dim() != 3 or z.shape[0] != x0.shape[0] or z.shape[2] != self.z_dim:
            raise ValueError(f"motion-dvae.{where}: latents['z'] must be (B, T-1, {self.z_dim}) with B = {x0.shape[0]}, got {tuple(z.shape)}")
        return x0, z

    def decode(self, latents: dict[str, torch.Tensor], timestamps: torch.Tensor, shape: torch.Tensor | None = None) -> Decoded:
        """Motion at the 30 fps grid ``timestamps`` (B, T) with T = z.shape[1] + 1 (frame 0 = x0):
        rotations (B, T, 22, 3, 3) and translation (B, T, 3) in the canonical frame."""
        x0n, z = self._check_latents(latents, "decode")
        B, T = timestamps.shape
        if B != x0n.shape[0] or T != z.shape[1] + 1:
            raise ValueError(f"motion-dvae.decode: timestamps {tuple(timestamps.shape)} must be (B, T) = "
                             f"({x0n.shape[0]}, {z.shape[1] + 1}) (one frame per latent z_t plus frame 0)")
        if T > 1 and not _regular_30fps(timestamps, self.window.fps):
            raise ValueError("motion-dvae.decode: timestamps must be a regular 30 fps grid (the model is recurrent at 30 fps); "
                             "the protocol interpolates to other times")
        with cudnn_rnn_backward([self.net]):
            states = self.net.unnormalise(self.net.decode_normalised(x0n, z))
        rot, trans = state_to_motion(states)
        return Decoded(rotations=rot, trans=trans, extra={"state": states})

    def prior_term(self, latents: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B,) learned: -1/(T-1) sum_t log N(z_t; prior(h_{t-1})); l2: mean over frames of |z_t|^2."""
        x0n, z = self._check_latents(latents, "prior_term")
        if self.prior_term_kind == "learned":
            with cudnn_rnn_backward([self.net]):
                return self.net.prior_nll_normalised(x0n, z)
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
        """Posterior means ``{"x0n": (B, 138), "z": (B, T-1, 48)}`` of a motion.

        The motion is canonicalised at its first frame (decode returns the canonical frame: the
        caller aligns heading and ground-plane offset) and, if its timestamps are not a 30 fps grid,
        resampled to one from its first timestamp (then T is the grid's length). The standardised
        states are held to the training data's support (:func:`hold_to_training_support`: the axes
        the data never turns at their mean, the first state within ``X0_HOLD`` deviations). x0n is
        the held first state (x_0 is given in the DVAE); z_t the clean encoder's posterior means on
        the held states, fed back, decoding from that x0n.
        """
        states, *_ = self._prepare(rotations, trans, timestamps, "encode_motion")
        xn, x0n = hold_to_training_support(self.net.normalise(states), self.net.state_std)
        z = self.net.infer(self.net.encoder, xn, x0n, sample=False)[0]
        return {"x0n": x0n, "z": z}

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
            gen = torch.Generator().manual_seed(seed)  # CPU draws, moved: the same noise on any device
            losses = []
            with torch.enable_grad(), cudnn_rnn_backward(nets):
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
        """ONNX: (x0n (B, 138), z (B, T, 48)) -> (rotations (B, T+1, 22, 3, 3), trans (B, T+1, 3)).

        The canonical-frame decode path of :meth:`decode` (one LSTM over the sequence, MLP heads,
        axis-angle -> matrices), on the fit's latents (x0n standardised). Batch is dynamic; T is the
        example's (29 latents, a 1 s window) and should be taken as fixed in the exported graph.
        Example latents: the training mean first state and an ancestral prior sample (seed 0).
        """
        g = torch.Generator().manual_seed(0)
        with torch.no_grad():
            x0 = self.net.x0_mean.expand(2, -1).clone()
            z = self.net.sample_prior(x0, self.window.frames - 1, generator=g)
        return ExportSpec(module=_DecoderExport(self.net).eval(), example_inputs=(self.net.normalise(x0), z),
                          input_names=["x0n", "z"], output_names=["rotations", "trans"])

    @classmethod
    def train_embedded(cls, out_dir=None, steps=None, seed: int = 0, overwrite: bool = False, dataset=None) -> dict:
        """``python -m benchmark train motion-dvae``: retrain the embedded weights (train_motion_dvae).

        ``steps`` is the DVAE phase's step count; the denoising phase gets 2/5 as many."""
        from priors.motion_dvae.train import train_motion_dvae

        out = embedded_out_dir(out_dir, DEFAULT_WEIGHTS, overwrite)
        kw = {}
        if steps is not None:
            kw = {"steps": int(steps), "denoise_steps": max(1, 2 * int(steps) // 5)}
        _, record = train_motion_dvae(out, seed=seed, dataset=dataset, **kw)
        return record


@contextlib.contextmanager
def cudnn_rnn_backward(modules):
    """Where a gradient flows through the frozen network's LSTMs on CUDA: cuDNN computes an RNN's
    backward only in training mode ("cudnn RNN backward can only be called in training mode"), and
    the fits differentiate the latents through the network frozen in eval mode. Its LSTMs (one
    layer, or no dropout between layers: the same function in either mode) are put in training mode
    for the call; others run without cuDNN. Nothing changes on the CPU or without a gradient."""
    rnns = [m for mod in modules for m in mod.modules() if isinstance(m, nn.RNNBase) and not m.training]
    if not rnns or not torch.is_grad_enabled() or rnns[0].weight_ih_l0.device.type != "cuda":
        yield
        return
    if any(m.num_layers > 1 and m.dropout > 0 for m in rnns):
        with torch.backends.cudnn.flags(enabled=False):
            yield
        return
    for m in rnns:
        m.train(True)
    try:
        yield
    finally:
        for m in rnns:
            m.train(False)
