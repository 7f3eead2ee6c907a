"""Motion-DVAE: the networks at any size and their losses (pure torch, no I/O).

See the package docstring (:mod:`priors.motion_dvae`) for the method and the sizes; the canonical
frame and the state vectors are in :mod:`priors.motion_dvae.states`.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from benchmark.core.skeleton import NUM_JOINTS
from priors.motion_dvae.states import FPS, POSE_DIM, STATE_DIM, body_points, state_to_motion


PAPER_CONFIG = {"z_dim": 48, "hidden": 1024, "mlp_hidden": 1024}
EMBEDDED_CONFIG = {"z_dim": 48, "hidden": 256, "mlp_hidden": 256, "feedback": True, "encoder_residual": True}

POINT_WEIGHT = 100.0  # weight of the squared point errors (metres^2) in the DVAE loss
KL_ANNEAL_FRACTION = 0.25  # paper: KL annealing over the first 50 of 200 epochs
NOISE_PRIOR_SHAPE = 100.0  # Inverse-Gamma shape a0 of the per-frame noise variance (large: ~Gaussian)
NOISE_PRIOR_SCALE_M = 0.1  # prior mean precision a0 / b0 = 1 / NOISE_PRIOR_SCALE_M^2
LOGVAR_RANGE = (-12.0, 8.0)
DEC_LOGVAR_RANGE = (-7.0, 2.0)  # decoder variance bounds (standardised units)
DENOISE_INPUT_CLIP = 3.0  # standard deviations, joint rotations of the denoising networks' input (denoise_input)
RESIDUAL_CLIP = 3.0  # standard deviations, the clean encoder's residual input (Encoder, residual=True)
STATE_STD_FLOOR = 1e-3  # the least standard deviation of a state dimension (train.compute_statistics):
# a dimension at it never moves in the training data (a hinge joint's off axes)


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
    """q(z_t | x_0, z_{1:t-1}, x_{t:T}): anti-causal LSTM over states + forward recurrence over z.

    residual=True (feedback wiring only, :meth:`MotionDVAE.infer`): the heads also read the gap
    between the target pose x^_t and the decoded pose x^dec_{t-1}, each standardised dimension
    clipped to +-RESIDUAL_CLIP, through two bias-free Linear maps that start at zero (so the wiring
    starts as the encoder without it) [inferred]."""

    def __init__(self, z_dim: int, hidden: int, mlp_hidden: int, residual: bool = False):
        super().__init__()
        self.z_dim = z_dim
        self.bwd_rnn = nn.LSTM(STATE_DIM, hidden, batch_first=True)
        self.fwd_cell = nn.LSTMCell(z_dim + STATE_DIM, hidden)
        self.post_mean = MLP([2 * hidden, mlp_hidden, mlp_hidden, z_dim])
        self.post_logvar = MLP([2 * hidden, mlp_hidden, mlp_hidden, z_dim])
        self.residual = bool(residual)
        if self.residual:
            self.res_mean = nn.Linear(POSE_DIM, mlp_hidden, bias=False)
            self.res_logvar = nn.Linear(POSE_DIM, mlp_hidden, bias=False)
            with torch.no_grad():
                self.res_mean.weight.zero_()
                self.res_logvar.weight.zero_()

    def backward_features(self, xn: torch.Tensor) -> torch.Tensor:
        """(B, T, S) standardised states -> (B, T, H) anti-causal features b_t (summary of x_{t:T})."""
        out, _ = self.bwd_rnn(torch.flip(xn, [1]))
        return torch.flip(out, [1])

    def start(self, xn: torch.Tensor, x0n: torch.Tensor, b=None):
        """The forward cell's first state (from [0, x^_0]) and the heads' per-frame terms for inputs xn.

        The heads' first Linear acts on [f_{t-1}, b_t]: its b-part is computed for all t at once
        (the same maths as post_mean([f, b]), fewer sequential operations)."""
        if b is None:
            b = self.backward_features(xn)
        state = self.fwd_cell(torch.cat([xn.new_zeros(xn.shape[0], self.z_dim), x0n], -1))
        Hf = state[0].shape[-1]
        lin_m, lin_v = self.post_mean.net[0], self.post_logvar.net[0]
        heads = (F.linear(b[:, 1:], lin_m.weight[:, Hf:], lin_m.bias), F.linear(b[:, 1:], lin_v.weight[:, Hf:], lin_v.bias),
                 lin_m.weight[:, :Hf], lin_v.weight[:, :Hf])
        return state, heads

    def posterior(self, f: torch.Tensor, t: int, heads, gap: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, log-variance) of q(z_t) from the forward state f_{t-1} and :meth:`start`'s heads;
        ``gap`` (B, POSE_DIM): target pose at t minus decoded pose at t-1 (standardised), read only
        by a residual encoder, which needs it."""
        pre_m, pre_v, w_m, w_v = heads
        a_m, a_v = F.linear(f, w_m) + pre_m[:, t - 1], F.linear(f, w_v) + pre_v[:, t - 1]
        if self.residual:
            if gap is None:
                raise ValueError("motion-dvae: a residual encoder needs the decoded state (the feedback wiring)")
            gap = gap.clamp(-RESIDUAL_CLIP, RESIDUAL_CLIP)
            a_m, a_v = a_m + self.res_mean(gap), a_v + self.res_logvar(gap)
        mu = self.post_mean.net[1:](a_m)
        lv = self.post_logvar.net[1:](a_v).clamp(*LOGVAR_RANGE)
        return mu, lv

    def forward(self, xn: torch.Tensor, x0n: torch.Tensor, sample: bool, generator=None, b=None):
        """Posterior over z_{1:T-1} for standardised states xn (B, T, S) and x^_0 (B, S).

        sample: draw z_t from q (reparameterised; ``generator`` for the noise) and feed it back,
        else feed back the posterior mean. Returns (z, q_mean, q_logvar), each (B, T-1, Z).
        """
        B, T, _ = xn.shape
        state, heads = self.start(xn, x0n, b)
        zs, means, logvars = [], [], []
        for t in range(1, T):
            mu, lv = self.posterior(state[0], t, heads)
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
        # residual on the noisy first positions/orientations and the first translation velocity
        # (the observed root path); the rotation velocities (finite differences of noisy rotations,
        # far off the data distribution) start from the data mean (0 standardised)
        base = torch.cat([yn[:, 0, :POSE_DIM + 3], torch.zeros_like(yn[:, 0, POSE_DIM + 3:])], -1)
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


