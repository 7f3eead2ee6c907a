"""The completion protocol (PROTOCOL.md, table1): fit every prior to degraded point clouds, score 30 fps output.

One work unit = one prior x one grid cell x one batch of sequences. All sequences of a unit are
optimised together as one batch of latents (no Python loop over sequences or frames in the loop).

Objective, the same for every prior (the table spec states it and the JSON records it)::

    sum_b [ ChamferMM_b(mesh vertices at observed timestamps, observed points) + lambda_prior * prior_b ]

ChamferMM is the PROTOCOL.md Chamfer (Euclidean, half of the two directed means) in millimetres,
averaged over the sequence's observed frames; prior_b is the adapter's term. Variables: the
adapter's latents, the body shape, and the free rigid parameters the adapter needs:

- per-observed-frame root translation (priors that do not encode translation), LERP-ed;
- per-observed-frame root orientation (priors that do not encode it), SLERP-ed;
- a global heading (about y) and offset per sequence (decoders that normalise heading).

Translation starts at the observed points' centroid minus the rest mesh's centroid; root
orientation at identity; shape at the body's neutral shape. One Adam optimiser, cosine schedule.
Outside the observed span, per-observed-frame variables are held at their end values; priors that
decode the whole window (fixed-window, continuous) decode every output frame themselves.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections import OrderedDict
from dataclasses import dataclass

import roma
import torch

from benchmark.interpolate import lerp_frames, slerp_frames
from benchmark.metrics.static_chamfer import StaticChamfer
from benchmark.observations import PointCloudSequence
from priors.base import Decoded, FitBatch, PriorAdapter

log = logging.getLogger(__name__)


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


def _grid(adapter: PriorAdapter, window_s: float, B: int, device) -> torch.Tensor:
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
        grid = _grid(a, state.window_s, timestamps.shape[0], timestamps.device)
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
    """A fit's starting latents: ``latent_init="sample"`` (table1 v1-v2, PROTOCOL.md): the adapter's
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
        _set_yaw(state, base_root, base_heading, torch.full((B,), yaw, device=batch.points.device))
        rot, trans = body_parameters(state, batch.timestamps, observed=True)
        verts = body.skin(rest, rot, trans, vertex_indices=subset).vertices
        d = data_term(verts.flatten(0, 1))
        scores.append(d.view(B, n).mean(1))
    best = torch.stack(scores, 1).argmin(1).to(batch.points.dtype)  # (B,)
    _set_yaw(state, base_root, base_heading, 2 * math.pi * best / HEADING_CANDIDATES)


def _set_yaw(state: FitState, base_root, base_heading, yaw: torch.Tensor) -> None:
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
        opt.zero_grad(set_to_none=True)
        loss, log = step_loss(step)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"prior {prior_name!r}: non-finite loss at step {step}")
        loss.backward()
        opt.step()
        sched.step()
        if step == 0 or step == steps - 1 or step % LOG_EVERY == 0:
            history.append({"step": step, **log()})
        if callback is not None:
            callback(step, float(loss))
    return history


