"""Procedural motion sequences, continuous in time: plan -> queryable sequence -> Motion.

A :class:`SequencePlan` lists the actions of one sequence (contiguous :class:`Segment` s with
their parameters), the subject, the seed, the initial heading and gait phase. A
:class:`SyntheticSequence` turns it into motion for a given rest skeleton:

- Local poses at any time come straight from the actions' curves. Around each boundary between
  two segments the local rotations are cross-faded by SLERP over ``fade`` seconds (0.5 s,
  smoothstep weights), and so are the gait frequency, the heading rate and the flight schedule.
- The global gait phase and the heading are integrals of the (blended) frequency and heading
  rate, and the root's horizontal track is integrated by the contact solver
  (:mod:`benchmark.synthetic.contact`); all three are computed once on a fine internal grid
  (240 Hz, padded by 0.6 s on each side so that flights crossing the ends resolve) and
  interpolated at query times. The root height is evaluated directly at the query times.
- :meth:`SyntheticSequence.sample` takes any timestamps in [0, duration] (vectorised);
  :meth:`SyntheticSequence.to_motion` samples a uniform frame rate into a
  :class:`~benchmark.core.motion.Motion`.

Everything is deterministic: the randomness lives in the plan (drawn from the plan's seed by
:mod:`benchmark.synthetic.plans`); a sequence is a pure function of plan and skeleton.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import roma
import torch

from benchmark.body.lbs import forward_kinematics
from benchmark.core.motion import Motion
from benchmark.core.rotations import matrix_to_axis_angle, slerp_matrices
from benchmark.core.skeleton import NUM_JOINTS
from benchmark.synthetic.action_base import ActionInput
from benchmark.synthetic.actions import get_action
from benchmark.synthetic.contact import interp_uniform, solve_root_track
from benchmark.synthetic.curves import smoothstep
from benchmark.synthetic.rest import RestSkeleton
from benchmark.synthetic.subjects import Subject

# Bump when a change to the generator changes its output for the same plan and seed; cached
# splits whose manifest names another version are rebuilt.
GENERATOR_VERSION = "2"

GRID_RATE = 240.0  # Hz, internal integration grid
GRID_PAD = 0.6  # s, grid padding before 0 and after the end
FADE = 0.5  # s, cross-fade between consecutive actions
_DTYPE = torch.float64
_TIME_TOL = 1e-9


@dataclass
class Segment:
    """One action over [start, end) seconds, with its parameters (JSON-friendly)."""

    action: str
    start: float
    end: float
    params: dict = field(default_factory=dict)

    def to_meta(self) -> dict:
        return {"action": self.action, "start": round(self.start, 6), "end": round(self.end, 6), "params": self.params}


@dataclass
class SequencePlan:
    """The actions of one sequence and everything random about it."""

    subject: Subject
    segments: list[Segment]
    seed: int
    heading0: float = 0.0  # rad, initial facing direction (rotation about +y of +z)
    phase0: float = 0.0  # global gait phase at t = 0 (cycles)
    kind: str = ""  # the program that made it (e.g. "walk_to_run"), for bookkeeping
    fade: float = FADE

    def __post_init__(self):
        if not self.segments:
            raise ValueError("SequencePlan: no segments")
        if abs(self.segments[0].start) > _TIME_TOL:
            raise ValueError(f"SequencePlan: the first segment must start at 0 s, got {self.segments[0].start}")
        for a, b in zip(self.segments, self.segments[1:]):
            if abs(a.end - b.start) > _TIME_TOL:
                raise ValueError(f"SequencePlan: segments must be contiguous; {a.action} ends at {a.end}, "
                                 f"{b.action} starts at {b.start}")
        for s in self.segments:
            get_action(s.action)  # raises on an unknown name
            if s.end - s.start < self.fade - _TIME_TOL:
                raise ValueError(
                    f"SequencePlan: segment {s.action} [{s.start}, {s.end}) is shorter than the {self.fade} s "
                    "cross-fade; make it longer"
                )

    @property
    def duration(self) -> float:
        return float(self.segments[-1].end)

    def to_meta(self) -> dict:
        return {
            "kind": self.kind,
            "seed": int(self.seed),
            "heading0": round(float(self.heading0), 9),
            "phase0": round(float(self.phase0), 9),
            "fade": self.fade,
            "actions": [s.to_meta() for s in self.segments],
        }


class SyntheticSequence:
    """A generated sequence, queryable at any timestamp in [0, duration] (see module docstring)."""

    def __init__(self, plan: SequencePlan, skeleton: RestSkeleton, grid_rate: float = GRID_RATE):
        self.plan = plan
        self.skeleton = skeleton
        self.duration = plan.duration
        segs = plan.segments
        self._actions = [get_action(s.action) for s in segs]
        self._bounds = torch.tensor([s.start for s in segs[1:]], dtype=_DTYPE)
        half = plan.fade / 2
        self._anchors = [0.0] + [s.start - half for s in segs[1:]]
        style = plan.subject.style
        self._freq = torch.tensor(
            [a.frequency(s.params, style) if a.gait else style.cadence for a, s in zip(self._actions, segs)],
            dtype=_DTYPE,
        )
        self._local_freq = [a.frequency(s.params, style) for a, s in zip(self._actions, segs)]

        # Internal grid: gait phase, actions, heading, contact points, root track.
        n_pad = int(round(GRID_PAD * grid_rate))
        n_body = int(math.ceil(self.duration * grid_rate - 1e-9))
        dt = self.duration / n_body
        self._grid = (torch.arange(-n_pad, n_body + n_pad + 1, dtype=_DTYPE)) * dt
        ia, ib, w = self._blend_index(self._grid)
        freq = self._freq[ia] * (1 - w) + self._freq[ib] * w
        phase = torch.cat([freq.new_zeros(1), torch.cumulative_trapezoid(freq, self._grid)])
        self._phase = phase - phase[n_pad] + plan.phase0
        rot, air, rate = self._evaluate(self._grid, self._phase, ia, ib, w)
        heading = torch.cat([rate.new_zeros(1), torch.cumulative_trapezoid(rate, self._grid)])
        self._heading = heading - heading[n_pad] + plan.heading0
        rot[:, 0] = _yaw(self._heading) @ rot[:, 0]
        points = self._points(rot)
        self.track = solve_root_track(self._grid, points, air, origin_time=0.0)

    # ------------------------------------------------------------------ internals
    def _blend_index(self, t: torch.Tensor):
        """Per time: the two segments to blend (ia, ib) and the weight of ib (T,)."""
        half = self.plan.fade / 2
        k = torch.searchsorted(self._bounds, t.contiguous(), right=True)  # segment of t
        ia, ib = k.clone(), k.clone()
        w = torch.zeros_like(t)
        if len(self._bounds):
            j = torch.searchsorted(self._bounds, t.contiguous()).clamp(max=len(self._bounds) - 1)
            # nearest boundary: j or j - 1
            jm = (j - 1).clamp(min=0)
            dj = (t - self._bounds[j]).abs()
            djm = (t - self._bounds[jm]).abs()
            near = torch.where(djm < dj, jm, j)
            d = t - self._bounds[near]
            inside = d.abs() < half
            ia = torch.where(inside, near, ia)  # boundary `near` sits between segments near and near + 1
            ib = torch.where(inside, near + 1, ib)
            w = torch.where(inside, smoothstep((d + half) / self.plan.fade), w)
        return ia, ib, w

    def _evaluate(self, t, gait_phase, ia, ib, w):
        """Blended local rotations (T, 22, 3, 3), airborne (T,), heading rate (T,)."""
        T = len(t)
        rot_a = torch.empty(T, NUM_JOINTS, 3, 3, dtype=_DTYPE)
        rot_b = torch.empty(T, NUM_JOINTS, 3, 3, dtype=_DTYPE)
        air_a, air_b = torch.zeros(T, dtype=_DTYPE), torch.zeros(T, dtype=_DTYPE)
        rate_a, rate_b = torch.zeros(T, dtype=_DTYPE), torch.zeros(T, dtype=_DTYPE)
        style = self.plan.subject.style
        for s, (action, seg) in enumerate(zip(self._actions, self.plan.segments)):
            need = (ia == s) | (ib == s)
            if not need.any():
                continue
            ts = t[need]
            local_t = ts - self._anchors[s]
            phase = gait_phase[need] if action.gait else self._local_freq[s] * local_t
            r, a, h = action.evaluate(ActionInput(phase=phase, time=local_t, params=seg.params, style=style,
                                                  rest_joints=self.skeleton.joints))
            for sel, rot, air, rate in ((ia == s, rot_a, air_a, rate_a), (ib == s, rot_b, air_b, rate_b)):
                sub = sel[need]
                rot[sel] = r[sub]
                air[sel] = a[sub]
                rate[sel] = h[sub]
        blend = w > 0
        rot = rot_a
        if blend.any():
            rot = rot_a.clone()
            rot[blend] = slerp_matrices(rot_a[blend], rot_b[blend], w[blend][:, None])
        air = air_a * (1 - w) + air_b * w
        rate = rate_a * (1 - w) + rate_b * w
        return rot, air, rate

    def _points(self, rot: torch.Tensor) -> torch.Tensor:
        g_rot, joints = forward_kinematics(rot, self.skeleton.joints)
        return self.skeleton.posed_points(g_rot, joints)

    # ------------------------------------------------------------------ queries
    def sample(self, timestamps) -> tuple[torch.Tensor, torch.Tensor]:
        """Poses (T, 22, 3) axis-angle (rad) and root translation (T, 3) (m) at timestamps (T,) s.

        Timestamps must lie in [0, duration]; any order, any spacing. float64 tensors.
        """
        t = torch.as_tensor(timestamps, dtype=_DTYPE).flatten()
        if t.numel() == 0:
            raise ValueError("SyntheticSequence.sample: no timestamps given")
        lo, hi = float(t.min()), float(t.max())
        if lo < -_TIME_TOL or hi > self.duration + _TIME_TOL:
            raise ValueError(
                f"SyntheticSequence.sample: timestamps span [{lo}, {hi}] s, outside the sequence "
                f"[0, {self.duration}] s ({self.plan.kind or 'sequence'}, seed {self.plan.seed})"
            )
        rot = self.local_rotations(t)
        g_rot, joints = forward_kinematics(rot, self.skeleton.joints)
        points = self.skeleton.posed_points(g_rot, joints)
        ground = -points[..., 1].amin(dim=-1)
        y = self.track.height(t, ground)
        xz = self.track.horizontal(t)
        trans = torch.stack([xz[:, 0], y, xz[:, 1]], dim=-1)
        return matrix_to_axis_angle(rot), trans

    def local_rotations(self, t: torch.Tensor) -> torch.Tensor:
        """(T, 22, 3, 3) local rotations at times t (T,), root rotation including the heading."""
        phase = interp_uniform(t, self._grid, self._phase)
        heading = interp_uniform(t, self._grid, self._heading)
        ia, ib, w = self._blend_index(t)
        rot, _, _ = self._evaluate(t, phase, ia, ib, w)
        rot[:, 0] = _yaw(heading) @ rot[:, 0]
        return rot

    def frame_times(self, fps: float) -> torch.Tensor:
        """Uniform timestamps k / fps covering [0, duration]."""
        n = int(math.floor(self.duration * fps + 1e-6)) + 1
        return torch.arange(n, dtype=_DTYPE) / fps

    def to_motion(self, fps: float, source: str = "", meta: dict | None = None) -> Motion:
        """The sequence sampled at ``fps`` as a Motion (shape = the subject's phenotype, body "anny")."""
        if not (fps > 0 and math.isfinite(fps)):
            raise ValueError(f"SyntheticSequence.to_motion: fps must be a positive number, got {fps!r}")
        t = self.frame_times(fps)
        poses, trans = self.sample(t)
        info = {
            "generator": "benchmark.synthetic",
            "generator_version": GENERATOR_VERSION,
            "subject": self.plan.subject.name,
            "sex": self.plan.subject.sex,
            "fps": float(fps),
            **self.plan.to_meta(),
            "skeleton": self.skeleton.to_meta(),
        }
        if meta:
            info.update(meta)
        return Motion(
            poses=poses.float(), trans=trans.float(), timestamps=t,
            shape=torch.tensor(self.plan.subject.phenotype, dtype=torch.float32), body="anny",
            source=source or f"synthetic:{self.plan.kind or 'sequence'}:{self.plan.seed}", meta=info,
        )


def _yaw(angle: torch.Tensor) -> torch.Tensor:
    """(T,) heading angles -> (T, 3, 3) rotations about +y."""
    rv = torch.zeros(*angle.shape, 3, dtype=angle.dtype)
    rv[..., 1] = angle
    return roma.rotvec_to_rotmat(rv)


def generate(plan: SequencePlan, skeleton: RestSkeleton) -> SyntheticSequence:
    """The sequence for a plan and a rest skeleton (see :class:`SyntheticSequence`)."""
    return SyntheticSequence(plan, skeleton)