def _lstm_step(x_gates: torch.Tensor, h: torch.Tensor, c: torch.Tensor, w_hh: torch.Tensor, b_hh: torch.Tensor):
    """One step of a torch LSTM (gate order i, f, g, o) whose input term ``x_gates`` = W_ih x + b_ih is given."""
    i, f, g, o = (x_gates + F.linear(h, w_hh, b_hh)).chunk(4, -1)
    c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
    return torch.sigmoid(o) * torch.tanh(c), c


def _randn(like: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """Standard normal noise shaped like ``like``, drawn on the generator's device, moved to like's."""
    dev = generator.device if generator is not None else like.device
    return torch.randn(like.shape, generator=generator, device=dev, dtype=like.dtype).to(like.device)


def gaussian_kl(mq, lq, mp, lp):
    """KL(N(mq, e^lq) || N(mp, e^lp)) per element."""
    return 0.5 * (lp - lq + (torch.exp(lq) + (mq - mp) ** 2) * torch.exp(-lp) - 1.0)


class MotionDVAE(nn.Module):
    """The Motion-DVAE network with its denoising networks (module docstring for the wiring)."""

    def __init__(self, z_dim: int = 48, hidden: int = 1024, mlp_hidden: int = 1024, fps: float = FPS,
                 feedback: bool = False, encoder_residual: bool = False):
        super().__init__()
        self.z_dim, self.hidden, self.mlp_hidden, self.fps = int(z_dim), int(hidden), int(mlp_hidden), float(fps)
        # feedback: the encoders' forward recurrence reads the decoded state x^_{t-1} where it would
        # read x^_0 (see :meth:`infer`); the same parameters, a different wiring
        self.feedback = bool(feedback)
        # encoder_residual: the clean encoder's heads also read target minus decoded pose (Encoder)
        self.encoder_residual = bool(encoder_residual)
        if self.encoder_residual and not self.feedback:
            raise ValueError("motion-dvae: encoder_residual=True needs feedback=True (the residual is taken against the decoded state)")
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
        self.encoder = Encoder(Z, H, M, residual=self.encoder_residual)
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
        return {"z_dim": self.z_dim, "hidden": self.hidden, "mlp_hidden": self.mlp_hidden, "fps": self.fps,
                "feedback": self.feedback, "encoder_residual": self.encoder_residual}

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

    def infer(self, enc: Encoder, xn: torch.Tensor, x0n: torch.Tensor, sample: bool, generator=None, b=None):
        """Posterior over z_{1:T-1} with encoder ``enc`` on standardised inputs xn (B, T, S), and the
        decoding of those z: returns (z, q_mean, q_logvar, h (B, T, H), decoded xn (B, T, S)).

        Without feedback this is ``enc(...)`` followed by :meth:`decode_normalised`. With feedback
        (``self.feedback``) the encoder's forward cell reads [z_t, x^_t] (the decoded standardised
        state at t) instead of [z_t, x^_0], so z_{t+1} is chosen knowing where the decoder is: the
        posterior q(z_t | x_0, z_{1:t-1}, x_{t:T}) conditions on the same variables (x^_{t-1} is a
        deterministic function of x_0 and z_{1:t-1}) [inferred wiring: the paper's conditioning
        inputs are lost in our copy]. Without it the encoder could not see the decoder's accumulated
        increments drift off the data (reconstruction 41 mm off by frame 5, 57 mm over 2 s).
        The generative LSTM is stepped here with its own weights; h and the decoded states equal
        :meth:`gen_features` / :meth:`decode_normalised` of the returned z up to rounding.
        """
        if not self.feedback:
            z, qm, qlv = enc(xn, x0n, sample=sample, generator=generator, b=b)
            h = self.gen_features(x0n, z)
            return z, qm, qlv, h, self.decode_normalised(x0n, z, h)
        B, T, _ = xn.shape
        Z = self.z_dim
        state, heads = enc.start(xn, x0n, b)
        g = self.gen_rnn
        gw_z, gw_x = g.weight_ih_l0[:, :Z], g.weight_ih_l0[:, Z:]
        g_const = F.linear(x0n, gw_x, g.bias_ih_l0)  # the x^_0 part of every generative input
        zeros = x0n.new_zeros(B, self.hidden)
        hg, cg = _lstm_step(g_const, zeros, zeros, g.weight_hh_l0, g.bias_hh_l0)  # h_0 (z_0 = 0)
        dec_lin = self.decoder.net[0]
        dw_h, dw_z = dec_lin.weight[:, :self.hidden], dec_lin.weight[:, self.hidden:]
        dec_rest = self.decoder.net[1:]
        x = x0n
        zs, means, logvars, hs, xs = [], [], [], [hg], [x0n]
        for t in range(1, T):
            gap = xn[:, t, :POSE_DIM] - x[:, :POSE_DIM] if enc.residual else None
            mu, lv = enc.posterior(state[0], t, heads, gap)
            z = mu + torch.exp(0.5 * lv) * _randn(mu, generator) if sample else mu
            hg, cg = _lstm_step(F.linear(z, gw_z) + g_const, hg, cg, g.weight_hh_l0, g.bias_hh_l0)
            x = x + dec_rest(F.linear(hg, dw_h) + F.linear(z, dw_z, dec_lin.bias))
            zs.append(z)
            means.append(mu)
            logvars.append(lv)
            hs.append(hg)
            xs.append(x)
            if t < T - 1:
                state = enc.fwd_cell(torch.cat([z, x], -1), state)
        h, xdec = torch.stack(hs, 1), torch.stack(xs, 1)
        if not zs:
            empty = xn.new_zeros(B, 0, Z)
            return empty, empty, empty, h, xdec
        return torch.stack(zs, 1), torch.stack(means, 1), torch.stack(logvars, 1), h, xdec

    def encode_means(self, xn: torch.Tensor) -> torch.Tensor:
        """(B, T-1, Z) the clean encoder's posterior means for standardised clean states xn (B, T, S)."""
        return self.infer(self.encoder, xn, xn[:, 0], sample=False)[0]

    def prior_nll(self, x0: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """(B,) -1/(T-1) sum_t log N(z_t; prior(h_{t-1})), nats per frame (sum over dims), x0 raw."""
        return self.prior_nll_normalised(self.normalise(x0), z)

    def prior_nll_normalised(self, x0n: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """:meth:`prior_nll` for the standardised first state x0n (B, S)."""
        if z.shape[1] == 0:
            return x0n.new_zeros(x0n.shape[0])
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
    def dvae_loss(self, states: torch.Tensor, points: torch.Tensor, beta: float, point_weight: float = POINT_WEIGHT,
                  root_marker_m: float = 0.0, encoder_states: torch.Tensor | None = None) -> dict:
        """Clean-data loss for canonical states (B, T, 138) and their body points (B, T, P, 3);
        ``point_weight`` multiplies the squared point errors (m^2). ``root_marker_m`` > 0 adds two
        markers that far along the root's x and z axes to the points (the root's heading then weighs
        like a lever of that length: a heading error of theta moves a path of length L by theta*L).
        ``encoder_states``: what the clean encoder reads instead of ``states`` (B, T, 138; a noisy copy
        in the same canonical frame); the decoder's x_0 is its first frame with every dimension but
        the translation held within +-DENOISE_INPUT_CLIP standard deviations (the hinge joints' axes
        that barely vary in the data sit at the 1e-3 std floor, so a noise of 0.05 rad puts them 50
        deviations off, and a decoder fed that x_0 diverged: reconstruction loss 1.5e8); the targets
        stay ``states``."""
        xn = self.normalise(states)
        x0n = xn[:, 0]
        xin = xn
        if encoder_states is not None:
            xin = self.normalise(encoder_states)
            c = DENOISE_INPUT_CLIP
            x0n = torch.cat([xin[:, 0, :3], xin[:, 0, 3:].clamp(-c, c)], -1)
        z, qm, qlv, h, rec_n = self.infer(self.encoder, xin, x0n, sample=True)
        pm, plv = self.prior_params(h[:, :-1])
        lv = self.dec_logvar.clamp(*DEC_LOGVAR_RANGE)
        sq = (rec_n[:, 1:] - xn[:, 1:]).square()
        rec = 0.5 * (sq * torch.exp(-lv) + lv).sum(-1).mean()
        kl = gaussian_kl(qm, qlv, pm, plv).sum(-1).mean()
        rot, trans = state_to_motion(self.unnormalise(rec_n[:, 1:]))
        pts = (body_points(rot, trans, self.rest_joints) - points[:, 1:]).square().sum(-1)
        if root_marker_m:
            gt_rot, _ = state_to_motion(states[:, 1:])
            axes = (rot[..., 0, :, ::2] - gt_rot[..., 0, :, ::2]) * root_marker_m  # (B, T-1, 3, 2): x and z axes
            pts = torch.cat([pts, axes.square().sum(-2)], -1)
        point_sq = pts.sum(-1).mean()
        loss = rec + beta * kl + point_weight * point_sq
        return {"loss": loss, "rec": rec, "kl": kl, "state_mse": sq.mean().detach(), "point_sq_m2": point_sq,
                "point_rmse_m": (pts.mean()).sqrt().detach(), "beta": torch.tensor(float(beta))}

    @staticmethod
    def denoise_input(yn: torch.Tensor) -> torch.Tensor:
        """The denoising networks' view of standardised noisy states (B, T, 138).

        Joint rotation vectors are clipped to +-DENOISE_INPUT_CLIP standard deviations and the rotation
        velocities set to the data mean (0); translation and its velocity (translation is not noised)
        are kept. Many rotation dimensions barely vary in the training data (hinge joints, wrists,
        feet: std at its 1e-3 floor), so axis-angle noise of 0.1 rad put them 100 standard deviations
        off, and the velocities (noisy finite differences x30) 10-20 off; the networks fed these (and
        the decoder fed the resulting x_0) produced motions metres off the observation (V2V 1.1-1.5 m)."""
        c = DENOISE_INPUT_CLIP
        return torch.cat([yn[..., :3], yn[..., 3:POSE_DIM].clamp(-c, c), yn[..., POSE_DIM:POSE_DIM + 3],
                          torch.zeros_like(yn[..., POSE_DIM + 3:])], -1)

    def denoise_forward(self, noisy_states: torch.Tensor, sample: bool, generator=None, nets=None):
        """Denoising inference on noisy canonical states (B, T, 138).

        nets: (encoder, init_state, noise) to use (default: this model's denoising networks).
        Returns dict with x0 (raw, B x 138), z, q_mean, q_logvar, x0 mean/logvar (standardised),
        noise alpha/beta (B, T), decoded standardised states (B, T, S) and features h.
        """
        enc, init, noise = nets if nets is not None else (self.denoise_encoder, self.init_state, self.noise)
        yn = self.denoise_input(self.normalise(noisy_states))
        m0, lv0 = init(yn)
        if sample:
            x0n = m0 + torch.exp(0.5 * lv0) * _randn(m0, generator)
        else:
            x0n = m0
        b = enc.backward_features(yn)
        z, qm, qlv, h, xn = self.infer(enc, yn, x0n, sample=sample, generator=generator, b=b)
        alpha, beta_ = noise(b)
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
