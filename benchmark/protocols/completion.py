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

import torch

from benchmark.metrics.static_chamfer import StaticChamfer
from benchmark.observations import PointCloudSequence
from benchmark.protocols.fit_state import (FACING_POINTS, FACING_VERTICES, HEADING_CANDIDATES, LATENT_INITS,  # noqa: F401
                                             LOG_EVERY, FitState, _check_decoded, _data_term, _grid, _initial_heading,
                                             _repeat_batch, _rigid_parameters, _set_yaw, _subset_batch, apply_free_rigid,
                                             body_parameters, frame_chamfer, init_state, initial_latents, optimise,
                                             parameter_groups)
from benchmark.protocols.start_search import (START_SEARCH_RULES, encoded_start, is_prior_free, limb_start_search,
                                              prior_free_start)
from priors.base import FitBatch, PriorAdapter

log = logging.getLogger(__name__)


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
    if start_search not in START_SEARCH_RULES:
        raise ValueError(f"fit: unknown start search {start_search!r}; choose one of {', '.join(START_SEARCH_RULES)}")
    own_start = start_search == "observation" and facing == "observation" and is_prior_free(adapter)
    if own_start:  # the prior-free start (facing, limb search) is this fit's start: computed once per observation
        state, facing_log = prior_free_start(body, batch, generator, device, lr, lambda_prior)
        state.adapter = adapter
        for p in state.parameters():
            p.requires_grad_(True)
    elif facing == "search":
        state, facing_log = facing_search(adapter, body, batch, generator, device, lr, lambda_prior, latent_init=latent_init)
    elif facing == "observation":
        state, facing_log = observed_facing(adapter, body, batch, generator, device, lr, lambda_prior, latent_init=latent_init)
    else:
        state = init_state(adapter, body, batch, generator, device, data_term=data_term, latent_init=latent_init)

    trace = []  # (B,) data term of every step: the convergence diagnostics (benchmark.fit_diagnostics)
    sampler = None
    if points_per_step is not None:
        sampler = torch.Generator().manual_seed(int(torch.randint(0, 2**62, (1,), generator=generator)))

    facing_log["facing_s"] = time.perf_counter() - t_facing
    if start_search in ("limbs", "observation") and not own_start:
        t_search = time.perf_counter()
        state, search_log = limb_start_search(adapter, body, batch, state, lr, lambda_prior)
        if start_search == "observation" and "start_choice_counts" not in search_log:
            state, search_log = encoded_start(adapter, body, batch, state, generator, device, lr, lambda_prior)
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
FACING_STEPS = (15, 25)  # coarse-fit steps per hypothesis: rigid parameters only, then every variable


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

