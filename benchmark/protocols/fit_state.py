"""The state of a completion fit and the pieces every fit and search shares (split from
:mod:`benchmark.protocols.completion`): the optimised variables
(:class:`FitState`), body parameters at any time, the initial state, the optimiser, and the
data term on subsets used by the coarse searches (facing, limb start)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import roma
import torch

from benchmark.core.interpolate import lerp_frames, slerp_frames
from benchmark.metrics.static_chamfer import StaticChamfer
from priors.base import Decoded, FitBatch, PriorAdapter

@dataclass
class FitState:
    """Everything optimised for one batch, and how to turn it into body parameters at any time."""

    adapter: PriorAdapter
    latents: dict
    shape_param: torch.Tensor  # (B, S)
    obs_t: torch.Tensor  # (B, n) observed timestamps
    window_s: float
    root: torch.Tensor | None = None  # (B, n, 6) free root orientation per observed frame
    trans: torch.Tensor | None = None  # (B, n, 3) free translation per observed frame
    heading: torch.Tensor | None = None  # (B, 1) free heading angle
    offset: torch.Tensor | None = None  # (B, 3) free offset
    bounded_shape: bool = True

    def shape(self) -> torch.Tensor:
        return torch.sigmoid(self.shape_param) if self.bounded_shape else self.shape_param

    def parameters(self) -> list[torch.Tensor]:
        params = [*self.latents.values(), self.shape_param]
        params += [p for p in (self.root, self.trans, self.heading, self.offset) if p is not None]
        return params


def decode_grid(adapter: PriorAdapter, window_s: float, B: int, device) -> torch.Tensor:
    """The decoder's own frame grid for fixed-window priors, covering the window."""
    w = adapter.window
    per_window = w.frames
    n_windows = max(1, math.ceil(window_s * w.fps / per_window - 1e-9))
    t = torch.arange(n_windows * per_window, dtype=torch.float64, device=device) / w.fps
    return t.expand(B, -1)


