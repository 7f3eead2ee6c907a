"""One-motion-cycle windows cut out of motion sequences, 100 anchors each (structured latent, sls).

Marsot et al. (3DV 2022, paper 001 §4.1) model motions "during which the hip performs a cycle",
0.3-3 s long, each resampled to n = 100 anchor frames uniformly spaced in time. They found the
cycles in AMASS by dynamic time warping against two hand-made gait templates (one starting with
each foot). The synthetic generator knows its phases, so no template matching is needed here:

- ``kind="gait"``: gait actions (walk, walk_backward, walk_curved, run, jog, skip, turn) share the
  global gait phase (cycles; the left foot strikes at phase 0 mod 1, the right one at 0.5). The
  phase is recomputed from the plan recorded in the motion's meta exactly as the generator
  integrates it (same 240 Hz grid, same blended frequency; :func:`gait_phase_track`). A cycle is
  one stride, from phase k + o to k + 1 + o for o in ``gait_starts`` (default both feet, as the
  paper's two templates). Every instant of the cycle must belong to gait actions (cross-fades
  between two gaits, e.g. walk -> run, are kept; any part in a non-gait action rejects it).
- ``kind="local"``: other periodic actions (sidestep, jumping jacks, squat, jump, boxing bounce,
  wave, idle, cartwheel) run their own phase ``frequency * (t - anchor)`` from their segment's
  fade-in; a cycle is [k, k + 1) of it and must lie outside the cross-fades of the segment.
- ``kind="event"``: kicks and reaches: one cycle per event (the leg or arm goes out and back),
  outside the cross-fades.
- ``kind="detected"`` (fallback, motions without a usable plan in ``meta``, e.g. real data):
  stride cycles between upward zero crossings of (left hip flexion - right hip flexion), with a
  minimum peak-to-peak amplitude; see :func:`detect_cycles`.

Then cycles shorter than ``min_s`` or longer than ``max_s`` (paper: 0.3 s, 3 s) or not inside
the motion's frames are dropped. :func:`cycle_windows` resamples each cycle to ``anchors`` frames
uniformly in [start, end] (both included; SLERP of the joint rotations, LERP of the translation
between the motion's frames) and returns one :class:`~benchmark.core.motion.Motion` per cycle, in the
world frame of its source (not aligned), timestamps 0 .. duration, with ``meta["cycle"]``.
"""

from __future__ import annotations

import logging
import math
import types
from dataclasses import asdict, dataclass

import numpy as np
import torch

from benchmark.core.interpolate import resample_intervals
from benchmark.core.motion import Motion
from benchmark.core.rotations import axis_angle_to_matrix, matrix_to_axis_angle

log = logging.getLogger(__name__)

MIN_CYCLE_S = 0.3  # paper §4.1: segments shorter than 0.3 s or longer than 3 s are pruned
MAX_CYCLE_S = 3.0
ANCHORS = 100  # paper Supp. §2: 100 anchor frames per motion
GAIT_STARTS = (0.0, 0.5)  # phase offsets of a stride's start: left foot strike, right foot strike
EVENT_ACTIONS = frozenset({"kick", "reach"})
METHODS = ("auto", "plan", "detect")
DETECT_MIN_AMPLITUDE = 0.15  # rad, peak-to-peak of (left - right hip flexion) within a detected cycle


@dataclass(frozen=True)
class Cycle:
    """One motion cycle [start, end] (seconds, in the source motion's time)."""

    start: float
    end: float
    action: str  # the action performing it ("" when detected)
    kind: str  # "gait", "local", "event" or "detected"
    start_event: str  # "left_strike", "right_strike", "phase+0.25", "phase0", "kick:front", "hip_crossing"
    segment: int = -1  # index of the plan segment (the first one for gait cycles; -1 when detected)

    @property
    def duration(self) -> float:
        return self.end - self.start

    def to_meta(self) -> dict:
        d = asdict(self)
        d["start"], d["end"] = round(self.start, 9), round(self.end, 9)
        return d