def fit(adapter: PriorAdapter, body, batch: FitBatch, steps: int, lr: float, lambda_prior: float,
        generator: torch.Generator, device, lr_final_fraction: float = 0.1, loss_vertices: int | None = None,
        callback=None, facing: str = "heading8", shape_lr_scale: float = 1.0,
        points_per_step: int | None = None, latent_init: str = "sample",
        start_search: str = "none") -> tuple[FitState, dict]:
    """Optimise one batch (see module docstring). Returns the state and a log: ``history`` (the
    logged steps), ``data_trace`` ((steps, B) the data term of every sequence at every step, mm)
    and, with ``facing="search"``, the facing search's choices.

    ``loss_vertices``: the data term uses a fixed farthest-point subset of that many mesh vertices
    (a profile size, for CPU speed); None uses every vertex. Evaluation always uses every vertex.

    The data term is the exact Chamfer loss (:func:`benchmark.metrics.chamfer.chamfer_loss`, exact
    nearest neighbours); the KD-trees of the observed points, which never move, are built once
    per fit (:class:`~benchmark.metrics.chamfer.StaticChamfer`) and shared by the heading search
    and every step.

    ``points_per_step``: where a frame has more observed points, each step's observed points ->
    mesh mean is taken over that many of them drawn uniformly with replacement, anew at every step
    (:meth:`~benchmark.metrics.chamfer.StaticChamfer.sample_b`, seeded from ``generator``): an
    unbiased estimate of the exact data term and of its gradient. The mesh -> observed points
    direction always uses every observed point. None: the exact data term at every step.

    ``latent_init``: where the prior's latents start (:func:`initial_latents`): ``"sample"`` (the
    adapter's ``init_latents``) or ``"mean"`` (table1 protocol v3: the prior's mean).
    """
    subset = body.loss_vertex_indices(loss_vertices)
    if facing not in FACING_RULES:
        raise ValueError(f"fit: unknown facing rule {facing!r}; choose one of {', '.join(FACING_RULES)}")
    B, n = batch.batch_size, batch.num_observed
    data_term = StaticChamfer(batch.points.flatten(0, 1), batch.lengths.flatten(0, 1))
    facing_log = {}
    t_facing = time.perf_counter()
    if facing == "search":
        state, facing_log = facing_search(adapter, body, batch, generator, device, lr, lambda_prior, latent_init=latent_init)
    elif facing == "observation":
        state, facing_log = observed_facing(adapter, body, batch, generator, device, lr, lambda_prior, latent_init=latent_init)
    else:
        state = init_state(adapter, body, batch, generator, device, data_term=data_term, latent_init=latent_init)

    trace = []  # (B,) data term of every step: the convergence diagnostics (benchmark.fit_diagnostics)
    sampler = None
    if points_per_step is not None:
        sampler = torch.Generator().manual_seed(int(torch.randint(0, 2**62, (1,), generator=generator)))

    if start_search not in START_SEARCH_RULES:
        raise ValueError(f"fit: unknown start search {start_search!r}; choose one of {', '.join(START_SEARCH_RULES)}")
    facing_log["facing_s"] = time.perf_counter() - t_facing
    if start_search == "limbs":
        t_search = time.perf_counter()
        state, search_log = limb_start_search(adapter, body, batch, state, lr, lambda_prior)
        facing_log.update(search_log, start_search_s=time.perf_counter() - t_search)

    def step_loss(step):
        rot, trans = body_parameters(state, batch.timestamps, observed=True)
        rest = body.prepare(state.shape())
        verts = body.skin(rest, rot, trans, vertex_indices=subset).vertices  # (B, n, V, 3)
        data = data_term(verts.flatten(0, 1), b_sample=points_per_step, generator=sampler).view(B, n).mean(1) * 1000.0
        trace.append(data.detach())
        prior = adapter.prior_term(state.latents)
        return (data + lambda_prior * prior).sum(), lambda: {"data_mm": float(data.detach().mean()),
                                                              "prior": float(prior.detach().mean())}

    history = optimise(adapter.name, parameter_groups(state, lr, shape_lr_scale), steps, lr, lr_final_fraction, step_loss,
                       callback=callback)
    data_trace = torch.stack(trace) if trace else torch.zeros(0, B)
    return state, {"history": history, "data_trace": data_trace, **facing_log}


# How a fit finds the facing direction: "heading8" (protocol v1 of table1): the 8-yaw Chamfer score
# of the T-pose; "search": :func:`facing_search` with the prior itself, a coarse fit per yaw
# hypothesis; "observation" (table1 protocol v2, `complete`): :func:`observed_facing`, the facing
# found on the observation by the prior-free search, every prior's start turned to it.
FACING_RULES = ("heading8", "search", "observation")
FACING_HYPOTHESES = 8  # yaw hypotheses of the facing search, evenly spaced about y
FACING_POINTS = 256  # observed points per frame the hypotheses are scored on
FACING_VERTICES = 400  # mesh vertices (farthest-point subset) the hypotheses are scored on
FACING_STEPS = (15, 25)  # coarse-fit steps per hypothesis: rigid parameters only, then every variable