def body_parameters(state: FitState, timestamps: torch.Tensor, observed: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Local rotations (B, T, 22, 3, 3) and translation (B, T, 3) at ``timestamps`` (B, T).

    ``observed`` says the timestamps are the observed ones (no interpolation of per-frame variables).
    """
    a = state.adapter
    kind = a.window.kind
    shape = state.shape() if a.shape_conditioned else None
    if kind == "per-frame":
        dec = a.decode(state.latents, state.obs_t, shape)
        rot = dec.rotations if observed else slerp_frames(dec.rotations, state.obs_t, timestamps)
        trans = None if dec.trans is None else (dec.trans if observed else lerp_frames(dec.trans, state.obs_t, timestamps))
    elif kind == "fixed":
        grid = decode_grid(a, state.window_s, timestamps.shape[0], timestamps.device)
        dec = a.decode(state.latents, grid, shape)
        rot = slerp_frames(dec.rotations, grid, timestamps)
        trans = None if dec.trans is None else lerp_frames(dec.trans, grid, timestamps)
    elif kind == "continuous":
        dec = a.decode(state.latents, timestamps, shape)
        rot, trans = dec.rotations, dec.trans
    else:
        raise ValueError(f"prior {a.name!r}: unknown window kind {kind!r}")
    _check_decoded(a, Decoded(rot, trans), timestamps)
    return apply_free_rigid(state, rot, trans, timestamps, observed)


def apply_free_rigid(state: FitState, rot: torch.Tensor, trans: torch.Tensor | None, timestamps: torch.Tensor,
                     observed: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The protocol's free rigid parameters of ``state`` composed with decoded (rot, trans) at
    ``timestamps`` (B, T): per-observed-frame root orientation (SLERP-ed) on the root, then the
    heading about y on root and translation, then per-observed-frame translation (LERP-ed) and the
    offset added. ``observed``: the timestamps are the observed ones (no interpolation)."""
    if state.root is not None:
        R = roma.special_gramschmidt(state.root.unflatten(-1, (3, 2)))
        R = R if observed else slerp_frames(R, state.obs_t, timestamps)
        rot = torch.cat([(R @ rot[:, :, 0])[:, :, None], rot[:, :, 1:]], dim=2)
    if state.heading is not None:
        zero = torch.zeros_like(state.heading)
        H = roma.rotvec_to_rotmat(torch.cat([zero, state.heading, zero], dim=-1))[:, None]  # (B, 1, 3, 3)
        rot = torch.cat([(H[:, :, None] @ rot[:, :, :1]), rot[:, :, 1:]], dim=2)
        if trans is not None:
            trans = (H @ trans[..., None])[..., 0]
    if state.trans is not None:
        free = state.trans if observed else lerp_frames(state.trans, state.obs_t, timestamps)
        trans = free if trans is None else trans + free
    if state.offset is not None:
        trans = trans + state.offset[:, None]
    return rot, trans


def _check_decoded(adapter, dec: Decoded, timestamps: torch.Tensor) -> None:
    B, T = timestamps.shape
    if dec.rotations.shape[:3] != (B, T, 22) or dec.rotations.shape[-2:] != (3, 3):
        raise ValueError(
            f"prior {adapter.name!r}: decode returned rotations of shape {tuple(dec.rotations.shape)}, "
            f"expected {(B, T, 22, 3, 3)}"
        )
    if dec.trans is not None and dec.trans.shape != (B, T, 3):
        raise ValueError(f"prior {adapter.name!r}: decode returned trans {tuple(dec.trans.shape)}, expected {(B, T, 3)}")


LATENT_INITS = ("sample", "mean")  # objective.latent_init (initial_latents)


def initial_latents(adapter: PriorAdapter, batch: FitBatch, generator: torch.Generator,
                    latent_init: str = "sample") -> dict[str, torch.Tensor]:
    """A fit's starting latents: ``latent_init="sample"`` (table1 v1-v2, docs/protocol.md): the adapter's
    ``init_latents`` (a random prior sample, or a deterministic encoder output); ``"mean"`` (table1
    v3): the prior's mean (``mean_latents``) where the adapter's start is a random sample, else its
    ``init_latents`` (deterministic already)."""
    if latent_init not in LATENT_INITS:
        raise ValueError(f"latent_init {latent_init!r}: choose one of {', '.join(LATENT_INITS)}")
    latents = adapter.mean_latents(batch) if latent_init == "mean" else None
    return adapter.init_latents(batch, generator) if latents is None else latents


def init_state(adapter: PriorAdapter, body, batch: FitBatch, generator: torch.Generator, device,
               data_term: StaticChamfer | None = None, search_heading: bool = True,
               latent_init: str = "sample") -> FitState:
    """The initial state of a fit (see module docstring). ``data_term``: the Chamfer against
    ``batch``'s observed points (frames flattened), when the caller already built it.
    ``search_heading``: run the 8-yaw T-pose search (protocol v1); False leaves the facing at +z.
    ``latent_init``: :func:`initial_latents`."""
    B, n = batch.batch_size, batch.num_observed
    latents = {k: v.detach().to(device).clone().requires_grad_(True)
               for k, v in initial_latents(adapter, batch, generator, latent_init).items()}
    bounded = body.name == "anny"
    default = body.default_shape(B).to(device)
    shape_param = (torch.logit(default.clamp(1e-4, 1 - 1e-4)) if bounded else default).clone().requires_grad_(True)
    with torch.no_grad():
        rest = body.prepare(default)
        tpose = body.skin(rest, torch.eye(3, device=device).expand(B, 1, 22, 3, 3), torch.zeros(B, 1, 3, device=device))
        rest_centroid = tpose.vertices[:, 0].mean(1)  # (B, 3)
        mask = torch.arange(batch.points.shape[2], device=device) < batch.lengths[..., None]
        cen = (batch.points * mask[..., None]).sum(2) / batch.lengths.clamp_min(1)[..., None]  # (B, n, 3)
        trans0 = cen - rest_centroid[:, None]
    state = FitState(adapter=adapter, latents=latents, shape_param=shape_param, obs_t=batch.timestamps,
                     window_s=batch.window_s, bounded_shape=bounded)
    if not adapter.encodes_translation:
        state.trans = trans0.clone().requires_grad_(True)
    if not adapter.encodes_root_orientation:
        eye6 = torch.eye(3, device=device)[:, :2].reshape(6)
        state.root = eye6.expand(B, n, 6).clone().requires_grad_(True)
    if adapter.heading_normalised:
        state.heading = torch.zeros(B, 1, device=device, requires_grad=True)
    if adapter.encodes_translation:
        state.offset = trans0.mean(1).clone().requires_grad_(True)
    if search_heading:
        _initial_heading(state, body, batch, data_term)
    return state


HEADING_CANDIDATES = 8


@torch.no_grad()
def _initial_heading(state: FitState, body, batch: FitBatch, data_term: StaticChamfer | None = None) -> None:
    """Coarse search of the initial facing direction, the same for every prior.

    The body is tried at HEADING_CANDIDATES yaw angles (about y, applied to the free root
    orientation or the free heading) and each sequence keeps the yaw with the lowest initial data
    term. Without it, every prior starts facing +z and a subject walking the other way is often
    fitted backwards, whatever the prior.
    """
    if state.root is None and state.heading is None:
        return
    B, n = batch.batch_size, batch.num_observed
    if data_term is None:
        data_term = StaticChamfer(batch.points.flatten(0, 1), batch.lengths.flatten(0, 1))
    subset = body.loss_vertex_indices(1000)
    rest = body.prepare(state.shape())
    base_root = None if state.root is None else state.root.detach().clone()
    base_heading = None if state.heading is None else state.heading.detach().clone()
    scores = []
    for k in range(HEADING_CANDIDATES):
        yaw = 2 * math.pi * k / HEADING_CANDIDATES
        set_yaw(state, base_root, base_heading, torch.full((B,), yaw, device=batch.points.device))
        rot, trans = body_parameters(state, batch.timestamps, observed=True)
        verts = body.skin(rest, rot, trans, vertex_indices=subset).vertices
        d = data_term(verts.flatten(0, 1))
        scores.append(d.view(B, n).mean(1))
    best = torch.stack(scores, 1).argmin(1).to(batch.points.dtype)  # (B,)
    set_yaw(state, base_root, base_heading, 2 * math.pi * best / HEADING_CANDIDATES)


def set_yaw(state: FitState, base_root, base_heading, yaw: torch.Tensor) -> None:
    if state.heading is not None:
        state.heading.copy_(base_heading + yaw[:, None])
        return
    zero = torch.zeros_like(yaw)
    Y = roma.rotvec_to_rotmat(torch.stack([zero, yaw, zero], -1))[:, None]  # (B, 1, 3, 3)
    R = roma.special_gramschmidt(base_root.unflatten(-1, (3, 2)))
    state.root.copy_((Y @ R)[..., :2].flatten(-2))


def parameter_groups(state: FitState, lr: float, shape_lr_scale: float = 1.0) -> list:
    """The optimiser's parameters of ``state``: one group at ``lr``, or, with ``shape_lr_scale`` != 1,
    the body shape in a group of its own at ``lr * shape_lr_scale`` (protocol v2's ``objective.shape_lr_scale``)."""
    params = state.parameters()
    if shape_lr_scale == 1.0:
        return params
    return [{"params": [p for p in params if p is not state.shape_param]},
            {"params": [state.shape_param], "lr": lr * shape_lr_scale}]


LOG_EVERY = 25  # optimisation history: the first, every 25th and the last step


def optimise(prior_name: str, parameters, steps: int, lr: float, lr_final_fraction: float, step_loss,
             callback=None) -> list[dict]:
    """The protocols' one optimiser: Adam at ``lr``, cosine-annealed to ``lr * lr_final_fraction``
    over ``steps``.

    ``step_loss(step)`` returns ``(loss, log)``: the scalar loss to minimise and a zero-argument
    callable giving the history entry's values (called on logged steps only). A non-finite loss
    raises FloatingPointError naming the prior and the step. ``callback(step, loss)`` is called
    after every step. Returns the history (a list of ``{"step": ..., **log()}``).
    """
    opt = torch.optim.Adam(parameters, lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(steps, 1), eta_min=lr * lr_final_fraction)
    history = []
    for step in range(steps):
        adam_step(opt, prior_name, step_loss, step, history, step == 0 or step == steps - 1 or step % LOG_EVERY == 0,
                  callback)
        sched.step()
    return history


def adam_step(opt, prior_name: str, step_loss, step: int, history: list, logged: bool, callback=None) -> None:
    """One optimiser step of :func:`optimise` and :func:`optimise_to_plateau`: the loss of
    ``step_loss(step)`` (a non-finite one raises FloatingPointError naming the prior and the step),
    its gradient, the step; the history entry when ``logged``; ``callback(step, loss)``."""
    opt.zero_grad(set_to_none=True)
    loss, log = step_loss(step)
    if not torch.isfinite(loss):
        raise FloatingPointError(f"prior {prior_name!r}: non-finite loss at step {step}")
    loss.backward()
    opt.step()
    if logged:
        history.append({"step": step, **log()})
    if callback is not None:
        callback(step, float(loss.detach()))


@dataclass(frozen=True)
class PlateauRule:
    """The step rule of table1 and sls protocol v6 (``objective.step_rule: plateau``): descend at the
    constant learning rate until every sequence of the batch has reached its plateau, then anneal.

    Every ``check_every`` steps, each sequence's objective (its data term plus its weighted prior
    term: what the optimiser minimises) is compared over the last ``window`` steps (means of
    ``smoothing`` steps at each end): its relative change ``(f[s - window] - f[s]) / f[s - window]``.
    A sequence stops descending at the first check where its change is within ``tolerance`` either
    way (still falling: not there yet; rising: the step is too large for where it is) and is held
    there; the descent ends when every sequence is held, or at the step cap; then ``anneal_steps``
    steps of cosine decay from ``lr`` to ``lr * lr_final_fraction`` settle Adam's jitter. A sequence
    is *converged* when its change was within ``tolerance`` when it stopped descending: it is judged at the full, constant learning
    rate, so a schedule that has already shrunk the steps cannot make a fit that still descends
    look flat (the flaw of the versions 1-5 flag).

    ``floor``: the change is relative to ``max(f[s - window], floor)``: an objective that falls to
    about 0 (sls's landmark term, fitted exactly by a free body) has a relative change that is all
    jitter, so below ``floor`` the tolerance is absolute, ``tolerance * floor``. 0 (table1): purely
    relative.

    ``reductions``: a sequence that meets the rule first has its step scaled by ``factor`` (its own
    learning rate, ``lr * factor ** stage``) and is judged anew once a whole window has passed at
    that rate; it is held when it meets the rule at its ``reductions``-th reduced rate. 0 (table1
    version 6): held at the first plateau, at the full rate. At the full rate Adam's steps knock a
    fit between basins; the reduced rates let it settle in the one it is in (docs/table1.md,
    "Robustness of version 6"). ``min_steps``: no sequence is held before that many descent steps
    (the robustness check's longer probe: it keeps descending at its last rate).

    ``rate_scaled``: the tolerance at a reduced rate is ``tolerance * factor ** stage``, the change
    a window at that rate shows when the fit descends as fast, per unit of step, as one that the
    rule would pass at the full rate. False (table1 version 7): the same tolerance at every rate,
    which at 0.09 x the rate passes a fit descending 11 x faster per unit of step.
    """

    window: int = 50
    tolerance: float = 0.005
    smoothing: int = 10
    check_every: int = 10
    anneal_steps: int = 50
    floor: float = 0.0
    reductions: int = 0
    factor: float = 0.3
    min_steps: int = 0
    rate_scaled: bool = False

    def tolerance_at(self, stage: torch.Tensor) -> torch.Tensor:
        """(B,) float64 tolerance of sequences at rate stages ``stage`` ((B,) reductions taken)."""
        tol = torch.full(stage.shape, self.tolerance, dtype=torch.float64)
        return tol * self.factor ** stage.double() if self.rate_scaled else tol

    @classmethod
    def from_spec(cls, value) -> "PlateauRule":
        """The rule of an ``objective.plateau`` mapping (missing keys keep their defaults)."""
        if value is None:
            return cls()
        known = ("window", "tolerance", "smoothing", "check_every", "anneal_steps", "floor", "reductions", "factor",
                 "min_steps", "rate_scaled")
        unknown = set(value) - set(known)
        if unknown:
            raise ValueError(f"objective.plateau: unknown key(s) {sorted(unknown)}; known: {', '.join(known)}")
        if not isinstance(value.get("rate_scaled", False), bool):
            raise ValueError(f"objective.plateau: rate_scaled must be true or false, got {value['rate_scaled']!r}")
        rule = cls(**{k: (v if k == "rate_scaled" else float(v) if k in ("tolerance", "floor", "factor") else int(v))
                      for k, v in value.items()})
        if (rule.window < 1 or rule.smoothing < 1 or rule.check_every < 1 or rule.anneal_steps < 0 or rule.tolerance < 0
                or rule.floor < 0 or rule.reductions < 0 or rule.min_steps < 0 or not 0 < rule.factor < 1):
            raise ValueError(f"objective.plateau: {value!r}: window, smoothing and check_every must be >= 1, "
                             "anneal_steps, tolerance, floor, reductions and min_steps >= 0, factor in (0, 1)")
        return rule

    @property
    def min_descent(self) -> int:
        """The fewest descent steps before the first check can judge a plateau."""
        return self.window + self.smoothing

    def decrease(self, trace: list[torch.Tensor]) -> torch.Tensor:
        """(B,) float64 relative decrease of the objective over the last ``window`` steps of
        ``trace`` (a list of (B,) per-step objectives, at least ``min_descent`` long; negative: it rose)."""
        d = torch.stack([t.detach().double().cpu() for t in trace[-self.min_descent:]])
        k = self.smoothing
        start, last = d[:k].mean(0), d[-k:].mean(0)
        if self.floor > 0:
            return (start - last) / start.clamp_min(self.floor)
        return torch.where(start > 0, (start - last) / start, torch.zeros_like(start))


def optimise_to_plateau(prior_name: str, parameters, max_steps: int, lr: float, lr_final_fraction: float, step_loss,
                        trace: list, rule: PlateauRule, callback=None) -> tuple[list[dict], dict]:
    """Adam at the constant ``lr``, each sequence stopping at its own plateau
    (:class:`PlateauRule`), then ``rule.anneal_steps`` steps of cosine decay to
    ``lr * lr_final_fraction`` for every sequence.

    A sequence that meets the rule at a check is held where it is (its variables are put back after
    every later step of the descent: the first dimension of every parameter is the batch); the
    descent ends when every sequence is held, or after ``max_steps - rule.anneal_steps`` steps, when
    the sequences still moving are judged as they are. ``step_loss(step)`` as in :func:`optimise`;
    it must append the step's (B,) per-sequence objective to ``trace``. A cap below the rule's least
    steps (``min_descent + anneal_steps``, e.g. the smoke profile's) runs :func:`optimise`'s cosine
    schedule over the cap instead and flags every sequence unconverged (``plateau_decrease`` None).

    Returns the history and ``{"steps": total steps, "descent_steps": (B,) list, the step each
    sequence stopped descending at, "plateau_decrease": (B,) list, "converged": (B,) list of bool,
    "stopped": "plateau" | "cap"}``."""
    if max_steps < rule.min_descent + rule.anneal_steps:
        history = optimise(prior_name, parameters, max_steps, lr, lr_final_fraction, step_loss, callback=callback)
        B = int(trace[-1].shape[0]) if trace else 0
        return history, {"descent_steps": [0] * B, "steps": max_steps, "stopped": "cap below the rule's least steps",
                         "plateau_decrease": [None] * B, "converged": [False] * B}
    opt = torch.optim.Adam(parameters, lr=lr)
    tensors = [p for group in opt.param_groups for p in group["params"]]
    history = []
    descent_cap = max_steps - rule.anneal_steps
    step = 0
    held = held_on = decrease = stopped_at = snapshot = stage = since = scale_on = None

    while step < descent_cap:
        before = None
        if scale_on is not None:  # some sequence descends at a reduced rate: its step is scaled below
            before = [p.detach().clone() for p in tensors]
        adam_step(opt, prior_name, step_loss, step, history, step % LOG_EVERY == 0, callback)
        step += 1
        if before is not None:
            _scale_steps(tensors, before, scale_on)
        if held is None:  # the batch size, known from the first step's objective
            B = int(trace[-1].shape[0])
            bad = [tuple(p.shape) for p in tensors if p.dim() == 0 or p.shape[0] != B]
            if bad:
                raise ValueError(f"prior {prior_name!r}: the plateau rule holds sequences one by one and needs every "
                                 f"optimised variable batch first ({B} sequences); got shapes {bad}")
            held = torch.zeros(B, dtype=torch.bool)
            decrease = torch.full((B,), float("nan"), dtype=torch.float64)
            stopped_at = torch.full((B,), descent_cap, dtype=torch.long)
            snapshot = [p.detach().clone() for p in tensors]
            stage = torch.zeros(B, dtype=torch.long)
            since = torch.zeros(B, dtype=torch.long)  # descent steps since the sequence's rate last changed
        since += 1
        with torch.no_grad():
            if bool(held.any()):  # the held sequences stay where they stopped
                for p, snap in zip(tensors, snapshot):
                    p[held_on] = snap[held_on]
        if step >= rule.min_descent and (step % rule.check_every == 0 or step == descent_cap):
            change = rule.decrease(trace)
            flat = ~held & (change.abs() <= rule.tolerance_at(stage)) & (since >= rule.min_descent)
            down = flat & (stage < rule.reductions)  # a plateau at a rate with reductions left: reduce it
            if bool(down.any()):
                stage[down] += 1
                since[down] = 0
                scale_on = (rule.factor ** stage.double()).to(tensors[0].device)
            last = flat & ~down & torch.tensor(step >= rule.min_steps)
            new = last | (~held & torch.tensor(step == descent_cap))
            if bool(new.any()):
                decrease[new] = change[new]
                stopped_at[new] = step
                held |= new
                held_on = held.to(tensors[0].device)  # the mask on the variables' device, moved only when it changes
                new_on = new.to(tensors[0].device)
                with torch.no_grad():
                    for p, snap in zip(tensors, snapshot):
                        snap[new_on] = p.detach()[new_on]
            if bool(held.all()):
                break
    descent = step
    if rule.anneal_steps:  # every sequence from its own last rate
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=rule.anneal_steps, eta_min=lr * lr_final_fraction)
        for i in range(rule.anneal_steps):
            before = None if scale_on is None else [p.detach().clone() for p in tensors]
            adam_step(opt, prior_name, step_loss, step, history, i == rule.anneal_steps - 1 or step % LOG_EVERY == 0,
                      callback)
            if before is not None:
                _scale_steps(tensors, before, scale_on)
            sched.step()
            step += 1
    # converged: within the tolerance when it stopped, at its last reduced rate
    within = (decrease.abs() <= rule.tolerance_at(stage)).tolist()
    converged = [bool(w and k >= rule.reductions) for w, k in zip(within, stage.tolist())]
    out = {"descent_steps": [int(v) for v in stopped_at.tolist()], "steps": step,
           "stopped": "plateau" if descent < descent_cap or all(converged) else "cap",
           "plateau_decrease": [round(float(v), 6) for v in decrease.tolist()], "converged": converged}
    if rule.reductions:
        out["reductions"] = [int(k) for k in stage.tolist()]
    return history, out


