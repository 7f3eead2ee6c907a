"""The ``sls`` protocol: completion with landmarks of one-cycle sequences (docs/protocol.md, "sls").

Paper: Marsot, Wuhrer, Franco, Durocher, "A structured latent space for human body motion
generation" (3DV 2022; paper 001, section 5, Table 1). Rules written here where the paper is
silent are the project's; ``benchmark/tables/sls.yaml`` states them as data.

Data (:func:`load_motions`, :class:`~benchmark.protocols.sls_data.SlsData`)
    Each test motion (synthetic test split, 50 fps, or ``--data``) is cut into one-cycle windows of
    ``data.anchors`` = 100 *anchor frames* uniformly spaced in time, both ends included (tau_i =
    i * D / 99, relative to the cycle start): ``benchmark.synthetic.cycles.cycle_windows`` (the
    generator's phase; gait strides start at the phase offsets ``data.gait_starts``, default the
    left foot strike only, so one motion's cycles never overlap) for a motion whose meta holds the
    generator's plan, else (``--data``)
    :func:`~benchmark.protocols.sls_cycles.fallback_cycles` (its docstring: a motion that does not
    repeat gives no cycle). A cycle across a hole in the timestamps or a teleport of the root is
    left out (:func:`~benchmark.core.plausibility.window_defect`), and every motion or cycle left
    out is named with its reason. Cycles of ``cycle_min_s``..``cycle_max_s`` seconds are kept,
    at most ``data.cycles_per_motion`` per motion (cycle_windows: a subset drawn with its seed 0,
    fixed, so the test sequences never depend on the table seed). Each cycle is rigidly aligned
    as the paper aligned CHUM segments at t = 0 (``data.align: first_anchor``): a yaw about +y
    makes the first anchor's root face +z and its root translation sits at x = z = 0 (height
    kept). Its id is ``<motion id>#c<k>``.
    Ground truth at the anchors: the posed mesh and joints, the 16 landmarks (the vertices
    ``body.landmark_indices``, :data:`benchmark.core.skeleton.LANDMARK_NAMES`) and two independent dense
    scans of ``data.points_per_scan`` points (:func:`benchmark.core.surface_sampling.sample_surface`): the
    *input scan* (what the observation is cut from) and the *evaluation scan* (what the metric is
    measured against), so the metric never rewards fitting the particular input sample. Every
    random draw is seeded per sequence from (table seed, sequence id): a sequence's data does not
    depend on which batch it is in.

Grid (one axis ``sweep``; the runner's grid is a product of axes, the paper's table is two sweeps)
    ``p0 p50 p100 p1000 p10000``: the spatial sweep, all 100 anchors observed with p points per
    scan (a fresh random subset per anchor; p = 0: landmarks only). ``f5 f20 f100``: the temporal
    sweep, all points, observed anchors I_5 = 20, 40, ..., 100, I_20 = 5, 10, ..., 100, I_100 =
    all (1-based; I_f = k * 100 / f, k = 1..f). Landmarks are observed at every observed anchor of
    every cell. The spec's ``sweeps`` mapping decodes each code. Degradation is seeded from (table
    seed, cell, sequence id), never the prior: every prior sees the same observation in a cell.

Objective (per sequence b; means over the observed anchors I)::

    sum_b [ w_dense,b * D_b + w_mocap,b * M_b + w_time,b * T_b + lambda_prior * prior_b ]

    D_b = mean_i ChamferMM(mesh vertices of anchor i, observed points of anchor i)  (mm, Euclidean)
    M_b = mean_i mean_l |landmark vertex l - observed landmark l|^2                   (cm^2)
    T_b = mean_i (tau_hat_i - tau_i)^2                                              ((10 ms)^2)

The units make each term about 1 at a good fit (1 mm Chamfer, 1 cm landmark error, 10 ms), and
D is table1's data term, so lambda_prior = 0.01 means what it means there. A term is *active* when
it has observations: D when p > 0, M always, T only for priors whose adapter has
``decode_anchors`` (decoded timestamps; the paper's w_time = 0 for fixed-duration priors).

Adaptive weights (GradNorm [Chen et al. 2018], as the paper; closed-form variant, per sequence):
every ``adaptive.every`` steps (from step 0), for each active term i, G_i,b = |grad of L_i,b with
respect to the sequence's latents| (unweighted term, all latent tensors together) and the
relative inverse training rate r_i,b = (L_i,b(t) / L_i,b(0)) / mean_j (L_j,b(t) / L_j,b(0)).
GradNorm's fixed point w_i G_i = mean weighted norm * r_i^alpha is solved directly:
w*_i,b = r_i,b^alpha / G_i,b, normalised so that sum_i w*_i,b = number of active terms (GradNorm's
renormalisation), then smoothed: w <- (1 - beta) w + beta w*. Weights start at 1 (as the paper's);
with a single active term the weight stays 1. alpha = ``adaptive.alpha`` (1.5), beta =
``adaptive.smoothing`` (0.5). Weights are positive by construction (G is floored at 1e-12).

Facing (``objective.facing``; protocol v2: ``aligned``): every fit starts with its free root
orientation at identity (or its heading at 0), facing +z, the facing the data rules give each
cycle's first anchor. Protocol v1 (``heading8``) ran table1 v1's 8-yaw T-pose score instead, which
turned landmark-only fits backwards; ``search`` runs table1 v2's coarse multi-hypothesis search.
The body shape has its own learning rate, ``objective.shape_lr_scale`` x lr. Every unit records,
per sequence, the root-orientation and facing errors, a backwards flag, the final data terms and
their decrease over the last 10 % of the steps (:mod:`benchmark.core.fit_diagnostics`).

Variables: the adapter's latents, the body shape and the free rigid parameters that
:func:`benchmark.protocols.fit_state.init_state` gives the adapter (per-observed-anchor root
orientation / translation, or a heading and offset). :func:`~benchmark.protocols.fit_state.init_state`
sees a :class:`~priors.base.FitBatch` whose points are each observed anchor's first
``objective.init_scan_points`` (1000) scan points (i.i.d. uniform samples, so an unbiased subset; it
bounds the cost of the heading search) followed by its 16 landmarks (so p = 0 still has points for
the translation start and the heading search),
timestamps the observed anchor times, window_s the longest cycle of the batch.

Start search (``objective.start_search``, protocol v4: ``observation``):
:func:`benchmark.protocols.sls_fit.sls_start`, table1's search with the aligned facing.

Steps (``objective.step_rule``, protocol v4: ``plateau``): one Adam optimiser at ``objective.lr``
until each sequence's objective (the unweighted sum of its active terms plus lambda_prior x prior)
plateaus (:class:`benchmark.protocols.step_rules.PlateauRule`, with a floor of 1 under the relative
change), then at 0.3 x and 0.09 x that sequence's rate until it plateaus again at each (the rule's
two reductions), then a short cosine anneal to 10 % of each sequence's rate; the profile's steps
are the cap. Versions 1-3: cosine to 10 % of ``objective.lr`` over the profile's steps.

Decoding the anchors: an adapter with ``decode_anchors(latents, shape) -> (Decoded (B, 100, ...),
tau_hat (B, 100))`` gives anchor i directly (the structured latent space's representation) and
its timestamp; the free rigid parameters are applied on top as in
:func:`~benchmark.protocols.fit_state.body_parameters`. Any other adapter is decoded at the anchor
timestamps through ``fit_state.body_parameters`` (per-frame priors at the observed anchors, then
SLERP/LERP; fixed-window priors on their grid covering the cycle; continuous priors directly).

Metric: at all 100 anchors, the vertex Chamfer (mm) between the completed anchor mesh and the
evaluation scan, the point-to-surface Chamfer, the landmark error (mean Euclidean distance over the
16 landmarks, mm) and MPJPE (mm); the derived table gives the mean over all anchors of all
sequences and the standard deviation over sequences.

The fallback cycle cutter (for data without the generator's phase) is
:func:`benchmark.protocols.sls_cycles.fallback_cycles`; the modules: ``sls_cycles`` (cycles),
``sls_data`` (the unit data and the observation), ``sls_fit`` (decoding and the fit), this one (the
protocol-module hooks).
"""