def _subset_batch(batch: FitBatch, points: int) -> FitBatch:
    """The first ``points`` observed points of every frame (i.i.d. uniform samples: an unbiased subset)."""
    m = min(points, batch.points.shape[2])
    return FitBatch(points=batch.points[:, :, :m], lengths=batch.lengths.clamp_max(m), timestamps=batch.timestamps,
                    window_s=batch.window_s, output_timestamps=batch.output_timestamps)


def _repeat_batch(batch: FitBatch, k: int) -> FitBatch:
    """Every sequence of ``batch`` repeated ``k`` times, hypothesis-major per sequence (b0h0, b0h1, ...)."""
    rep = lambda x: x.repeat_interleave(k, dim=0)  # noqa: E731
    return FitBatch(points=rep(batch.points), lengths=rep(batch.lengths), timestamps=rep(batch.timestamps),
                    window_s=batch.window_s, output_timestamps=rep(batch.output_timestamps))


def _rigid_parameters(state: FitState) -> list[torch.Tensor]:
    return [p for p in (state.root, state.trans, state.heading, state.offset) if p is not None]


def _data_term(state: FitState, body, batch: FitBatch, subset, chamfer: StaticChamfer) -> torch.Tensor:
    """(B,) the protocol's data term (mm): Chamfer of the mesh (vertex ``subset``) against the
    observed points of ``batch`` (``chamfer``: their StaticChamfer), mean over the observed frames."""
    B, n = batch.batch_size, batch.num_observed
    rot, trans = body_parameters(state, batch.timestamps, observed=True)
    rest = body.prepare(state.shape())
    verts = body.skin(rest, rot, trans, vertex_indices=subset).vertices
    return chamfer(verts.flatten(0, 1)).view(B, n).mean(1) * 1000.0


def facing_search(adapter: PriorAdapter, body, batch: FitBatch, generator: torch.Generator, device, lr: float,
                  lambda_prior: float, latent_init: str = "sample") -> tuple[FitState, dict]:
    """The initial state of a fit, with the facing direction found by a coarse multi-hypothesis fit.

    The same rule for every prior (protocol v2). Each sequence is tried at FACING_HYPOTHESES yaw
    angles about y (applied to the free root orientation, or to the free heading of a
    heading-normalised decoder). Every hypothesis is fitted briefly on a subset (FACING_POINTS
    observed points per frame, FACING_VERTICES mesh vertices): FACING_STEPS[0] steps of the rigid
    parameters only, then FACING_STEPS[1] steps of every variable, with the table's objective.
    Each sequence keeps the hypothesis with the lowest final data term, and the full fit continues
    from that hypothesis's fitted variables. A T-pose's Chamfer barely tells front from back; a
    posed body does (knees and elbows bend one way).

    Priors without a free root orientation or heading (none so far) start from ``init_state``.
    Returns the state (batch B) and a log: the chosen yaw (radians) and every hypothesis's score.
    """
    B = batch.batch_size
    K = FACING_HYPOTHESES
    small = _subset_batch(_repeat_batch(batch, K), FACING_POINTS)
    hyp = init_state(adapter, body, small, generator, device, search_heading=False, latent_init=latent_init)
    if hyp.root is None and hyp.heading is None:
        return init_state(adapter, body, batch, generator, device, search_heading=False, latent_init=latent_init), {
            "facing": "none: the prior has no free root orientation or heading"}
    yaw = (2 * math.pi / K) * torch.arange(K, device=device, dtype=batch.points.dtype).repeat(B)
    with torch.no_grad():
        base_root = None if hyp.root is None else hyp.root.detach().clone()
        base_heading = None if hyp.heading is None else hyp.heading.detach().clone()
        _set_yaw(hyp, base_root, base_heading, yaw)
    subset = body.loss_vertex_indices(FACING_VERTICES)
    chamfer = StaticChamfer(small.points.flatten(0, 1), small.lengths.flatten(0, 1))

    def loss_of(step):
        data = _data_term(hyp, body, small, subset, chamfer)
        prior = adapter.prior_term(hyp.latents)
        return (data + lambda_prior * prior).sum(), lambda: {}

    rigid_steps, all_steps = FACING_STEPS
    optimise(adapter.name, _rigid_parameters(hyp), rigid_steps, lr, 1.0, loss_of)
    optimise(adapter.name, hyp.parameters(), all_steps, lr, 1.0, loss_of)
    with torch.no_grad():
        scores = _data_term(hyp, body, small, subset, chamfer).view(B, K)
    best = scores.argmin(1)  # (B,)
    pick = torch.arange(B, device=device) * K + best
    # the adapter's own per-batch state (e.g. the initial latents its prior term measures from)
    # must be the full batch's when the full fit starts: initialise it last
    probe = init_state(adapter, body, batch, generator, device, search_heading=False, latent_init=latent_init)
    state = _select(hyp, pick, probe)
    return state, {"facing_yaw_rad": [float(y) for y in yaw.view(B, K)[torch.arange(B), best]],
                   "facing_scores_mm": [[round(float(v), 3) for v in row] for row in scores]}


