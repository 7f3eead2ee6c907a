"""The one-cycle windows of the ``sls`` protocol: cutting the test motions into cycles of anchor
frames and aligning each cycle (the data rules: :mod:`benchmark.protocols.sls`).

Fallback cycle cutter (:func:`fallback_cycles`, for data without the generator's phase): the pose
signal x(t) = the local rotation matrices of joints 1..21 (the root's heading excluded); the
period L is the smallest lag in [cycle_min_s, min(cycle_max_s, span / 2)] that is a local minimum
of the normalised mean squared difference d(L) = mean_t |x(t + L) - x(t)|^2 / (2 var x) below
``d_min + 0.2 (d_max - d_min)`` (YIN-style, so the fundamental wins over its multiples), and the
motion must be periodic (d(L) < 0.5). Cycle boundaries are the local minima of the projection of x
on its first principal direction that are the lowest within +-0.3 L (interior frames only);
consecutive boundaries 0.85 L to 1.15 L apart whose poses agree (|x(t1) - x(t0)|^2 / (2 var x) <=
max(0.1, 3 d(L))) make a cycle; where the pose already repeats within it at a half or a third of
its length (the same closure test), it is cut into those 2 or 3 parts: a motion whose cadence
changes is cut at its dominant period L, and two strides of a faster part would otherwise pass as
one cycle. Frame-quantised (20 ms at 50 fps).

Which cutter: a motion whose meta holds the generator's plan (the synthetic splits) is cut by
``benchmark.synthetic.cycles.cycle_windows`` on that plan's gait phase; every other motion (``--data``)
by :func:`fallback_cycles`, whose period and pose-closure checks keep a motion that does not repeat
from yielding a "cycle". Either way a cycle is left out, with its reason
(:func:`benchmark.core.plausibility.window_defect`, shared with the other tables' windows), when
it spans a hole in the timestamps (an interval more than ``GAP_RATIO`` = 2.5 times the motion's median
frame interval: frames are missing and the anchors would be interpolated across them) or a root
step faster than ``MAX_ROOT_SPEED`` = 20 m/s (a teleport: a glitch or two takes joined; no body moves so).
"""

from __future__ import annotations

import dataclasses
import math

import roma
import torch

from benchmark.core.plausibility import window_defect
from benchmark.core.rotations import axis_angle_to_matrix, matrix_to_axis_angle

FALLBACK = "sls.fallback_cycles (pose-signal period and principal-component minima)"
PLAN = "benchmark.synthetic.cycles.cycle_windows"


