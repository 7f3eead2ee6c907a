"""The completion protocol (docs/protocol.md, table1): fit every prior to degraded point clouds, score 30 fps output.

One work unit = one prior x one grid cell x one batch of sequences. All sequences of a unit are
optimised together as one batch of latents (no Python loop over sequences or frames in the loop).

Objective, the same for every prior (the table spec states it and the JSON records it)::

    sum_b [ ChamferMM_b(mesh vertices at observed timestamps, observed points) + lambda_prior * prior_b ]

ChamferMM is the docs/protocol.md Chamfer (Euclidean, half of the two directed means) in millimetres,
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

import logging
import time

import torch

from benchmark.metrics.static_chamfer import StaticChamfer
from benchmark.data.observations import PointCloudSequence
from benchmark.protocols.latent_checks import prior_values
from benchmark.protocols.facing import FACING_RULES, facing_search, observed_facing
from benchmark.protocols.fit_state import (FitState, batch_rows, body_parameters, init_state, parameter_groups,
                                           repeat_batch, row_frames, rows_independent, state_rows)
from benchmark.protocols.multi_start import MultiStart, select_copies, vary_copies
from benchmark.protocols.quasi_newton import OPTIMISERS, lbfgs_to_plateau
from benchmark.protocols.brief_fit import check_start_fit, search_fit
from benchmark.protocols.start_search import (ENCODED_START, START_SEARCH_RULES, is_prior_free, prior_free_start,
                                              searched_start)
from benchmark.protocols.step_rules import PlateauRule, optimise, optimise_to_plateau
from priors.base import FitBatch, PriorAdapter

log = logging.getLogger(__name__)


def fit(adapter: PriorAdapter, body, batch: FitBatch, steps: int, lr: float, lambda_prior: float,
        generator: torch.Generator, device, lr_final_fraction: float = 0.1, loss_vertices: int | None = None,
        callback=None, facing: str = "heading8", shape_lr_scale: float = 1.0,
        points_per_step: int | None = None, latent_init: str = "sample",
        start_search: str = "none", plateau: PlateauRule | None = None,
        multi_start: MultiStart | None = None, optimiser: str = "adam", keep_held: bool = True,
        start_fit: str = "exact") -> tuple[FitState, dict]:
    """Optimise one batch (see module docstring). Returns the state and a log: ``history`` (the
    logged steps), ``data_trace`` ((steps, B) the data term of every sequence at every step, mm)
    and, with ``facing="search"``, the facing search's choices.

    ``loss_vertices``: the data term uses a fixed farthest-point subset of that many mesh vertices
    (a profile size, for CPU speed); None uses every vertex. Evaluation always uses every vertex.

    The data term is the exact Chamfer loss (:func:`benchmark.metrics.chamfer.chamfer_loss`, exact
    nearest neighbours); the search grids of the observed points, which never move, are built once
    per fit (:class:`~benchmark.metrics.chamfer.StaticChamfer`) and shared by the heading search
    and every step.

    ``points_per_step``: where a frame has more observed points, each step's observed points ->
    mesh mean is taken over that many of them drawn uniformly with replacement, anew at every step
    (:meth:`~benchmark.metrics.chamfer.StaticChamfer.sample_b`, seeded from ``generator``): an
    unbiased estimate of the exact data term and of its gradient. The mesh -> observed points
    direction always uses every observed point. None: the exact data term at every step.

    ``latent_init``: where the prior's latents start (:func:`initial_latents`): ``"sample"`` (the
    adapter's ``init_latents``) or ``"mean"`` (table1 protocol v3: the prior's mean).

    ``plateau``: the step rule of protocol v6 (:class:`~benchmark.protocols.step_rules.PlateauRule`):
    ``steps`` is then the cap, and the log's ``plateau`` holds the steps taken and each sequence's
    convergence. None: ``steps`` steps of cosine decay (versions 1-5).

    ``multi_start``: where the start was encoded (``start_search="observation"``, a prior with a
    motion encoder), fit :class:`~benchmark.protocols.multi_start.MultiStart`'s copies of every
    sequence side by side and keep, per sequence, the one with the lowest objective at the last step;
    the log's ``multi_start`` holds each copy's final objective and the chosen copy. None: one start.

    ``keep_held``: under ``plateau`` with Adam, each step evaluates only the sequences still
    descending, the held ones' objective and gradient kept
    (:class:`~benchmark.protocols.kept_rows.KeptRows`; where the sequences are independent,
    :func:`~benchmark.protocols.fit_state.rows_independent`). False evaluates the whole batch at
    every step (the same fit to float rounding; ``perf --only plateau`` times both).

    ``start_fit``: the start search's brief fits, their data term and optimiser
    (``objective.start_fit``, :data:`~benchmark.protocols.brief_fit.START_FITS`).

    ``optimiser``: ``"adam"`` (every table), or ``"lbfgs"`` (a table1 version 8 candidate, with
    ``plateau`` only): the batched L-BFGS of :mod:`benchmark.protocols.quasi_newton` on the same
    objective, every variable at once (``shape_lr_scale`` does not apply), each sequence held at its
    plateau.
    """
    subset = body.loss_vertex_indices(loss_vertices)
    if optimiser not in OPTIMISERS:
        raise ValueError(f"fit: unknown optimiser {optimiser!r}; choose one of {', '.join(OPTIMISERS)}")
    if optimiser == "lbfgs" and plateau is None:
        raise ValueError("fit: optimiser 'lbfgs' needs the plateau step rule (objective.step_rule: plateau)")
    if multi_start is not None and multi_start.choose == "plateau" and (plateau is None or optimiser != "adam"):
        raise ValueError("fit: objective.multi_start choose 'plateau' races the copies to their first plateau: it needs "
                         "the plateau step rule (objective.step_rule: plateau) with Adam")
    if facing not in FACING_RULES:
        raise ValueError(f"fit: unknown facing rule {facing!r}; choose one of {', '.join(FACING_RULES)}")
    B, n = batch.batch_size, batch.num_observed
    data_term = StaticChamfer(batch.points.flatten(0, 1), batch.lengths.flatten(0, 1))
    facing_log = {}
    t_facing = time.perf_counter()
    if start_search not in START_SEARCH_RULES:
        raise ValueError(f"fit: unknown start search {start_search!r}; choose one of {', '.join(START_SEARCH_RULES)}")
    check_start_fit(start_fit)
    own_start = start_search == "observation" and facing == "observation" and is_prior_free(adapter)
    if own_start:  # the prior-free start (facing, limb search) is this fit's start: computed once per observation
        state, facing_log = prior_free_start(body, batch, generator, device, lr, lambda_prior,
                                             start_fit=search_fit(start_fit, encoded=False))
        state.adapter = adapter
    elif facing == "search":
        state, facing_log = facing_search(adapter, body, batch, generator, device, lr, lambda_prior, latent_init=latent_init)
    elif facing == "observation":
        state, facing_log = observed_facing(adapter, body, batch, generator, device, lr, lambda_prior, latent_init=latent_init)
    else:
        state = init_state(adapter, body, batch, generator, device, data_term=data_term, latent_init=latent_init)

    trace = []  # (B,) data term of every step: the convergence diagnostics (benchmark.core.fit_diagnostics)
    objective_trace = []  # (B,) objective of every step: the plateau rule (protocol v6)
    sampler = None
    if points_per_step is not None:
        sampler = torch.Generator().manual_seed(int(torch.randint(0, 2**62, (1,), generator=generator)))

    facing_log["facing_s"] = time.perf_counter() - t_facing
    single, K = state, 1  # the batch's own state (a template after multi_start's selection); copies per sequence
    if start_search in ("limbs", "observation") and not own_start:
        t_search = time.perf_counter()
        copies = multi_start.starts if multi_start is not None and start_search == "observation" else 1
        state, search_log = searched_start(adapter, body, batch, state, start_search, generator, device, lr,
                                           lambda_prior, copies=copies, start_fit=start_fit)
        if copies > 1 and search_log.get("start") == ENCODED_START:  # every copy holds the encoded start
            K = copies
            vary_copies(state, single, multi_start, generator)
            batch = repeat_batch(batch, K)
            B = batch.batch_size
            data_term = StaticChamfer(batch.points.flatten(0, 1), batch.lengths.flatten(0, 1))
        facing_log.update(search_log, start_search_s=time.perf_counter() - t_search)

    prior_trace = []  # (B,) prior term of every step: the history's log

    def objective(st: FitState, bt: FitBatch, chamfer: StaticChamfer, record: bool = True):
        rot, trans = body_parameters(st, bt.timestamps, observed=True)
        rest = body.prepare(st.shape())
        verts = body.skin(rest, rot, trans, vertex_indices=subset).vertices  # (R, n, V, 3)
        data = chamfer(verts.flatten(0, 1), b_sample=points_per_step, generator=sampler).view(bt.batch_size, n)
        data = data.mean(1) * 1000.0
        prior = prior_values(adapter, st.latents)
        value = data + lambda_prior * prior
        if record:
            trace.append(data.detach())
            prior_trace.append(prior.detach())
            objective_trace.append(value.detach())
        return value

    def step_loss(step):
        value = objective(state, batch, data_term)
        data, prior = trace[-1], prior_trace[-1]
        return value.sum(), lambda: {"data_mm": float(data.mean()), "prior": float(prior.mean())}

    def rows_entry():  # a step on some rows: the traces' last entries, which KeptRows.fill completes to the batch
        return {"data_mm": float(trace[-1].mean()), "prior": float(prior_trace[-1].mean())}

    row_views = {}

    def rows_view(rows):  # the batch and data term of the sequences rows, kept while the rows stay
        key = tuple(rows.tolist())
        if key not in row_views:
            row_views.clear()
            row_views[key] = (batch_rows(batch, rows), data_term.select(row_frames(rows, n)))
        return row_views[key]

    def rows_loss(step, rows):
        bt, chamfer = rows_view(rows)
        with adapter.batch_rows(rows):
            return objective(state_rows(state, rows), bt, chamfer).sum(), rows_entry

    groups = parameter_groups(state, lr, shape_lr_scale)
    plateau_log = {}
    if optimiser == "lbfgs":
        history, plateau_log = lbfgs_to_plateau(adapter.name, state.parameters(), steps, lr, step_loss, objective_trace,
                                                plateau, other_traces=(trace,), callback=callback)
    elif plateau is None:
        history = optimise(adapter.name, groups, steps, lr, lr_final_fraction, step_loss, callback=callback)
    else:
        def value_of(rows):  # the per-sequence objective of the sequences rows (None: all), for the check
            if rows is None:
                return objective(state, batch, data_term, record=False)
            return objective(state_rows(state, rows), *rows_view(rows), record=False)

        keep = keep_held and points_per_step is None and rows_independent(value_of, adapter, B, state.shape_param.device)
        history, plateau_log = optimise_to_plateau(adapter.name, groups, steps, lr, lr_final_fraction, step_loss, objective_trace,
                                                   plateau, callback=callback, rows_loss=rows_loss if keep else None,
                                                   row_traces=(trace, prior_trace),
                                                   race=K if K > 1 and multi_start.choose == "plateau" else 1)
    data_trace = torch.stack(trace) if trace else torch.zeros(0, B)
    if K > 1:  # each sequence keeps its copy with the lowest objective at the last step
        final = objective_trace[-1].detach().cpu().double().view(-1, K)
        best = final.argmin(1)
        race = plateau_log.pop("race", None)
        if race is not None:  # choose: plateau; the copies that had not all reached a plateau: chosen at the end
            raced = torch.tensor(race["winner"])
            best = torch.where(raced >= 0, raced, best)
        pick = torch.arange(final.shape[0]) * K + best
        state = select_copies(state, pick.to(single.obs_t.device), single)
        data_trace = data_trace[:, pick.to(data_trace.device)]
        plateau_log = {k: ([v[i] for i in pick.tolist()] if isinstance(v, list) and len(v) == B else v)
                       for k, v in plateau_log.items()}
        facing_log["multi_start"] = {"chosen": best.tolist(),
                                     "objective": [[round(float(v), 4) for v in row] for row in final],
                                     **({"chosen_at_step": race["step"]} if race is not None else {})}
    return state, {"history": history, "data_trace": data_trace, **facing_log,
                   **({"plateau": plateau_log} if plateau_log else {})}


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