def _mean_heading(state: FitState, batch: FitBatch) -> torch.Tensor:
    """(B,) circular mean over the observed frames of the heading (yaw of the root's +z axis about +y) of ``state``."""
    from benchmark.frames import heading

    rot, _ = body_parameters(state, batch.timestamps, observed=True)
    yaw = heading(rot[:, :, 0])  # (B, n)
    return torch.atan2(torch.sin(yaw).mean(1), torch.cos(yaw).mean(1))


# observation_facing's results in this process, by observation (see there): every prior of a
# table cell sees the same observation, so the search runs once per cell and worker, not once per prior.
_FACING_CACHE: OrderedDict = OrderedDict()
FACING_CACHE_SIZE = 16


def _facing_key(body, batch: FitBatch, device, lr: float, lambda_prior: float) -> tuple:
    """What :func:`observation_facing`'s result depends on: the observation's content (its
    :func:`~benchmark.degrade.fingerprint`), the body, the device, the objective and the search's sizes."""
    from benchmark.degrade import fingerprint

    obs = PointCloudSequence(points=batch.points.detach().cpu(), lengths=batch.lengths.cpu(),
                             timestamps=batch.timestamps.detach().cpu())
    return (fingerprint(obs), float(batch.window_s), id(body), str(device), float(lr), float(lambda_prior),
            FACING_HYPOTHESES, FACING_POINTS, FACING_VERTICES, tuple(FACING_STEPS))


@torch.no_grad()
def observation_facing(body, batch: FitBatch, generator: torch.Generator, device, lr: float,
                       lambda_prior: float) -> tuple[torch.Tensor, dict]:
    """(B,) the facing of each sequence of ``batch``, found on the observation alone: the facing
    search (:func:`facing_search`) of the prior-free body (``no-prior``: free per-frame pose, root
    orientation and translation), then the circular mean of its fitted heading over the observed
    frames. Returns the yaw (radians about +y, 0 = facing +z) and the search's log.

    A deterministic function of the observation (the prior-free body draws nothing from
    ``generator``): the result is kept per process (the last FACING_CACHE_SIZE observations) and
    served again, bit for bit, to the next prior fitted to the same observation."""
    from priors.no_prior import NoPrior

    key = _facing_key(body, batch, device, lr, lambda_prior)
    hit = _FACING_CACHE.get(key)
    if hit is not None and hit[0] is body:
        _FACING_CACHE.move_to_end(key)
        return hit[1].clone(), copy.deepcopy(hit[2])
    with torch.enable_grad():
        ref, log = facing_search(NoPrior(device=device), body, batch, generator, device, lr, lambda_prior)
    yaw = _mean_heading(ref, batch)
    _FACING_CACHE[key] = (body, yaw.clone(), copy.deepcopy(log))
    while len(_FACING_CACHE) > FACING_CACHE_SIZE:
        _FACING_CACHE.popitem(last=False)
    return yaw, log


