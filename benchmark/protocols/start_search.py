"""The limb start search of per-frame priors (table1 protocol v4, ``objective.start_search: limbs``).

After the facing is found (:mod:`benchmark.protocols.completion`), a per-frame prior whose latents
are per observed frame and that can express a pose in them tries, per observed frame, limb start
hypotheses in stages (arms, legs, the neighbouring frames' poses), each fitted briefly on the facing
search's subset; each frame keeps its best by data term. From the T-pose, no-prior's fits folded
the forearms into local minima of the data term (docs/protocol.md, table1 version 4).
"""

from __future__ import annotations

import copy
import dataclasses
from collections import OrderedDict

import roma
import torch

from benchmark.protocols.brief_fit import START_SOFTMIN_M, brief_fits, check_search_fit, search_chamfer, search_fit
from benchmark.protocols.latent_checks import check_latents, prior_values
from benchmark.protocols.fit_state import (FACING_POINTS, FACING_VERTICES, FitState, as_latent, body_parameters,
                                              decode_grid, frame_chamfer, init_state, repeat_batch, rigid_parameters,
                                              set_rigid, subset_batch)
from benchmark.protocols import start_cache
from benchmark.protocols.multi_start import repeat_state
from priors.base import FitBatch, MotionEncoder, PriorAdapter, has_motion_encoder

# objective.start_search: "none"; "limbs" (table1 protocol v4): :func:`limb_start_search` for the
# per-frame priors; "observation" (v5): the same, and every other prior with a motion encoder starts
# from the prior-free body's limb-searched start, encoded (:func:`encoded_start`).
START_SEARCH_RULES = ("none", "limbs", "observation")
ENCODED_START = "encoded prior-free start"  # encoded_start's log["start"]
START_SEARCH_STEPS = (15, 25)  # coarse-fit steps per start hypothesis: rigid parameters only, then every variable
# objective.start_fit: the data term and optimiser of the search's brief fits and choices
# (benchmark.protocols.brief_fit: START_FITS, resolved per search by search_fit; the facing
# search's stay exact, see there).
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
    return adapter.window.kind == "per-frame" and isinstance(adapter, MotionEncoder)


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
                check_latents(adapter, enc, lat, "encode_motion", extra=True)
                out.append({k: enc[k].detach().to(lat[k]) for k in lat})
    return out


def limb_start_search(adapter: PriorAdapter, body, batch: FitBatch, state: FitState, lr: float,
                      lambda_prior: float, start_fit: str = "exact") -> tuple[FitState, dict]:
    """A per-frame prior's start, limb by limb (table1 protocol v4, ``objective.start_search: limbs``).

    From ``state`` (the facing already set), stage by stage (:func:`limb_hypotheses`): every
    hypothesis is fitted briefly on a subset (FACING_POINTS observed points per frame,
    FACING_VERTICES mesh vertices; START_SEARCH_STEPS), and each observed frame keeps the
    hypothesis with the lowest data term at that frame (``start_fit``: that data term and the
    brief fits' optimiser, one search's rule: :data:`~benchmark.protocols.brief_fit.SEARCH_FITS`).
    A prior it does not apply to (:func:`supports_start_search`) keeps ``state``. Returns the state
    and the choice counts per stage."""
    if not supports_start_search(adapter):
        return state, {"start_search": "none: not a per-frame prior with encode_motion"}
    counts = []
    for state, stage_counts in limb_search_stages(adapter, body, batch, state, lr, lambda_prior, start_fit):
        counts.append(stage_counts)
    return state, {"start_choice_counts": counts}


def limb_search_stages(adapter: PriorAdapter, body, batch: FitBatch, state: FitState, lr: float, lambda_prior: float,
                       start_fit: str = "exact"):
    """The stages of :func:`limb_start_search` one by one: yields ``(state, choice counts)`` after
    each (``fit-check --start-probe`` reads the start between them). ``start_fit``: one search's
    rule (:data:`~benchmark.protocols.brief_fit.SEARCH_FITS`)."""
    check_search_fit(start_fit)
    stage = 0
    while (hyps := limb_hypotheses(adapter, state, stage)) is not None:
        state, stage_counts = _best_per_frame(adapter, body, batch, state, hyps, lr, lambda_prior, start_fit)
        yield state, stage_counts
        stage += 1