@torch.no_grad()
def _scale_steps(tensors: list, before: list, scale: torch.Tensor) -> None:
    """Scale each sequence's last optimiser step by ``scale`` (B,): its own learning rate (Adam's
    step does not depend on the gradient's scale, so a per-sequence rate is the scaled step)."""
    for p, b in zip(tensors, before):
        s = scale.to(p.dtype).view(-1, *([1] * (p.dim() - 1)))
        p.copy_(b + s * (p - b))


FACING_POINTS = 256  # observed points per frame the hypotheses are scored on
FACING_VERTICES = 400  # mesh vertices (farthest-point subset) the hypotheses are scored on


def subset_batch(batch: FitBatch, points: int) -> FitBatch:
    """The first ``points`` observed points of every frame (i.i.d. uniform samples: an unbiased subset)."""
    m = min(points, batch.points.shape[2])
    return FitBatch(points=batch.points[:, :, :m], lengths=batch.lengths.clamp_max(m), timestamps=batch.timestamps,
                    window_s=batch.window_s, output_timestamps=batch.output_timestamps)


def repeat_batch(batch: FitBatch, k: int) -> FitBatch:
    """Every sequence of ``batch`` repeated ``k`` times, hypothesis-major per sequence (b0h0, b0h1, ...)."""
    rep = lambda x: x.repeat_interleave(k, dim=0)  # noqa: E731
    return FitBatch(points=rep(batch.points), lengths=rep(batch.lengths), timestamps=rep(batch.timestamps),
                    window_s=batch.window_s, output_timestamps=rep(batch.output_timestamps))