def observed_facing(adapter: PriorAdapter, body, batch: FitBatch, generator: torch.Generator, device, lr: float,
                    lambda_prior: float, latent_init: str = "sample") -> tuple[FitState, dict]:
    """The initial state of a fit under table1 protocol v2: the prior's own initial state
    (:func:`init_state`, no heading search), turned about +y so that its mean heading over the
    observed frames is the observation's facing (:func:`observation_facing`).

    The facing of a body in a point cloud is a property of the observation, so it is found without
    the prior, the same way for every prior: a prior whose decoder cannot yet represent the motion
    (or whose coarse fits score poorly) still starts facing the right way, and a prior that turns
    away during its own fit shows it in the diagnostics. The turn goes to the free root orientation
    (per-frame priors) or to the free heading (priors that decode their own root orientation).
    """
    target, log = observation_facing(body, batch, generator, device, lr, lambda_prior)
    state = init_state(adapter, body, batch, generator, device, search_heading=False, latent_init=latent_init)
    if state.root is None and state.heading is None:
        return state, {"facing": "none: the prior has no free root orientation or heading"}
    with torch.no_grad():
        start = _mean_heading(state, batch)
        delta = torch.remainder(target - start + math.pi, 2 * math.pi) - math.pi
        base_root = None if state.root is None else state.root.detach().clone()
        base_heading = None if state.heading is None else state.heading.detach().clone()
        _set_yaw(state, base_root, base_heading, delta)
    return state, {"facing_yaw_rad": [round(float(y), 5) for y in target],
                   "facing_scores_mm": log["facing_scores_mm"], "facing_turn_rad": [round(float(d), 5) for d in delta]}


def _select(hyp: FitState, pick: torch.Tensor, like: FitState) -> FitState:
    """The hypotheses ``pick`` (one per sequence) of ``hyp`` as a fresh leaf state shaped like ``like``."""
    def take(x, ref):
        if x is None:
            return None
        y = x.detach()[pick].clone()
        if ref is not None and y.shape != ref.shape:
            raise ValueError(f"facing search: a variable of shape {tuple(x.shape)} is not batch-first "
                             f"(expected {tuple(ref.shape)} after selection)")
        return y.requires_grad_(True)

    latents = {k: take(v, like.latents[k]) for k, v in hyp.latents.items()}
    return FitState(adapter=like.adapter, latents=latents, shape_param=take(hyp.shape_param, like.shape_param),
                    obs_t=like.obs_t, window_s=like.window_s, root=take(hyp.root, like.root),
                    trans=take(hyp.trans, like.trans), heading=take(hyp.heading, like.heading),
                    offset=take(hyp.offset, like.offset), bounded_shape=like.bounded_shape)


@torch.no_grad()
def decode_output(state: FitState, body, out_t: torch.Tensor):
    rot, trans = body_parameters(state, out_t)
    rest = body.prepare(state.shape())
    return body.skin(rest, rot, trans), rot, trans


def observation_batch(obs: PointCloudSequence, window_s: float, out_t: torch.Tensor, device) -> FitBatch:
    if not bool(obs.frame_mask.all()):
        raise ValueError("completion: every sequence of a unit must have all its observed frames (no padding)")
    t0 = obs.timestamps[:, :1]
    return FitBatch(points=obs.points.to(device), lengths=obs.lengths.to(device),
                    timestamps=(obs.timestamps - t0).to(device), window_s=window_s, output_timestamps=out_t.to(device))