def _best_per_frame(adapter: PriorAdapter, body, batch: FitBatch, state: FitState, hyps: list[dict],
                    lr: float, lambda_prior: float, start_fit: str = "exact") -> tuple[FitState, list[int]]:
    """Per observed frame, the best of the start hypotheses ``hyps`` (latents of ``state``'s shapes,
    per observed frame along dimension 1), each fitted briefly from ``state``'s rigid parameters
    and shape. The data term is a mean over frames of terms of that frame's variables and the
    shared shape, so each frame takes its own best; the shape is that of the hypothesis with the
    lowest mean. ``start_fit``: the data term and optimiser
    (:data:`~benchmark.protocols.brief_fit.SEARCH_FITS`; under ``smooth`` the frames of a hypothesis
    share the L-BFGS's curvature pairs and line search, so a frame's fit is no longer alone; its
    choice still is)."""
    K = len(hyps)
    B, n = batch.batch_size, batch.num_observed
    small = subset_batch(repeat_batch(batch, K), FACING_POINTS)

    def rep(x):
        return None if x is None else x.detach().repeat_interleave(K, dim=0).clone().requires_grad_(True)

    latents = {k: as_latent(adapter, k, torch.stack([h[k] for h in hyps], 1).flatten(0, 1).clone())
               for k in state.latents}
    hyp = FitState(adapter=adapter, latents=latents, shape_param=rep(state.shape_param), obs_t=small.timestamps,
                   window_s=state.window_s, root=rep(state.root), trans=rep(state.trans), heading=rep(state.heading),
                   offset=rep(state.offset), bounded_shape=state.bounded_shape)
    subset = body.loss_vertex_indices(FACING_VERTICES)
    chamfer = search_chamfer(small.points.flatten(0, 1), small.lengths.flatten(0, 1), start_fit)

    def frame_terms():
        return frame_chamfer(hyp, body, small, subset, chamfer) * 1000.0

    brief_fits(adapter.name, zip((rigid_parameters(hyp), hyp.parameters()), START_SEARCH_STEPS), lr,
               lambda: frame_terms().mean(1) + lambda_prior * prior_values(adapter, hyp.latents), start_fit)
    with torch.no_grad():
        scores = frame_terms().view(B, K, n)
    best = scores.argmin(1)  # (B, n)

    def per_frame(x, grad=True):
        if x is None:
            return None
        y = x.detach().view(B, K, *x.shape[1:])
        if y.shape[2] != n:
            raise ValueError(f"start search: prior {adapter.name!r} has a variable of shape {tuple(x.shape[1:])} "
                             f"that is not per observed frame ({n} frames along dimension 1): a per-frame prior "
                             "with encode_motion must keep every latent per observed frame (check-prior checks it)")
        idx = best.view(B, 1, n, *([1] * (y.dim() - 3))).expand(B, 1, n, *y.shape[3:])
        y = y.gather(1, idx)[:, 0].clone()
        return y.requires_grad_(True) if grad else y

    whole = scores.mean(2).argmin(1)  # (B,)

    def per_sequence(x):
        if x is None:
            return None
        return x.detach().view(B, K, *x.shape[1:])[torch.arange(B), whole].clone().requires_grad_(True)

    latents = {k: as_latent(adapter, k, per_frame(v, grad=False)) for k, v in hyp.latents.items()}
    out = FitState(adapter=adapter, latents=latents,
                   shape_param=per_sequence(hyp.shape_param), obs_t=state.obs_t, window_s=state.window_s,
                   root=per_frame(hyp.root), trans=per_frame(hyp.trans), heading=per_sequence(hyp.heading),
                   offset=per_sequence(hyp.offset), bounded_shape=state.bounded_shape)
    return out, [int(c) for c in torch.bincount(best.flatten(), minlength=K)]


def supports_encoded_start(adapter: PriorAdapter) -> bool:
    """Whether :func:`encoded_start` applies: a prior that is not per-frame (those search their own
    start, :func:`limb_start_search`) and has a motion encoder (``has_encoder`` and ``encode_motion``)."""
    return adapter.window.kind != "per-frame" and has_motion_encoder(adapter)