def fallback_cycles(motion, min_s: float = 0.3, max_s: float = 3.0, max_cycles: int | None = None,
                    why: list | None = None) -> list[tuple[float, float]]:
    """One-cycle windows [(t0, t1), ...] (seconds, the motion's own clock) found from the pose
    signal alone (see the module docstring). Empty when the motion is not periodic; then ``why``
    (a list), when given, receives the reason."""
    poses = torch.as_tensor(motion.poses, dtype=torch.float64)
    ts = torch.as_tensor(motion.timestamps, dtype=torch.float64)
    T = poses.shape[0]
    span = float(ts[-1] - ts[0]) if T > 1 else 0.0
    too_short = (f"lasts {span:.2f} s ({T} frames): telling a cycle of at least {min_s:g} s needs two of them "
                 f"and a few frames more")
    if T < 4:
        return _none(why, too_short)
    fps = (T - 1) / span
    x = axis_angle_to_matrix(poses[:, 1:]).reshape(T, -1)
    x = x - x.mean(0)
    var = float(x.square().sum(1).mean())
    if var < 1e-8:
        return _none(why, "no joint moves (one pose throughout): there is no cycle to cut")
    lo = max(1, math.ceil(min_s * fps - 1e-9))
    hi = min(int(math.floor(max_s * fps + 1e-9)), T // 2)
    if hi < lo + 2:
        return _none(why, too_short)
    lags = torch.arange(lo - 1, hi + 2)
    d = torch.stack([(x[int(L):] - x[: T - int(L)]).square().sum(1).mean() for L in lags.clamp_min(1)]) / (2 * var)
    inner = d[1:-1]
    local = (inner <= d[:-2]) & (inner <= d[2:])
    thr = float(inner.min()) + 0.2 * float(inner.max() - inner.min())
    cand = torch.nonzero(local & (inner <= thr)).flatten()
    if cand.numel() == 0 or float(inner[cand[0]]) > 0.5:
        return _none(why, f"its joints do not repeat a movement with a period of {min_s:g}-{hi / fps:.2f} s (not "
                          f"periodic, or slower than half its {span:.2f} s)")
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
    close_max = max(0.1, 3 * float(inner[cand[0]]))
    for a, b in zip(events, events[1:]):
        closes = float((x[b] - x[a]).square().sum()) / (2 * var) <= close_max
        if not (0.85 * L <= b - a <= 1.15 * L and closes):
            continue
        for a, b in _repeats_within(x, var, a, b, close_max):
            if min_s - 1e-9 <= float(ts[b] - ts[a]) <= max_s + 1e-9:
                cycles.append((float(ts[a]), float(ts[b])))
        if max_cycles is not None and len(cycles) >= max_cycles:
            del cycles[max_cycles:]
            break
    if not cycles:
        _none(why, f"its joints repeat with a period of {L / fps:.2f} s, but no stretch of it returns to its "
                   f"starting pose one period later within {min_s:g}-{max_s:g} s")
    return cycles


def _repeats_within(x: torch.Tensor, var: float, a: int, b: int, close_max: float) -> list[tuple[int, int]]:
    """Frames [(a, b)], or the k equal parts of [a, b] when the pose signal ``x`` repeats k = 2 or 3
    times within it: a motion whose period changes (a walk, then a run at a faster cadence) is cut
    at the period of its dominant part, so two strides of the faster part pass as one "cycle" that
    closes. A true cycle does not repeat within itself (over a stride the left and right limbs swap
    at half the period, so x(t + D/2) differs from x(t)); parts shorter than 2 frames are not tried."""
    n = b - a
    for k in (2, 3):
        lag = int(round(n / k))
        if lag < 2:
            break
        d = float((x[a + lag: b + 1] - x[a: b + 1 - lag]).square().sum(1).mean()) / (2 * var)
        if d <= close_max:
            edges = [a + int(round(j * n / k)) for j in range(k + 1)]
            return list(zip(edges, edges[1:]))
    return [(a, b)]


def _none(why: list | None, reason: str) -> list:
    if why is not None:
        why.append(reason)
    return []


def cut_cycles(motions: list, anchors: int, min_s: float, max_s: float, per_motion: int,
               gait_starts=(0.0,), skipped: dict | None = None) -> tuple[list[list], str]:
    """Per motion, up to ``per_motion`` one-cycle Motions of ``anchors`` frames (timestamps 0 .. D,
    the source's world frame, ``meta["cycle"]`` with the cycle's start/end in the source's time and
    its ``cutter``); and the name of the cutter(s) used.

    A motion with the generator's plan in its meta: ``benchmark.synthetic.cycles.cycle_windows`` (the
    generator's phase; cycles start at the phase offsets ``gait_starts``, default the left foot
    strike only, so a motion's cycles never overlap; a seeded (seed 0) subset of ``per_motion`` when
    there are more). Any other motion (or all, when that module cannot be imported):
    :func:`fallback_cycles` (the first ``per_motion`` usable cycles) resampled here. A cycle with a
    :func:`~benchmark.core.plausibility.window_defect` is left out. ``skipped`` (a dict), when given, receives {motion index:
    [reason, ...]} for every cycle left out and every motion without a cycle.
    """
    try:
        from benchmark.synthetic.cycles import cycle_windows, plan_from_meta
    except ImportError:
        cycle_windows = plan_from_meta = None
    skipped = {} if skipped is None else skipped
    planned = [k for k, m in enumerate(motions) if plan_from_meta is not None and _has_plan(m, plan_from_meta)]
    out: list[list] = [[] for _ in motions]
    if planned:
        windows = cycle_windows([motions[k] for k in planned], anchors=anchors, min_s=min_s, max_s=max_s,
                                gait_starts=tuple(gait_starts), max_per_motion=per_motion, seed=0, method="plan")
        for w in windows:
            k = planned[int(w.meta["cycle"]["motion_index"])]
            c = w.meta["cycle"]
            why = window_defect(motions[k], float(c["start"]), float(c["end"]))
            if why is not None:
                skipped.setdefault(k, []).append(f"cycle {float(c['start']):.2f}-{float(c['end']):.2f} s: {why}")
                continue
            out[k].append(dataclasses.replace(w, meta={**w.meta, "cycle": {**c, "motion_index": k}}))
        for k in planned:
            if not out[k] and k not in skipped:
                skipped[k] = [f"the generator's plan has no cycle of {min_s:g}-{max_s:g} s inside its frames"]
    for k, m in enumerate(motions):
        if k in planned:
            continue
        why: list = []
        for t0, t1 in fallback_cycles(m, min_s, max_s, why=why):
            if len(out[k]) >= per_motion:
                break
            defect = window_defect(m, t0, t1)
            if defect is not None:
                skipped.setdefault(k, []).append(f"cycle {t0:.2f}-{t1:.2f} s: {defect}")
                continue
            tau = torch.linspace(0.0, t1 - t0, anchors, dtype=torch.float64)
            w = m.resample(t0 + tau)
            meta = {**dict(m.meta), "cycle": {"start": t0, "end": t1, "kind": "fallback", "motion_index": k,
                                              "source": m.source, "cutter": FALLBACK}}
            out[k].append(dataclasses.replace(w, timestamps=tau, meta=meta))
        if why:
            skipped[k] = why
    n_plan = len(planned)
    if n_plan == len(motions):
        return out, PLAN
    if n_plan == 0:
        return out, FALLBACK
    return out, f"{PLAN} ({n_plan} motions with the generator's plan), {FALLBACK} (the other {len(motions) - n_plan})"


def _has_plan(motion, plan_from_meta) -> bool:
    try:
        plan_from_meta(motion.meta)
    except KeyError:
        return False
    return True


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