# objective.start_search (table1 protocol v4): "none", or "limbs": :func:`limb_start_search`.
START_SEARCH_RULES = ("none", "limbs")
START_SEARCH_STEPS = (15, 25)  # coarse-fit steps per start hypothesis: rigid parameters only, then every variable
# The limb start hypotheses, in stages: first each arm in the T-pose, lowered to the side, or lowered
# with the elbow bent forward; then each leg as it is, or with the hip flexed forward and the knee
# bent. Local rotation vectors (radians) of the left limb's joints (SMPL order); the right limb's
# are mirrored about the x = 0 plane. None keeps the limb as it is.
LIMB_START_STAGES = (
    ({"shoulder": 16, "elbow": 18}, {"shoulder": 17, "elbow": 19},
     ({}, {"shoulder": (0.0, 0.0, -1.2)}, {"shoulder": (0.0, 0.0, -1.2), "elbow": (0.0, -1.57, 0.0)})),
    ({"hip": 1, "knee": 4}, {"hip": 2, "knee": 5},
     (None, {"hip": (-0.6, 0.0, 0.0), "knee": (1.2, 0.0, 0.0)})),
)


def supports_start_search(adapter: PriorAdapter) -> bool:
    """Whether ``limb_start_search`` applies: a per-frame prior (one latent set per observed frame)
    that can express a given pose in its latents (``encode_motion``: exact for no-prior, the
    encoder's mean for VPoser)."""
    return adapter.window.kind == "per-frame" and type(adapter).encode_motion is not PriorAdapter.encode_motion


def limb_hypotheses(adapter: PriorAdapter, state: FitState, stage: int) -> list[dict] | None:
    """The start hypotheses of ``stage`` from ``state`` (None past the last stage): for each limb
    stage, every combination of its starts for the left and right limb set on the decoded pose of
    every observed frame and encoded back (``adapter.encode_motion``); the last stage: each
    frame's own latents and those of the previous and the next observed frame."""
    if stage > len(LIMB_START_STAGES):
        return None
    lat = {k: v.detach() for k, v in state.latents.items()}
    if stage == len(LIMB_START_STAGES):
        prev = {k: torch.cat([v[:, :1], v[:, :-1]], 1) for k, v in lat.items()}
        nxt = {k: torch.cat([v[:, 1:], v[:, -1:]], 1) for k, v in lat.items()}
        return [{k: v.clone() for k, v in lat.items()}, prev, nxt]
    left_joints, right_joints, starts = LIMB_START_STAGES[stage]
    with torch.no_grad():
        shape = state.shape() if adapter.shape_conditioned else None
        rot = adapter.decode(lat, state.obs_t, shape).rotations
        zero_trans = rot.new_zeros(*rot.shape[:2], 3)
        mirror = torch.tensor([1.0, -1.0, -1.0], dtype=rot.dtype, device=rot.device)
        out = []
        for left in starts:
            for right in starts:
                r = rot.clone()
                for joints, cfg, flip in ((left_joints, left, False), (right_joints, right, True)):
                    if cfg is None:
                        continue
                    for part, j in joints.items():
                        v = torch.tensor(cfg.get(part, (0.0, 0.0, 0.0)), dtype=rot.dtype, device=rot.device)
                        r[:, :, j] = roma.rotvec_to_rotmat(v * mirror if flip else v)
                enc = adapter.encode_motion(r, zero_trans, state.obs_t)
                out.append({k: enc[k].detach().to(lat[k]) for k in lat})
    return out


def limb_start_search(adapter: PriorAdapter, body, batch: FitBatch, state: FitState, lr: float,
                      lambda_prior: float) -> tuple[FitState, dict]:
    """A per-frame prior's start, limb by limb (table1 protocol v4, ``objective.start_search: limbs``).

    From ``state`` (the facing already set), stage by stage (:func:`limb_hypotheses`): every
    hypothesis is fitted briefly on a subset (FACING_POINTS observed points per frame,
    FACING_VERTICES mesh vertices; START_SEARCH_STEPS), and each observed frame keeps the
    hypothesis with the lowest data term at that frame. A prior it does not apply to
    (:func:`supports_start_search`) keeps ``state``. Returns the state and the choice counts per stage."""
    if not supports_start_search(adapter):
        return state, {"start_search": "none: not a per-frame prior with encode_motion"}
    counts = []
    stage = 0
    while (hyps := limb_hypotheses(adapter, state, stage)) is not None:
        state, stage_counts = _best_per_frame(adapter, body, batch, state, hyps, lr, lambda_prior)
        counts.append(stage_counts)
        stage += 1
    return state, {"start_choice_counts": counts}