def is_prior_free(adapter: PriorAdapter) -> bool:
    """Whether ``adapter`` is the prior-free body of :func:`prior_free_start` (no-prior: no weights,
    nothing to configure), whose own fit then starts from that start, served from the cache."""
    from priors.no_prior import NoPrior

    return type(adapter) is NoPrior


# prior_free_start's results in this process, by observation: every prior of a table cell sees the
# same observation, so the prior-free search runs once per cell and worker, not once per prior.
_START_CACHE: OrderedDict = OrderedDict()
START_CACHE_SIZE = 8


PRIOR_FREE_FACINGS = ("observation", "aligned")


def prior_free_start(body, batch: FitBatch, generator: torch.Generator, device, lr: float,
                     lambda_prior: float, facing: str = "observation", start_fit: str = "exact") -> tuple[FitState, dict]:
    """The prior-free body's start on the observation (the state no-prior's fit starts from under
    ``start_search: limbs``): its facing (``facing``: ``"observation"``, found on the observation,
    :func:`benchmark.protocols.facing.observed_facing`, table1; ``"aligned"``, facing +z, the
    facing the sls data rules give every sequence), then :func:`limb_start_search` (``start_fit`` as there).
    Deterministic (the prior-free body draws nothing from ``generator``); kept per process for the
    last START_CACHE_SIZE observations and served again as a fresh copy, and, within a table run, on
    disk for its other workers and its resumptions (:mod:`benchmark.protocols.start_cache`). Returns the state and the
    search's log."""
    from benchmark.protocols.facing import facing_keys, observed_facing
    from priors.no_prior import NoPrior

    if facing not in PRIOR_FREE_FACINGS:
        raise ValueError(f"prior_free_start: unknown facing {facing!r}; choose one of {', '.join(PRIOR_FREE_FACINGS)}")
    sizes = (repr(LIMB_START_STAGES), START_SEARCH_STEPS)
    if check_search_fit(start_fit) != "exact":  # (the exact fit's keys as before: their stored starts stay valid)
        sizes += (start_fit, START_SOFTMIN_M)
    process_key, run_key = facing_keys(body, batch, device, lr, lambda_prior)
    key = ("start", facing, *process_key, *sizes)
    hit = _START_CACHE.get(key)
    if hit is None or hit[0] is not body:
        ref_prior = NoPrior(device=device)
        disk_key = ("start", facing, *run_key, *sizes)  # on disk: a table run's <out>/cache/starts (start_cache)
        stored = start_cache.load_state(disk_key, ref_prior, device)
        if stored is None:
            if facing == "aligned":
                state = init_state(ref_prior, body, batch, generator, device, search_heading=False, latent_init="mean")
                facing_log = {"facing": "aligned"}
            else:
                state, facing_log = observed_facing(ref_prior, body, batch, generator, device, lr, lambda_prior,
                                                    latent_init="mean")  # (exact under either start_fit: brief_fit)
            state, search_log = limb_start_search(ref_prior, body, batch, state, lr, lambda_prior, start_fit)
            stored = (state, {**facing_log, **search_log})
            start_cache.store_state(disk_key, *stored)
        hit = (body, *stored)
        _START_CACHE[key] = hit
        while len(_START_CACHE) > START_CACHE_SIZE:
            _START_CACHE.popitem(last=False)
    _START_CACHE.move_to_end(key)
    _, state, log = hit
    return _leaf_copy(state), copy.deepcopy(log)


def _leaf_copy(state: FitState, **changes) -> FitState:
    """``state`` with every variable a fresh leaf copy that requires grad, then ``changes`` applied."""
    leaf = lambda x: None if x is None else x.detach().clone().requires_grad_(True)  # noqa: E731
    fields = {"latents": {k: as_latent(state.adapter, k, v.detach().clone()) for k, v in state.latents.items()},
              "shape_param": leaf(state.shape_param),
              **{name: leaf(getattr(state, name)) for name in ("root", "trans", "heading", "offset")}}
    return dataclasses.replace(state, **{**fields, **changes})