def rigid_parameters(state: FitState) -> list[torch.Tensor]:
    return [p for p in (state.root, state.trans, state.heading, state.offset) if p is not None]


def frame_chamfer(state: FitState, body, batch: FitBatch, subset, chamfer: StaticChamfer) -> torch.Tensor:
    """(B, n) the Chamfer (metres) of the mesh (vertex ``subset``) against the observed points of
    ``batch`` (``chamfer``: their StaticChamfer) at each observed frame."""
    B, n = batch.batch_size, batch.num_observed
    rot, trans = body_parameters(state, batch.timestamps, observed=True)
    rest = body.prepare(state.shape())
    verts = body.skin(rest, rot, trans, vertex_indices=subset).vertices
    return chamfer(verts.flatten(0, 1)).view(B, n)


def subset_data_term(state: FitState, body, batch: FitBatch, subset, chamfer: StaticChamfer) -> torch.Tensor:
    """(B,) the protocol's data term (mm): :func:`frame_chamfer`, mean over the observed frames."""
    return frame_chamfer(state, body, batch, subset, chamfer).mean(1) * 1000.0


@torch.no_grad()
def set_rigid(state: FitState, timestamps: torch.Tensor, rotations: torch.Tensor | None,
              trans: torch.Tensor | None) -> None:
    """Set ``state``'s free rigid parameters so that its motion at the observed ``timestamps``
    (B, n) follows a given root orientation (``rotations``: (B, n, 22, 3, 3) local rotations, or
    their roots) and translation (B, n, 3): the free root orientation to the root (priors that do not
    decode it), the free heading to the mean yaw between it and the decoded root, the free
    translation to the translation (priors that do not decode it), the free offset to the mean
    difference from the decoded translation."""
    R_obs = None if rotations is None else rotations[:, :, 0].to(state.shape_param)
    if state.root is not None and R_obs is not None:
        state.root.copy_(R_obs[..., :, :2].flatten(-2))
    if state.heading is not None and R_obs is not None:
        state.heading.zero_()
        rot, _ = body_parameters(state, timestamps, observed=True)
        rel = R_obs @ rot[:, :, 0].transpose(-1, -2)  # H with H @ decoded root = observed root
        yaw = torch.atan2(rel[..., 0, 2], rel[..., 2, 2])  # (B, n) yaw about +y
        state.heading.copy_(torch.atan2(yaw.sin().mean(1), yaw.cos().mean(1))[:, None])
    if trans is not None:
        tr_obs = trans.to(state.shape_param)
        if state.trans is not None:  # the prior does not decode translation
            state.trans.copy_(tr_obs)
        elif state.offset is not None:  # it does: align its decoded translation on average
            state.offset.zero_()
            _, tr = body_parameters(state, timestamps, observed=True)
            state.offset.copy_((tr_obs - tr).mean(1))