# ----------------------------------------------------------------------------------- plans
def plan_from_meta(meta: dict):
    """The :class:`~benchmark.synthetic.generator.SequencePlan` recorded in a synthetic Motion's meta.

    Needs the plan fields written by ``SyntheticSequence.to_motion`` ("actions", "phase0", "fade",
    "seed", "heading0", "kind") and the subject's style in "subject_info" (written by
    ``benchmark.synthetic.splits.generate_split``). Raises KeyError naming the missing field.
    """
    from benchmark.synthetic.generator import GENERATOR_VERSION, Segment, SequencePlan
    from benchmark.synthetic.subjects import PHENOTYPE_LABELS, Style, Subject

    if not isinstance(meta, dict):
        raise KeyError(f"motion meta must be a dict, got {type(meta).__name__}")
    for key in ("actions", "phase0", "subject_info"):
        if key not in meta:
            raise KeyError(
                f"motion meta has no field {key!r}: not a synthetic motion from benchmark.synthetic.splits "
                "(its plan cannot be rebuilt); use method='detect' to find cycles from the hip angles"
            )
    version = meta.get("generator_version")
    if version is not None and str(version) != GENERATOR_VERSION:
        raise KeyError(
            f"motion meta field 'generator_version' is {version!r}, the generator is {GENERATOR_VERSION!r}: the gait "
            "phase cannot be recomputed from the plan; rebuild the split or use method='detect'"
        )
    info = meta["subject_info"]
    try:
        phen = info["phenotype"]
        phenotype = tuple(float(phen[k]) for k in PHENOTYPE_LABELS) if isinstance(phen, dict) else tuple(phen)
        subject = Subject(str(info.get("name", "subject")), phenotype, Style(**info["style"]))
    except (KeyError, TypeError) as exc:
        raise KeyError(f"motion meta field 'subject_info' lacks 'phenotype' or a valid 'style' ({exc})") from exc
    segments = [Segment(a["action"], float(a["start"]), float(a["end"]), dict(a.get("params", {}))) for a in meta["actions"]]
    return SequencePlan(
        subject=subject, segments=segments, seed=int(meta.get("seed", 0)), heading0=float(meta.get("heading0", 0.0)),
        phase0=float(meta["phase0"]), kind=str(meta.get("kind", "")), fade=float(meta.get("fade", 0.5)),
    )


def _blender(plan):
    """A stand-in carrying what ``SyntheticSequence._blend_index`` reads (the plan and its segment
    bounds), so the generator's own blending rule is used without building a sequence."""
    return types.SimpleNamespace(plan=plan, _bounds=torch.tensor([s.start for s in plan.segments[1:]], dtype=torch.float64))


def _blend_index(plan, t: torch.Tensor):
    from benchmark.synthetic.generator import SyntheticSequence

    return SyntheticSequence._blend_index(_blender(plan), torch.as_tensor(t, dtype=torch.float64))