def searched_start(adapter: PriorAdapter, body, batch: FitBatch, state: FitState, rule: str,
                   generator: torch.Generator, device, lr: float, lambda_prior: float,
                   facing: str = "observation", copies: int = 1, start_fit: str = "exact") -> tuple[FitState, dict]:
    """The start search of ``objective.start_search`` ``rule`` (``limbs`` or ``observation``; its
    brief fits' data term ``objective.start_fit``, ``start_fit``) from
    ``state``: :func:`limb_start_search` for the per-frame priors; under ``observation``, every other
    prior with a motion encoder starts from the prior-free start (``facing`` as in
    :func:`prior_free_start`), encoded (:func:`encoded_start`; ``copies`` as there)."""
    state, log = limb_start_search(adapter, body, batch, state, lr, lambda_prior, search_fit(start_fit, encoded=False))
    if rule == "observation" and "start_choice_counts" not in log:
        state, log = encoded_start(adapter, body, batch, state, generator, device, lr, lambda_prior, facing=facing,
                                   copies=copies, start_fit=start_fit)
    return state, log


def encoded_start(adapter: PriorAdapter, body, batch: FitBatch, state: FitState, generator: torch.Generator, device,
                  lr: float, lambda_prior: float, facing: str = "observation", copies: int = 1,
                  start_fit: str = "exact") -> tuple[FitState, dict]:
    """A window or continuous prior's start under ``start_search: observation`` (table1 protocol v5):
    the prior-free body's start on the observation (:func:`prior_free_start`: facing, then limb by
    limb; ``facing`` as there; ``start_fit``, the spec's, resolved for it by
    :func:`~benchmark.protocols.brief_fit.search_fit`), at the output timestamps (or, for a fixed-window prior whose latents
    follow its own frame grid and cover more, on that grid), encoded by the prior (``encode_motion``:
    the posterior mean);
    its body shape; the free rigid parameters set to its root orientation and translation at the
    observed frames (:func:`~benchmark.protocols.fit_state.set_rigid`). Latents the encoder does not
    return keep ``state``'s. A prior it does not apply to (:func:`supports_encoded_start`) keeps
    ``state``. ``copies`` > 1 (``objective.multi_start``): the state and the encoding for every
    sequence repeated that many times (hypothesis-major, :func:`~benchmark.protocols.fit_state.repeat_batch`),
    so the adapter's own per-batch state (e.g. the start its prior term measures from) is the copies'.
    Returns the state and a log."""
    if not supports_encoded_start(adapter):
        return state, {"start_search": "none: a per-frame prior or a prior without a motion encoder"}
    ref, ref_log = prior_free_start(body, batch, generator, device, lr, lambda_prior, facing=facing,
                                    start_fit=search_fit(start_fit, encoded=True))
    if copies > 1:
        ref, state, batch = repeat_state(ref, copies), repeat_state(state, copies), repeat_batch(batch, copies)

    def encoded_on(t):
        rot, trans = body_parameters(ref, t)
        enc = adapter.encode_motion(rot, trans, t)
        check_latents(adapter, enc, state.latents, "encode_motion", partial=True, shapes=False, extra=True)  # shapes: below
        return {k: enc.get(k, v).detach().to(v) for k, v in state.latents.items()}

    def mismatch(enc):
        return [(k, tuple(enc[k].shape), tuple(v.shape)) for k, v in state.latents.items() if enc[k].shape != v.shape]

    with torch.no_grad():
        latents = encoded_on(batch.output_timestamps)
        if mismatch(latents) and adapter.window.kind == "fixed":
            # a prior whose latents follow its own frame grid (Motion-DVAE: one per 30 fps frame),
            # which covers whole windows: longer than a sequence shorter than a window (sls's cycles)
            latents = encoded_on(decode_grid(adapter, state.window_s, batch.batch_size, batch.timestamps.device))
        rot_obs, trans_obs = body_parameters(ref, batch.timestamps, observed=True)
    for k, got, want in mismatch(latents):
        raise ValueError(f"start search: prior {adapter.name!r}: encode_motion's {k!r} has shape {got}, "
                         f"its fit's latents {want} for the same window: they must agree")
    shape_param = state.shape_param
    if ref.bounded_shape == state.bounded_shape and ref.shape_param.shape == state.shape_param.shape:
        shape_param = ref.shape_param
    out = _leaf_copy(dataclasses.replace(state, latents=latents, shape_param=shape_param))
    set_rigid(out, batch.timestamps, rot_obs, trans_obs)
    return out, {"start_choice_counts": ref_log.get("start_choice_counts", []), "start": ENCODED_START}
