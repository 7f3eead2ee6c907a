"""The ``sls`` protocol: completion with landmarks of one-cycle sequences (docs/protocol.md, "sls").

Paper: Marsot, Wuhrer, Franco, Durocher, "A structured latent space for human body motion
generation" (3DV 2022; paper 001, section 5, Table 1). Rules written here where the paper is
silent are the project's; ``benchmark/tables/sls.yaml`` states them as data.

Data (:func:`load_motions`, :class:`SlsData`)
    Each test motion (synthetic test split, 50 fps, or ``--data``) is cut into one-cycle windows of
    ``data.anchors`` = 100 *anchor frames* uniformly spaced in time, both ends included (tau_i =
    i * D / 99, relative to the cycle start): ``benchmark.synthetic.cycles.cycle_windows`` (the
    generator's phase; gait strides start at the phase offsets ``data.gait_starts``, default the
    left foot strike only, so one motion's cycles never overlap) when importable, else
    :func:`fallback_cycles` (below). Cycles of ``cycle_min_s``..``cycle_max_s`` seconds are kept,
    at most ``data.cycles_per_motion`` per motion (cycle_windows: a subset drawn with its seed 0,
    fixed, so the test sequences never depend on the table seed). Each cycle is rigidly aligned
    as the paper aligned CHUM segments at t = 0 (``data.align: first_anchor``): a yaw about +y
    makes the first anchor's root face +z and its root translation sits at x = z = 0 (height
    kept). Its id is ``<motion id>#c<k>``.
    Ground truth at the anchors: the posed mesh and joints, the 16 landmarks (the vertices
    ``body.landmark_indices``, :data:`benchmark.skeleton.LANDMARK_NAMES`) and two independent dense
    scans of ``data.points_per_scan`` points (:func:`benchmark.surface_sampling.sample_surface`): the
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
their decrease over the last 10 % of the steps (:mod:`benchmark.fit_diagnostics`).

Variables: the adapter's latents, the body shape and the free rigid parameters that
:func:`benchmark.protocols.fit_state.init_state` gives the adapter (per-observed-anchor root
orientation / translation, or a heading and offset). :func:`~benchmark.protocols.fit_state.init_state`
sees a :class:`~priors.base.FitBatch` whose points are each observed anchor's first
``objective.init_scan_points`` (1000) scan points (i.i.d. uniform samples, so an unbiased subset; it
bounds the cost of the heading search) followed by its 16 landmarks (so p = 0 still has points for
the translation start and the heading search),
timestamps the observed anchor times, window_s the longest cycle of the batch. One Adam optimiser,
cosine schedule to 10 % of ``objective.lr`` over the profile's steps.

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

Fallback cycle cutter (:func:`fallback_cycles`, for data without the generator's phase): the pose
signal x(t) = the local rotation matrices of joints 1..21 (the root's heading excluded); the
period L is the smallest lag in [cycle_min_s, min(cycle_max_s, span / 2)] that is a local minimum
of the normalised mean squared difference d(L) = mean_t |x(t + L) - x(t)|^2 / (2 var x) below
``d_min + 0.2 (d_max - d_min)`` (YIN-style, so the fundamental wins over its multiples), and the
motion must be periodic (d(L) < 0.5). Cycle boundaries are the local minima of the projection of x
on its first principal direction that are the lowest within +-0.3 L (interior frames only);
consecutive boundaries 0.85 L to 1.15 L apart whose poses agree (|x(t1) - x(t0)|^2 / (2 var x) <=
max(0.1, 3 d(L))) make a cycle. Frame-quantised (20 ms at 50 fps).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import time
from dataclasses import dataclass

import roma
import torch

from benchmark.degrade import degrade, fingerprint
from benchmark.metrics.static_chamfer import StaticChamfer
from benchmark.observations import Landmarks, PointCloudSequence, ground_truth_at
from benchmark.fit_diagnostics import sequence_diagnostics
from benchmark.protocols.completion_unit import evaluate, loss_vertex_count
from benchmark.protocols.facing import facing_search
from benchmark.protocols.fit_state import (FitState, apply_free_rigid, body_parameters, init_state, optimise,
                                           parameter_groups)
from benchmark.protocols.unit_data import UnitData
from benchmark.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from benchmark.surface_sampling import sample_surface
from benchmark.work_units import stable_seed
from benchmark.unit_arrays import ground_truth_pose
from priors.base import AnchorDecoder, FitBatch, PriorAdapter

log = logging.getLogger(__name__)

KNOWN_KINDS = ("per-frame", "fixed", "continuous")
# Term scales: D in mm (x1e3 of metres), M in cm^2 (x1e4 of m^2), T in (10 ms)^2 (x1e4 of s^2).
DENSE_SCALE, MOCAP_SCALE, TIME_SCALE = 1e3, 1e4, 1e4
GRAD_FLOOR = 1e-12


# ============================================================================ cycles
def fallback_cycles(motion, min_s: float = 0.3, max_s: float = 3.0, max_cycles: int | None = None) -> list[tuple[float, float]]:
    """One-cycle windows [(t0, t1), ...] (seconds, the motion's own clock) found from the pose
    signal alone (see the module docstring). Empty when the motion is not periodic."""
    poses = torch.as_tensor(motion.poses, dtype=torch.float64)
    ts = torch.as_tensor(motion.timestamps, dtype=torch.float64)
    T = poses.shape[0]
    if T < 4:
        return []
    fps = (T - 1) / float(ts[-1] - ts[0])
    x = axis_angle_to_matrix(poses[:, 1:]).reshape(T, -1)
    x = x - x.mean(0)
    var = float(x.square().sum(1).mean())
    if var < 1e-8:
        return []
    lo = max(1, math.ceil(min_s * fps - 1e-9))
    hi = min(int(math.floor(max_s * fps + 1e-9)), T // 2)
    if hi < lo + 2:
        return []
    lags = torch.arange(lo - 1, hi + 2)
    d = torch.stack([(x[int(L):] - x[: T - int(L)]).square().sum(1).mean() for L in lags.clamp_min(1)]) / (2 * var)
    inner = d[1:-1]
    local = (inner <= d[:-2]) & (inner <= d[2:])
    thr = float(inner.min()) + 0.2 * float(inner.max() - inner.min())
    cand = torch.nonzero(local & (inner <= thr)).flatten()
    if cand.numel() == 0 or float(inner[cand[0]]) > 0.5:
        return []
    L = int(lags[1:-1][cand[0]])
    u = x @ torch.linalg.svd(x, full_matrices=False).Vh[0]
    w = max(1, int(round(0.3 * L)))
    padded = torch.nn.functional.pad(u[None, None], (w, w), mode="replicate")[0, 0]
    is_min = u <= padded.unfold(0, 2 * w + 1, 1).amin(1)
    events = []
    for i in torch.nonzero(is_min).flatten().tolist():
        if i == 0 or i == T - 1 or u[i] > u[i - 1] or u[i] > u[i + 1]:  # an end of the motion, not a minimum
            continue
        if not events or i - events[-1] >= 0.5 * L:
            events.append(i)
    cycles = []
    for a, b in zip(events, events[1:]):
        dur = float(ts[b] - ts[a])
        closes = float((x[b] - x[a]).square().sum()) / (2 * var) <= max(0.1, 3 * float(inner[cand[0]]))
        if 0.85 * L <= b - a <= 1.15 * L and closes and min_s - 1e-9 <= dur <= max_s + 1e-9:
            cycles.append((float(ts[a]), float(ts[b])))
            if max_cycles is not None and len(cycles) >= max_cycles:
                break
    return cycles


def cut_cycles(motions: list, anchors: int, min_s: float, max_s: float, per_motion: int,
               gait_starts=(0.0,)) -> tuple[list[list], str]:
    """Per motion, up to ``per_motion`` one-cycle Motions of ``anchors`` frames (timestamps 0 .. D,
    the source's world frame, ``meta["cycle"]`` with the cycle's start/end in the source's time);
    and the name of the cutter used.

    ``benchmark.synthetic.cycles.cycle_windows`` (the generator's phase; cycles start at the phase
    offsets ``gait_starts``, default the left foot strike only, so a motion's cycles never overlap;
    a seeded (seed 0) subset of ``per_motion`` when there are more) when importable, else
    :func:`fallback_cycles` (the first ``per_motion`` cycles) resampled here.
    """
    try:
        from benchmark.synthetic.cycles import cycle_windows
    except ImportError:
        cycle_windows = None
    out: list[list] = [[] for _ in motions]
    if cycle_windows is None:
        for k, m in enumerate(motions):
            for t0, t1 in fallback_cycles(m, min_s, max_s, per_motion):
                tau = torch.linspace(0.0, t1 - t0, anchors, dtype=torch.float64)
                w = m.resample(t0 + tau)
                meta = {**dict(m.meta), "cycle": {"start": t0, "end": t1, "kind": "fallback", "motion_index": k,
                                                  "source": m.source}}
                out[k].append(dataclasses.replace(w, timestamps=tau, meta=meta))
        return out, "sls.fallback_cycles (pose-signal period and principal-component minima)"
    windows = cycle_windows(motions, anchors=anchors, min_s=min_s, max_s=max_s, gait_starts=tuple(gait_starts),
                            max_per_motion=per_motion, seed=0)
    for w in windows:
        out[int(w.meta["cycle"]["motion_index"])].append(w)
    return out, "benchmark.synthetic.cycles.cycle_windows"


def align_first_anchor(m):
    """The cycle Motion rigidly moved so its first anchor's root faces +z with its root translation
    at x = z = 0 (height kept): a yaw about +y applied to the whole motion (world-rigid)."""
    poses, trans = m.poses.double(), m.trans.double()
    R = axis_angle_to_matrix(poses[:, 0])
    fwd = R[0, :, 2]
    yaw = -math.atan2(float(fwd[0]), float(fwd[2]))
    Y = roma.rotvec_to_rotmat(torch.tensor([0.0, yaw, 0.0], dtype=torch.float64))
    poses = poses.clone()
    poses[:, 0] = matrix_to_axis_angle(Y @ R)
    trans = (trans - trans[0]) @ Y.T
    trans[:, 1] += float(m.trans[0, 1])
    return dataclasses.replace(m, poses=poses.float(), trans=trans.float())


def load_motions(spec: dict, data: str | None, body) -> dict:
    """{sequence id: one-cycle anchor Motion} from the test motions (the protocol-module hook).

    Ids are ``<motion id>#c<k>``; each Motion has ``data.anchors`` frames at tau = 0 .. D (s)."""
    d = spec["data"]
    motions = source_motions(data, body)
    ids = sorted(motions)
    A = int(d["anchors"])
    cycles, cutter = cut_cycles([motions[i] for i in ids], A, float(d["cycle_min_s"]), float(d["cycle_max_s"]),
                                int(d.get("cycles_per_motion", 1)), tuple(d.get("gait_starts", (0.0,))))
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
            meta = {**dict(w.meta), "cycle": {**dict(w.meta.get("cycle", {})), "cutter": cutter}}
            out[cid] = dataclasses.replace(w, source=cid, meta=meta)
    if skipped:
        log.warning("sls: %d motions have no motion cycle of %s-%s s and are left out: %s", len(skipped),
                    d["cycle_min_s"], d["cycle_max_s"], skipped[:5])
    if not out:
        raise ValueError(f"sls: no motion cycle found in {len(ids)} motions ({cutter}); check the data")
    log.info("sls: %d one-cycle sequences from %d motions (%s)", len(out), len(ids), cutter)
    return out


def source_motions(data: str | None, body) -> dict:
    """The whole test motions by id (the synthetic test split, or ``--data``); tests replace this."""
    from benchmark.table_data import load_motions as load_table_motions

    return load_table_motions(data, 0.0, body)


# ============================================================================ data
@dataclass
class SlsUnitData:
    anchor_t: torch.Tensor  # (B, A) seconds from the cycle start
    scans: PointCloudSequence  # (B, A, N, 3) input scans at the anchors
    landmarks: torch.Tensor  # (B, A, 16, 3) observed landmarks (noisy when data.landmark_noise_std > 0)
    gt_landmarks: torch.Tensor  # (B, A, 16, 3) the landmark vertices of the ground-truth mesh
    eval: UnitData  # evaluation scans (gt_points) and joints at the anchors


class SlsData:
    """Builds and caches (the last batch) the anchors' ground truth of batches of sequences."""

    def __init__(self, spec: dict, body, motions_by_id: dict, seed: int):
        self.spec, self.body, self.motions, self.seed = spec, body, motions_by_id, seed
        self._cache: dict = {}

    def unit_data(self, ids: list[str]) -> SlsUnitData:
        key = tuple(ids)
        if key in self._cache:
            return self._cache[key]
        d = self.spec["data"]
        n_points = int(d["points_per_scan"])
        noise = float(d.get("scan_noise_std", 0.0))
        motions = [self.motions[s] for s in ids]
        A = int(d["anchors"])
        for s, m in zip(ids, motions):
            if m.num_frames != A:
                raise ValueError(f"sls: sequence {s} has {m.num_frames} frames, expected {A} anchors (use sls.load_motions)")
        t = torch.stack([torch.as_tensor(m.timestamps, dtype=torch.float64) for m in motions])
        gt = ground_truth_at(self.body, motions, t)
        faces = self.body.faces
        scans, evals = [], []
        with torch.no_grad():
            for b, s in enumerate(ids):
                g_in = torch.Generator().manual_seed(stable_seed("sls-scan", self.seed, s))
                g_ev = torch.Generator().manual_seed(stable_seed("sls-eval-scan", self.seed, s))
                scans.append(sample_surface(gt.vertices[b:b + 1], faces, n_points, g_in, noise))
                evals.append(sample_surface(gt.vertices[b:b + 1], faces, n_points, g_ev, noise))
        points = torch.cat(scans)
        B = len(ids)
        pcs = PointCloudSequence(points=points, lengths=torch.full((B, A), n_points, dtype=torch.long), timestamps=t)
        gt_landmarks = self.body.landmarks(gt.vertices)
        landmarks = gt_landmarks
        lm_noise = float(d.get("landmark_noise_std", 0.0))
        if lm_noise > 0:
            rows = [torch.randn(landmarks.shape[1:], generator=torch.Generator().manual_seed(stable_seed("sls-lm", self.seed, s)))
                    for s in ids]
            landmarks = landmarks + lm_noise * torch.stack(rows).to(landmarks)
        data = SlsUnitData(anchor_t=t, scans=pcs, landmarks=landmarks, gt_landmarks=gt_landmarks,
                           eval=UnitData(scans=None, out_t=t, gt_points=torch.cat(evals), gt_joints=gt.joints))
        self._cache = {key: data}
        return data


# ============================================================================ observations
@dataclass
class Observation:
    index: torch.Tensor  # (n,) long, 0-based observed anchors
    points: torch.Tensor | None  # (B, n, P, 3) or None (landmarks only)
    landmarks: torch.Tensor  # (B, n, 16, 3)
    timestamps: torch.Tensor  # (B, n) observed anchor times (tau)
    fingerprint: str


def sweep_rule(spec: dict, code: str) -> tuple[int | None, int]:
    """(points per scan or None for all, observed anchor count) of a sweep code (spec ``sweeps``)."""
    sweeps = spec.get("sweeps") or {}
    if code not in sweeps:
        raise ValueError(f"{spec.get('_source', 'benchmark/tables/sls.yaml')}: grid value {code!r} has no entry in "
                         f"'sweeps' (known: {sorted(sweeps)}); add {{points: ..., frames: ...}} for it")
    rule = sweeps[code]
    pts = rule.get("points", "all")
    return (None if pts == "all" else int(pts)), int(rule.get("frames", spec["data"]["anchors"]))


def observed_anchors(anchors: int, frames: int) -> torch.Tensor:
    """0-based I_f: anchors k * A / f (1-based), k = 1..f (I_5 of 100 = 20, 40, ..., 100)."""
    if frames < 1 or anchors % frames:
        raise ValueError(f"sls: {frames} observed frames do not divide the {anchors} anchors evenly")
    step = anchors // frames
    return torch.arange(1, frames + 1) * step - 1


def observe(data: SlsUnitData, spec: dict, code: str, seed: int, ids: list[str]) -> Observation:
    """The cell's observation: the observed anchors' (sub-sampled) scans and landmarks."""
    points, frames = sweep_rule(spec, code)
    A = data.anchor_t.shape[1]
    idx = observed_anchors(A, frames)
    t = data.anchor_t[:, idx]
    lm = data.landmarks[:, idx]
    B = len(ids)
    prints = []
    obs_points = None
    if points != 0:
        rows = []
        for b, s in enumerate(ids):
            pcs = PointCloudSequence(points=data.scans.points[b:b + 1, idx], lengths=data.scans.lengths[b:b + 1, idx],
                                     timestamps=t[b:b + 1])
            if points is not None:
                pcs = degrade(pcs, points, None, seed=stable_seed("sls-degrade", seed, code, s))
            rows.append(pcs.points)
            prints.append(fingerprint(pcs))
        obs_points = torch.cat(rows)
    for b in range(B):
        prints.append(fingerprint(Landmarks(positions=lm[b:b + 1], timestamps=t[b:b + 1])))
    fp = hashlib.sha256("|".join([code, *prints]).encode()).hexdigest()
    return Observation(index=idx, points=obs_points, landmarks=lm, timestamps=t, fingerprint=fp)


# ============================================================================ decoding
def uses_anchor_decoder(adapter) -> bool:
    """Whether the adapter decodes its anchors itself (an :class:`~priors.base.AnchorDecoder`)."""
    return isinstance(adapter, AnchorDecoder)


def _rigid(state: FitState, rot: torch.Tensor, trans: torch.Tensor | None, timestamps: torch.Tensor):
    """The free rigid parameters of ``state`` applied to decoded (rot, trans) at ``timestamps``."""
    rot, trans = apply_free_rigid(state, rot, trans, timestamps)
    if trans is None:
        raise ValueError(f"prior {state.adapter.name!r}: decode_anchors gave no translation and the protocol has none free")
    return rot, trans


def decode_anchors(state: FitState, anchor_t: torch.Tensor, index: torch.Tensor | None):
    """Rotations (B, k, 22, 3, 3), translation (B, k, 3) and decoded timestamps (B, k) or None at
    the anchors ``index`` (None: all). ``anchor_t`` (B, A) are the anchors' true timestamps."""
    a = state.adapter
    if uses_anchor_decoder(a):
        shape = state.shape() if a.shape_conditioned else None
        dec, tau_hat = a.decode_anchors(state.latents, shape)
        B, A = anchor_t.shape
        if dec.rotations.shape[:3] != (B, A, 22) or tuple(tau_hat.shape) != (B, A):
            raise ValueError(f"prior {a.name!r}: decode_anchors gave rotations {tuple(dec.rotations.shape)} and tau_hat "
                             f"{tuple(tau_hat.shape)}, expected ({B}, {A}, 22, 3, 3) and ({B}, {A})")
        rot, trans = dec.rotations, dec.trans
        if index is not None:
            rot, tau_hat = rot[:, index], tau_hat[:, index]
            trans = None if trans is None else trans[:, index]
        t = anchor_t if index is None else anchor_t[:, index]
        rot, trans = _rigid(state, rot, trans, t)
        return rot, trans, tau_hat
    if index is not None and torch.equal(anchor_t[:, index], state.obs_t):
        rot, trans = body_parameters(state, state.obs_t, observed=True)
    else:
        rot, trans = body_parameters(state, anchor_t if index is None else anchor_t[:, index])
    return rot, trans, None


# ============================================================================ fit
@dataclass
class AdaptiveWeights:
    """Closed-form GradNorm weights per (term, sequence); see the module docstring."""

    active: list
    batch: int
    alpha: float = 1.5
    smoothing: float = 0.5
    every: int = 10

    def __post_init__(self):
        self.w = torch.ones(len(self.active), self.batch, dtype=torch.float64)
        self.initial: torch.Tensor | None = None

    def due(self, step: int) -> bool:
        return len(self.active) > 1 and step % max(self.every, 1) == 0

    def update(self, losses: torch.Tensor, grad_norms: torch.Tensor) -> None:
        """losses, grad_norms: (n_terms, B) unweighted term values and their latent-gradient norms."""
        losses = losses.detach().double().cpu()
        grad_norms = grad_norms.detach().double().cpu()
        if self.initial is None:
            self.initial = losses.clamp_min(1e-12)
        ratio = (losses / self.initial).clamp_min(1e-12)
        r = ratio / ratio.mean(0, keepdim=True)
        target = r.pow(self.alpha) / grad_norms.clamp_min(GRAD_FLOOR)
        target = len(self.active) * target / target.sum(0, keepdim=True)
        self.w = (1 - self.smoothing) * self.w + self.smoothing * target


def _latent_grad_norms(terms: list[torch.Tensor], latents: list[torch.Tensor]) -> torch.Tensor:
    """(n_terms, B): per sequence, |d term_b / d latents_b| over all latent tensors."""
    B = terms[0].shape[0]
    rows = []
    for term in terms:
        grads = torch.autograd.grad(term.sum(), latents, retain_graph=True, allow_unused=True)
        sq = torch.zeros(B, dtype=torch.float64, device=term.device)
        for g in grads:
            if g is not None:
                sq = sq + g.reshape(B, -1).double().square().sum(1)
        rows.append(sq.sqrt())
    return torch.stack(rows)


def active_terms(adapter, obs: Observation, objective: dict) -> list[str]:
    terms = []
    if obs.points is not None:
        terms.append("dense")
    terms.append("mocap")
    if uses_anchor_decoder(adapter) and objective.get("time_term", True):
        terms.append("time")
    return terms


def fit_sls(adapter: PriorAdapter, body, obs: Observation, anchor_t: torch.Tensor, steps: int, objective: dict,
            generator: torch.Generator, device, loss_vertices: int | None = None) -> tuple[FitState, dict]:
    """Optimise one batch against its observation (see module docstring)."""
    lr = float(objective["lr"])
    lam = float(objective["lambda_prior"])
    ad = objective.get("adaptive", {}) or {}
    lr_final = float(objective.get("lr_final_fraction", 0.1))
    B, n = obs.landmarks.shape[:2]
    idx = obs.index.to(device)
    anchor_t = anchor_t.to(device)
    obs_t = obs.timestamps.to(device)
    lm = obs.landmarks.to(device)
    pts = None if obs.points is None else obs.points.to(device)
    cap = objective.get("init_scan_points")
    init_pts = lm if pts is None else torch.cat([pts if cap in (None, "all") else pts[:, :, : int(cap)], lm], dim=2)
    batch = FitBatch(points=init_pts, lengths=torch.full((B, n), init_pts.shape[2], dtype=torch.long, device=device),
                     timestamps=obs_t, window_s=float(anchor_t[:, -1].max()), output_timestamps=anchor_t)
    facing = str(objective.get("facing", "heading8"))
    latent_init = str(objective.get("latent_init", "sample"))  # v3: "mean" (as table1 v3)
    if facing == "search":
        state, _ = facing_search(adapter, body, batch, generator, device, lr, lam, latent_init=latent_init)
    elif facing in ("heading8", "aligned"):  # aligned: start facing +z, as the data rules align every sequence
        state = init_state(adapter, body, batch, generator, device, search_heading=facing == "heading8",
                           latent_init=latent_init)
    else:
        raise ValueError(f"sls: unknown objective.facing {facing!r}; choose heading8 (protocol v1), aligned or search")
    subset = body.loss_vertex_indices(loss_vertices)
    lm_idx = body.landmark_indices.to(device)
    skin_idx = lm_idx if pts is None else (None if subset is None else torch.cat([subset.to(device), lm_idx]))
    terms_used = active_terms(adapter, obs, objective)
    weights = AdaptiveWeights(terms_used, B, alpha=float(ad.get("alpha", 1.5)), smoothing=float(ad.get("smoothing", 0.5)),
                              every=int(ad.get("every", 10)))
    latents = list(state.latents.values())
    # the observed points never move: their search structures are built once (same values as chamfer_loss)
    dense = None if pts is None else StaticChamfer(pts.flatten(0, 1))

    trace = []  # (B,) the unweighted sum of the active data terms at every step (fit diagnostics)

    def step_loss(step):
        rot, trans, tau_hat = decode_anchors(state, anchor_t, idx)
        rest = body.prepare(state.shape())
        verts = body.skin(rest, rot, trans, vertex_indices=skin_idx).vertices  # (B, n, K, 3)
        pred_lm = verts[:, :, -lm_idx.numel():] if skin_idx is not None else verts.index_select(2, lm_idx)
        terms = {"mocap": (pred_lm - lm).square().sum(-1).mean((1, 2)) * MOCAP_SCALE}
        if pts is not None:
            v = verts[:, :, : verts.shape[2] - lm_idx.numel()] if skin_idx is not None else verts
            terms["dense"] = dense(v.flatten(0, 1)).view(B, n).mean(1) * DENSE_SCALE
        if "time" in terms_used:
            terms["time"] = (tau_hat.double() - obs_t).square().mean(1).to(verts.dtype) * TIME_SCALE
        values = [terms[k] for k in terms_used]
        trace.append(sum(v.detach() for v in values))
        if weights.due(step):
            weights.update(torch.stack([v.detach() for v in values]), _latent_grad_norms(values, latents))
        w = weights.w.to(device=device, dtype=verts.dtype)
        data = sum(w[i] * values[i] for i in range(len(values)))
        prior = adapter.prior_term(state.latents)

        def log():
            entry = {"prior": float(prior.detach().mean())}
            for i, k in enumerate(terms_used):
                entry[k] = float(values[i].detach().mean())
                entry[f"w_{k}"] = float(weights.w[i].mean())
            return entry

        return (data + lam * prior).sum(), log

    params = parameter_groups(state, lr, float(objective.get("shape_lr_scale", 1.0)))  # as table1 v2
    history = optimise(adapter.name, params, steps, lr, lr_final, step_loss)
    return state, {"history": history, "terms": terms_used, "data_trace": torch.stack(trace) if trace else torch.zeros(0, B),
                   "weights": {k: weights.w[i].tolist() for i, k in enumerate(terms_used)}}


# ============================================================================ the protocol module
def make_source(spec: dict, body, motions_by_id: dict, seed: int) -> SlsData:
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
                          loss_vertices=loss_vertex_count(profile))
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
    diagnostics = sequence_diagnostics(info["data_trace"], rot[:, :, 0], gt_pose[0][:, :, 0])
    for b, (sid, row) in enumerate(zip(unit.sequence_ids, per_seq)):
        row["id"] = sid
        row["diagnostics"] = diagnostics[b]
        row["sums"]["landmark_m"] = float(lm_err[b].sum())
        if tau_hat is not None:
            row["tau_mae_s"] = float((tau_hat[b].detach().cpu().double() - data.anchor_t[b]).abs().mean())
    return {
        "unit_id": unit.unit_id, "spec_hash": unit.spec_hash, "prior": unit.prior, "cell": dict(unit.cell),
        "sequence_ids": list(unit.sequence_ids), "fingerprint": obs.fingerprint, "per_sequence": per_seq,
        "timings": {"fit_s": t1 - t0, "eval_s": t2 - t1}, "device": str(device), "na_reason": None,
        "fit_log": info["history"], "terms": info["terms"], "final_weights": info["weights"],
        "decoder": "decode_anchors" if uses_anchor_decoder(adapter) else "completion.body_parameters",
        "arrays": unit_arrays(unit, data, obs, rot, trans, state.shape(), gt_pose),  # the runner stores it as .npz
    }


def unit_arrays(unit, data: SlsUnitData, obs: Observation, rot, trans, shape, gt_pose) -> dict:
    """The fitted and ground-truth motion at the anchors and a subsample of the observed scans,
    for the report's animations (:mod:`benchmark.unit_arrays`)."""
    from benchmark.unit_arrays import fit_arrays

    gt_rot, gt_trans, gt_shape = gt_pose
    t0 = data.anchor_t[:, :1]
    return fit_arrays(unit, data.anchor_t - t0, rot, trans, shape, gt_rot, gt_trans, gt_shape, obs.timestamps - t0,
                      obs.points)