def gait_phase_track(plan, grid_rate: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(grid (G,), global gait phase (G,)) of a plan, as :class:`SyntheticSequence` integrates it.

    The same grid (``GRID_RATE``, padded by ``GRID_PAD``), the same blended per-segment frequency
    (gait actions: their own frequency; other actions: the subject's cadence) and the same
    trapezoidal integral, anchored at ``plan.phase0`` at t = 0. float64.
    """
    from benchmark.synthetic.actions import get_action
    from benchmark.synthetic.generator import GRID_PAD, GRID_RATE

    rate = GRID_RATE if grid_rate is None else float(grid_rate)
    style = plan.subject.style
    actions = [get_action(s.action) for s in plan.segments]
    freq_seg = torch.tensor(
        [a.frequency(s.params, style) if a.gait else style.cadence for a, s in zip(actions, plan.segments)],
        dtype=torch.float64,
    )
    n_pad = int(round(GRID_PAD * rate))
    n_body = int(math.ceil(plan.duration * rate - 1e-9))
    dt = plan.duration / n_body
    grid = torch.arange(-n_pad, n_body + n_pad + 1, dtype=torch.float64) * dt
    ia, ib, w = _blend_index(plan, grid)
    freq = freq_seg[ia] * (1 - w) + freq_seg[ib] * w
    phase = torch.cat([freq.new_zeros(1), torch.cumulative_trapezoid(freq, grid)])
    return grid, phase - phase[n_pad] + plan.phase0


def _pure_zone(plan, s: int) -> tuple[float, float]:
    """[start, end] of segment s outside the cross-fades with its neighbours."""
    half = plan.fade / 2
    seg = plan.segments[s]
    lo = seg.start + (half if s > 0 else 0.0)
    hi = seg.end - (half if s < len(plan.segments) - 1 else 0.0)
    return lo, hi


def plan_cycles(plan, *, t_min: float = 0.0, t_max: float | None = None, min_s: float = MIN_CYCLE_S,
                max_s: float = MAX_CYCLE_S, actions=None, gait_starts=GAIT_STARTS) -> list[Cycle]:
    """The cycles of a plan within [t_min, t_max] (default: the whole plan), sorted by start.

    actions: None for every action, else an iterable of action names to keep.
    """
    from benchmark.synthetic.actions import get_action

    t_max = plan.duration if t_max is None else float(t_max)
    keep = None if actions is None else set(actions)
    eps = 1e-9
    out: list[Cycle] = []

    def accept(a: float, b: float) -> bool:
        return a >= t_min - eps and b <= t_max + eps and min_s - eps <= b - a <= max_s + eps

    # gait cycles: the global phase
    is_gait = [get_action(s.action).gait for s in plan.segments]
    if any(is_gait):
        grid, phase = gait_phase_track(plan)
        g, p = grid.numpy(), phase.numpy()
        gait_flags = torch.tensor(is_gait)
        for off in gait_starts:
            k0 = math.floor(float(p[0]) - off) - 1
            k1 = math.ceil(float(p[-1]) - off) + 1
            targets = np.arange(k0, k1 + 1, dtype=np.float64) + off
            targets = targets[(targets >= p[0]) & (targets <= p[-1])]
            times = np.interp(targets, p, g)
            for a, b in zip(times[:-1], times[1:]):
                a, b = float(a), float(b)
                if not accept(a, b):
                    continue
                probe = torch.linspace(a, b, 64, dtype=torch.float64)
                ia, ib, w = _blend_index(plan, probe)
                if not bool((gait_flags[ia] & gait_flags[ib]).all()):
                    continue
                seg = int(ia[0])
                names = {plan.segments[int(i)].action for i in torch.cat([ia, ib[w > 0]]).unique()}
                if keep is not None and not names <= keep:
                    continue
                label = "left_strike" if off == 0.0 else ("right_strike" if off == 0.5 else f"phase+{off:g}")
                out.append(Cycle(a, b, plan.segments[seg].action, "gait", label, seg))

    # non-gait actions: their own phase or their events, outside the cross-fades
    style = plan.subject.style
    half = plan.fade / 2
    for s, seg in enumerate(plan.segments):
        action = get_action(seg.action)
        if action.gait or (keep is not None and seg.action not in keep):
            continue
        lo, hi = _pure_zone(plan, s)
        anchor = 0.0 if s == 0 else seg.start - half
        if seg.action in EVENT_ACTIONS:
            for ev in seg.params.get("events", []):
                a = anchor + float(ev["start"])
                b = a + float(ev["duration"])
                if a >= lo - eps and b <= hi + eps and accept(a, b):
                    out.append(Cycle(a, b, seg.action, "event", f"{seg.action}:{ev.get('kind', ev.get('arm', 'event'))}", s))
            continue
        f = float(action.frequency(seg.params, style))
        if not f > 0:
            continue
        k = math.ceil((lo - anchor) * f - 1e-9)
        while True:
            a, b = anchor + k / f, anchor + (k + 1) / f
            if b > hi + eps:
                break
            if accept(a, b):
                out.append(Cycle(a, b, seg.action, "local", "phase0", s))
            k += 1
    out.sort(key=lambda c: (c.start, c.end))
    return out


# ----------------------------------------------------------------------------------- detection
def hip_flexion(poses: torch.Tensor) -> torch.Tensor:
    """(T, 22, 3) axis-angle -> (T, 2) flexion (rad) of the left and right thigh: the angle of the
    thigh direction R_hip @ (0, -1, 0) in the pelvis' sagittal plane, positive forward (+z)."""
    R = axis_angle_to_matrix(torch.as_tensor(poses, dtype=torch.float64)[:, 1:3])  # (T, 2, 3, 3)
    down = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    v = R @ down
    return torch.atan2(v[..., 2], -v[..., 1])


def detect_cycles(motion: Motion, *, min_s: float = MIN_CYCLE_S, max_s: float = MAX_CYCLE_S,
                  min_amplitude: float = DETECT_MIN_AMPLITUDE) -> list[Cycle]:
    """Stride cycles of any motion from its hip angles (no plan needed).

    s(t) = flexion(left thigh) - flexion(right thigh), centred by its mean; a cycle runs from one
    upward zero crossing of s to the next (linear interpolation between frames: about the moment
    the left leg passes the right on its way forward), and is kept if s spans at least
    ``min_amplitude`` rad peak-to-peak inside it and its duration is in [min_s, max_s].
    """
    if motion.num_frames < 3:
        return []
    flex = hip_flexion(motion.poses)
    s = (flex[:, 0] - flex[:, 1]).numpy()
    s = s - s.mean()
    t = motion.timestamps.numpy()
    up = np.nonzero((s[:-1] < 0) & (s[1:] >= 0))[0]
    times = [float(t[i] + (t[i + 1] - t[i]) * (-s[i]) / (s[i + 1] - s[i])) for i in up]
    out = []
    for a, b in zip(times[:-1], times[1:]):
        inside = (t >= a) & (t <= b)
        if not inside.any() or not (min_s <= b - a <= max_s):
            continue
        if float(s[inside].max() - s[inside].min()) < min_amplitude:
            continue
        out.append(Cycle(a, b, "", "detected", "hip_crossing", -1))
    return out


def find_cycles(motion: Motion, *, min_s: float = MIN_CYCLE_S, max_s: float = MAX_CYCLE_S, actions=None,
                gait_starts=GAIT_STARTS, method: str = "auto") -> list[Cycle]:
    """The cycles of one motion that lie inside its frames (see the module docstring).

    method: "plan" (the plan in ``motion.meta``; raises KeyError if it is missing), "detect" (hip
    angles), or "auto" (the plan when the meta has one, else detection, with a log line).
    """
    if method not in METHODS:
        raise ValueError(f"find_cycles: method must be one of {METHODS}, got {method!r}")
    t0, t1 = float(motion.timestamps[0]), float(motion.timestamps[-1])
    if method in ("plan", "auto"):
        try:
            plan = plan_from_meta(motion.meta)
        except KeyError as exc:
            if method == "plan":
                raise KeyError(f"{motion.source or 'motion'}: {exc.args[0]}") from exc
            log.info("%s: no usable plan in meta (%s); detecting cycles from the hip angles", motion.source or "motion", exc.args[0])
        else:
            return plan_cycles(plan, t_min=t0, t_max=t1, min_s=min_s, max_s=max_s, actions=actions, gait_starts=gait_starts)
    return detect_cycles(motion, min_s=min_s, max_s=max_s)


def cycle_windows(motions, *, anchors: int = ANCHORS, min_s: float = MIN_CYCLE_S, max_s: float = MAX_CYCLE_S,
                  actions=None, gait_starts=GAIT_STARTS, method: str = "auto", max_per_motion: int | None = None,
                  max_cycles: int | None = None, seed: int = 0) -> list[Motion]:
    """One :class:`Motion` of ``anchors`` frames per motion cycle of ``motions`` (list of Motion).

    Each returned motion: poses (anchors, 22, 3), trans (anchors, 3) in its source's world frame,
    timestamps 0 .. duration (uniform), the source's shape and body, source
    ``"<source>#cycle<k>"`` and meta = the source's meta plus ``meta["cycle"]`` = {start, end (s, in
    the source's time), action, kind, start_event, segment, motion_index, source}.
    ``max_per_motion`` / ``max_cycles``: keep a seeded random subset (in order) of that size.
    Selection and order are deterministic for a given input and seed.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 31337]))
    picked: list[tuple[int, Cycle]] = []
    for i, m in enumerate(motions):
        cycles = find_cycles(m, min_s=min_s, max_s=max_s, actions=actions, gait_starts=gait_starts, method=method)
        if max_per_motion is not None and len(cycles) > max_per_motion:
            idx = np.sort(rng.choice(len(cycles), size=max_per_motion, replace=False))
            cycles = [cycles[j] for j in idx]
        picked += [(i, c) for c in cycles]
    if max_cycles is not None and len(picked) > max_cycles:
        idx = np.sort(rng.choice(len(picked), size=max_cycles, replace=False))
        picked = [picked[j] for j in idx]
    out: list[Motion] = []
    by_motion: dict[int, list[Cycle]] = {}
    for i, c in picked:
        by_motion.setdefault(i, []).append(c)
    for i in sorted(by_motion):
        m, cycles = motions[i], by_motion[i]
        rot, trans, rel = resample_intervals(m, [(c.start, c.end) for c in cycles], anchors)
        poses = matrix_to_axis_angle(rot.double()).float()
        for k, c in enumerate(cycles):
            meta = dict(m.meta)
            meta["cycle"] = {**c.to_meta(), "motion_index": i, "source": m.source}
            out.append(Motion(poses=poses[k], trans=trans[k], timestamps=rel[k], shape=m.shape, body=m.body,
                              source=f"{m.source or 'motion'}#cycle{k}", meta=meta))
    return out


__all__ = [
    "ANCHORS", "MIN_CYCLE_S", "MAX_CYCLE_S", "GAIT_STARTS", "EVENT_ACTIONS", "Cycle", "plan_from_meta",
    "gait_phase_track", "plan_cycles", "hip_flexion", "detect_cycles", "find_cycles", "cycle_windows",
]