def _best_per_frame(adapter: PriorAdapter, body, batch: FitBatch, state: FitState, hyps: list[dict],
                    lr: float, lambda_prior: float) -> tuple[FitState, list[int]]:
    """Per observed frame, the best of the start hypotheses ``hyps`` (latents of ``state``'s shapes,
    per observed frame along dimension 1), each fitted briefly from ``state``'s rigid parameters
    and shape. The data term is a mean over frames of terms of that frame's variables and the
    shared shape, so each frame takes its own best; the shape is that of the hypothesis with the
    lowest mean."""
    K = len(hyps)
    B, n = batch.batch_size, batch.num_observed
    small = _subset_batch(_repeat_batch(batch, K), FACING_POINTS)

    def rep(x):
        return None if x is None else x.detach().repeat_interleave(K, dim=0).clone().requires_grad_(True)

    latents = {k: torch.stack([h[k] for h in hyps], 1).flatten(0, 1).clone().requires_grad_(True)
               for k in state.latents}
    hyp = FitState(adapter=adapter, latents=latents, shape_param=rep(state.shape_param), obs_t=small.timestamps,
                   window_s=state.window_s, root=rep(state.root), trans=rep(state.trans), heading=rep(state.heading),
                   offset=rep(state.offset), bounded_shape=state.bounded_shape)
    subset = body.loss_vertex_indices(FACING_VERTICES)
    chamfer = StaticChamfer(small.points.flatten(0, 1), small.lengths.flatten(0, 1))

    def frame_terms():
        rot, trans = body_parameters(hyp, small.timestamps, observed=True)
        rest = body.prepare(hyp.shape())
        verts = body.skin(rest, rot, trans, vertex_indices=subset).vertices
        return chamfer(verts.flatten(0, 1)).view(B * K, n) * 1000.0

    def loss_of(step):
        return (frame_terms().mean(1) + lambda_prior * adapter.prior_term(hyp.latents)).sum(), lambda: {}

    rigid_steps, all_steps = START_SEARCH_STEPS
    optimise(adapter.name, _rigid_parameters(hyp), rigid_steps, lr, 1.0, loss_of)
    optimise(adapter.name, hyp.parameters(), all_steps, lr, 1.0, loss_of)
    with torch.no_grad():
        scores = frame_terms().view(B, K, n)
    best = scores.argmin(1)  # (B, n)

    def per_frame(x):
        if x is None:
            return None
        y = x.detach().view(B, K, *x.shape[1:])
        if y.shape[2] != n:
            raise ValueError(f"start search: prior {adapter.name!r} has a variable of shape {tuple(x.shape[1:])} "
                             f"that is not per observed frame ({n} frames along dimension 1)")
        idx = best.view(B, 1, n, *([1] * (y.dim() - 3))).expand(B, 1, n, *y.shape[3:])
        return y.gather(1, idx)[:, 0].clone().requires_grad_(True)

    whole = scores.mean(2).argmin(1)  # (B,)

    def per_sequence(x):
        if x is None:
            return None
        return x.detach().view(B, K, *x.shape[1:])[torch.arange(B), whole].clone().requires_grad_(True)

    out = FitState(adapter=adapter, latents={k: per_frame(v) for k, v in hyp.latents.items()},
                   shape_param=per_sequence(hyp.shape_param), obs_t=state.obs_t, window_s=state.window_s,
                   root=per_frame(hyp.root), trans=per_frame(hyp.trans), heading=per_sequence(hyp.heading),
                   offset=per_sequence(hyp.offset), bounded_shape=state.bounded_shape)
    return out, [int(c) for c in torch.bincount(best.flatten(), minlength=K)]