from __future__ import annotations

import dataclasses
import logging
import time

import torch

from benchmark.core.fit_diagnostics import sequence_diagnostics
from benchmark.protocols.completion_unit import evaluate, loss_vertex_count
from benchmark.protocols.step_rules import plateau_rule
from benchmark.protocols.sls_cycles import align_first_anchor, cut_cycles
from benchmark.protocols.sls_data import Observation, SlsData, SlsUnitData, check_same_cells, observe
from benchmark.protocols.sls_fit import decode_anchors, fit_sls, uses_anchor_decoder
from benchmark.data.unit_arrays import ground_truth_pose

log = logging.getLogger(__name__)

KNOWN_KINDS = ("per-frame", "fixed", "continuous")


def load_motions(spec: dict, data: str | None, body) -> dict:
    """{sequence id: one-cycle anchor Motion} from the test motions (the protocol-module hook).

    Ids are ``<motion id>#c<k>``; each Motion has ``data.anchors`` frames at tau = 0 .. D (s)."""
    d = spec["data"]
    motions = source_motions(data, body)
    ids = sorted(motions)
    A = int(d["anchors"])
    left_out: dict = {}
    cycles, cutter = cut_cycles([motions[i] for i in ids], A, float(d["cycle_min_s"]), float(d["cycle_max_s"]),
                                int(d.get("cycles_per_motion", 1)), tuple(d.get("gait_starts", (0.0,))), skipped=left_out)
    out = {}
    skipped = []
    for sid, cs in zip(ids, cycles):
        if not cs:
            skipped.append(sid)
        for k, w in enumerate(cs):
            if w.num_frames != A:
                raise ValueError(f"sls: the cycle cutter ({cutter}) gave {w.num_frames} frames for {sid}, expected {A}")
            if d.get("align") == "first_anchor":
                w = align_first_anchor(w)
            cid = f"{sid}#c{k}"
            cyc = dict(w.meta.get("cycle", {}))
            meta = {**dict(w.meta), "cycle": {**cyc, "cutter": cyc.get("cutter", cutter)}}
            out[cid] = dataclasses.replace(w, source=cid, meta=meta)
    reasons = {ids[k]: "; ".join(r) for k, r in sorted(left_out.items())}
    dropped = [sid for sid in reasons if sid not in skipped]
    for sid in dropped:  # a motion that kept some cycles: the ones left out, with their reasons
        log.warning("sls: %s: left out %s", sid, reasons[sid])
    if skipped:
        log.warning("sls: %d of %d motions have no usable motion cycle of %s-%s s and are left out: %s", len(skipped),
                    len(ids), d["cycle_min_s"], d["cycle_max_s"], _named(skipped, reasons, 10))
    if not out:
        where = f"--data {data}" if data is not None else "the synthetic test split"
        raise ValueError(f"{where}: sls found no usable motion cycle of {d['cycle_min_s']}-{d['cycle_max_s']} s in any "
                         f"of its {len(ids)} motions ({_named(ids, reasons, 3)}; cutter: {cutter}); "
                         "sls completes one-cycle sequences: give motions that repeat a movement (walking, running) "
                         "with at least one whole cycle, or run another table on these motions")
    log.info("sls: %d one-cycle sequences from %d motions (%s)", len(out), len(ids), cutter)
    return out


def _named(ids: list, reasons: dict, n: int) -> str:
    """The first ``n`` motions, each with its reason, then how many more."""
    text = "; ".join(f"{sid} ({reasons[sid]})" if sid in reasons else sid for sid in ids[:n])
    return text + (f"; and {len(ids) - n} more" if len(ids) > n else "")


def source_motions(data: str | None, body) -> dict:
    """The whole test motions by id (the synthetic test split, or ``--data``); tests replace this."""
    from benchmark.data.table_data import load_motions as load_table_motions

    return load_table_motions(data, 0.0, body)


# ============================================================================ the protocol module
def make_source(spec: dict, body, motions_by_id: dict, seed: int) -> SlsData:
    check_same_cells(spec)  # a column shown as another's must be its observation
    return SlsData(spec, body, motions_by_id, seed)


def na_reason(spec: dict, adapter) -> str | None:
    kind = adapter.window.kind
    if uses_anchor_decoder(adapter) or kind in KNOWN_KINDS:
        return None
    return (f"prior {adapter.name!r} has window kind {kind!r} and no decode_anchors: the sls protocol "
            f"decodes anchors through decode_anchors or completion.body_parameters ({', '.join(KNOWN_KINDS)})")


def run_unit(unit, spec: dict, profile: dict, adapter, body, source: SlsData, device) -> dict:
    code = unit.cell["sweep"]
    data = source.unit_data(unit.sequence_ids)
    obs = observe(data, spec, code, source.seed, list(unit.sequence_ids))
    g = torch.Generator().manual_seed(unit.seed)
    t0 = time.perf_counter()
    state, info = fit_sls(adapter, body, obs, data.anchor_t, int(profile["steps"]), spec["objective"], g, device,
                          loss_vertices=loss_vertex_count(profile), plateau=plateau_rule(spec))
    t1 = time.perf_counter()
    with torch.no_grad():
        rot, trans, tau_hat = decode_anchors(state, data.anchor_t.to(device), None)
        output = body.skin(body.prepare(state.shape()), rot, trans)
    sp = profile.get("surface_points", "all")
    per_seq = evaluate(body, output, data.eval, device, surface_points=None if sp in (None, "all") else int(sp))
    lm_err = (body.landmarks(output.vertices).cpu() - data.gt_landmarks.cpu().to(torch.float32)).norm(dim=-1).mean(-1)  # (B, A)
    t2 = time.perf_counter()
    motions = [source.motions[sid] for sid in unit.sequence_ids]
    gt_pose = ground_truth_pose(source.body, motions, data.anchor_t)
    diagnostics = sequence_diagnostics(info["data_trace"], rot[:, :, 0], gt_pose[0][:, :, 0], plateau=info.get("plateau"))
    for b, (sid, row) in enumerate(zip(unit.sequence_ids, per_seq)):
        row["id"] = sid
        row["diagnostics"] = diagnostics[b]
        row["sums"]["landmark_m"] = float(lm_err[b].sum())
        if tau_hat is not None:
            row["tau_mae_s"] = float((tau_hat[b].detach().cpu().double() - data.anchor_t[b]).abs().mean())
    return {
        "unit_id": unit.unit_id, "spec_hash": unit.spec_hash, "prior": unit.prior, "cell": dict(unit.cell),
        "sequence_ids": list(unit.sequence_ids), "fingerprint": obs.fingerprint, "per_sequence": per_seq,
        "timings": {"fit_s": t1 - t0, "eval_s": t2 - t1,
                    **({"start_search_s": info["start_search_s"]} if "start_search_s" in info else {})},
        "device": str(device), "na_reason": None,
        **({"start_search": {"start_choice_counts": info["start_choice_counts"]}} if "start_choice_counts" in info else {}),
        "fit_log": info["history"], "terms": info["terms"], "final_weights": info["weights"],
        "decoder": "decode_anchors" if uses_anchor_decoder(adapter) else "completion.body_parameters",
        "arrays": unit_arrays(unit, data, obs, rot, trans, state.shape(), gt_pose),  # the runner stores it as .npz
    }


def unit_arrays(unit, data: SlsUnitData, obs: Observation, rot, trans, shape, gt_pose) -> dict:
    """The fitted and ground-truth motion at the anchors and a subsample of the observed scans,
    for the report's animations (:mod:`benchmark.data.unit_arrays`)."""
    from benchmark.data.unit_arrays import fit_arrays

    gt_rot, gt_trans, gt_shape = gt_pose
    t0 = data.anchor_t[:, :1]
    return fit_arrays(unit, data.anchor_t - t0, rot, trans, shape, gt_rot, gt_trans, gt_shape, obs.timestamps - t0,
                      obs.points)
