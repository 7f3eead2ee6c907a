"""The procedural actions: smooth joint-angle curves of a phase, per action.

Every action maps a phase (cycles) and a time (seconds since its segment began) to local joint
rotations (T, 22, 3, 3) in the SMPL convention, through the anatomical angles of
:mod:`benchmark.synthetic.posing`. Gait actions (``gait = True``) share one phase convention,
the left foot strikes the floor at phase 0 (mod 1), so that a walk can blend into a run or a turn
with the legs in step; the others start their own phase at 0 when their segment fades in.

The curves are Fourier series fitted to keyframes read off published gait curves (walking after
Winter's normative data, running after Novacheck 1998), one-shot keyframe curves (PCHIP) for the
jump, kicks, punches and the cartwheel, and smooth windows for contact schedules. Per-subject
style (cadence, stride, arm swing, lean, ...; see :class:`benchmark.synthetic.subjects.Style`)
scales and offsets them; per-segment parameters (speed, direction, turn rate, the punch and kick
events) are drawn by :meth:`Action.sample_params` from the segment's own random generator.

Besides the pose, an action tells the contact solver when the body is airborne (ballistic
flight: running, skipping, jumping jacks, jumps) and its heading rate (rad/s; curved walking,
turning on the spot). It does not place the root: the contact solver does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from benchmark.synthetic.curves import FourierCurve, KeyframeCurve, bump, deg, smootherstep, window
from benchmark.synthetic.posing import PoseBuilder, mirror_pose

_DTYPE = torch.float64
TWO_PI = 2 * math.pi


@dataclass
class ActionInput:
    """What an action sees: phase (T,) cycles, time (T,) seconds since the segment's start,
    its parameters (JSON-friendly dict) and the subject's style."""

    phase: torch.Tensor
    time: torch.Tensor
    params: dict
    style: object
    rest_joints: torch.Tensor | None = None  # (22, 3) the subject's T-pose joints (default canonical)

    @property
    def joints(self) -> torch.Tensor:
        if self.rest_joints is None:
            from benchmark.synthetic.rest import CANONICAL_JOINTS

            return torch.tensor(CANONICAL_JOINTS, dtype=_DTYPE)
        return self.rest_joints

    @property
    def n(self) -> int:
        return int(self.phase.shape[0])


class Action:
    """Base class. Subclasses set ``name`` (and ``gait`` / ``one_shot``) and implement ``pose``;
    ``airborne`` and ``heading_rate`` default to "never" and "straight ahead"."""

    name = "action"
    gait = False  # shares the global gait phase (left foot strike at phase 0)
    one_shot = False  # one cycle fills the segment (cartwheel); the planner sizes the segment

    def sample_params(self, rng: np.random.Generator, style, duration: float) -> dict:
        return {}

    def frequency(self, params: dict, style) -> float:
        """Cycles per second."""
        return 1.0

    def pose(self, x: ActionInput) -> torch.Tensor:
        raise NotImplementedError

    def airborne(self, x: ActionInput) -> torch.Tensor:
        """(T,) 1.0 where the action wants ballistic flight, else 0.0."""
        return torch.zeros(x.n, dtype=_DTYPE)

    def heading_rate(self, x: ActionInput) -> torch.Tensor:
        """(T,) rad/s, positive turns the facing direction toward the body's left (+x)."""
        return torch.zeros(x.n, dtype=_DTYPE)

    def evaluate(self, x: ActionInput) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(rotations (T, 22, 3, 3), airborne (T,), heading rate (T,)), mirrored if params say so."""
        rot = self.pose(x)
        air = self.airborne(x)
        rate = self.heading_rate(x)
        if x.params.get("mirror", False):
            rot = mirror_pose(rot)
            rate = -rate
        return rot, air, rate


# ---------------------------------------------------------------------------------------- helpers


def _relaxed_arms(pb: PoseBuilder, style, abd=None, swing=0.0) -> None:
    abd = deg(9.0) if abd is None else abd
    for side, sgn in (("left", 1.0), ("right", -1.0)):
        pb.arm(side, flex=sgn * swing, abd=abd, twist=deg(5.0), elbow=style.elbow)


def _rng_choice(rng, options, p=None):
    return options[int(rng.choice(len(options), p=p))]


# ---------------------------------------------------------------------------------------- gaits

# Walking, left leg (degrees), shaped after Winter's normative gait curves and adjusted so that on
# the generator's skeletons the left heel strikes at phase ~0.1 and the swing foot clears ~3 cm.
_WALK_HIP = FourierCurve([(0.0, 28), (0.1, 24), (0.2, 16), (0.3, 8), (0.4, 0), (0.5, -7), (0.58, -10),
                          (0.65, -4), (0.72, 12), (0.8, 25), (0.88, 30), (0.95, 29)], order=5)
_WALK_KNEE = FourierCurve([(0.0, 4), (0.07, 9), (0.15, 11), (0.25, 9), (0.35, 6), (0.45, 7), (0.52, 12),
                           (0.58, 24), (0.64, 42), (0.7, 62), (0.76, 70), (0.82, 62), (0.88, 40), (0.94, 16),
                           (0.99, 5)], order=7)
_WALK_ANKLE = FourierCurve([(0.0, 0), (0.07, -6), (0.15, 1), (0.3, 6), (0.45, 9), (0.54, 8), (0.6, 0),
                            (0.66, -10), (0.72, 0), (0.78, 10), (0.87, 10), (0.95, 4)], order=6)
_WALK_TOE = FourierCurve([(0.0, 3), (0.1, 0), (0.42, 0), (0.5, 8), (0.56, 22), (0.62, 33), (0.68, 25),
                          (0.74, 8), (0.8, 0)], order=6)
_WALK_ABD = FourierCurve([(0.0, 0), (0.15, -3), (0.45, 0), (0.7, 3), (0.9, 1)], order=3)

# Running, left leg, phase 0 = left foot strike, toe-off at 0.37 (degrees), after Novacheck 1998.
_RUN_HIP = FourierCurve([(0.0, 32), (0.1, 22), (0.2, 8), (0.3, -6), (0.37, -12), (0.45, -4), (0.55, 18),
                         (0.65, 40), (0.75, 48), (0.85, 44), (0.93, 36)], order=5)
_RUN_KNEE = FourierCurve([(0.0, 20), (0.08, 34), (0.14, 40), (0.25, 27), (0.36, 16), (0.45, 45), (0.55, 85),
                          (0.62, 100), (0.7, 92), (0.8, 58), (0.9, 28), (0.97, 20)], order=7)
_RUN_ANKLE = FourierCurve([(0.0, 4), (0.12, 20), (0.25, 12), (0.36, -20), (0.45, -14), (0.6, 0), (0.8, 8),
                           (0.95, 6)], order=5)
_RUN_TOE = FourierCurve([(0.0, 0), (0.25, 0), (0.33, 22), (0.41, 8), (0.5, 0)], order=5)

# Skipping (step-hop), left leg: step at 0, hop flight 0.17-0.36, right step at 0.5 (degrees).
_SKIP_HIP = FourierCurve([(0.0, 25), (0.15, 15), (0.2, 10), (0.27, 8), (0.34, 5), (0.45, -5), (0.56, -14),
                          (0.65, 10), (0.75, 50), (0.82, 62), (0.9, 45), (0.97, 28)], order=6)
_SKIP_KNEE = FourierCurve([(0.0, 10), (0.1, 25), (0.18, 15), (0.27, 20), (0.36, 28), (0.45, 15), (0.56, 25),
                           (0.65, 75), (0.75, 100), (0.82, 90), (0.9, 50), (0.97, 15)], order=7)
_SKIP_ANKLE = FourierCurve([(0.0, 2), (0.1, 12), (0.19, -20), (0.27, -10), (0.34, 0), (0.42, 10), (0.55, -22),
                            (0.65, -10), (0.8, 5), (0.95, 2)], order=6)


def _gait_modulation(phase: torch.Tensor, double_support: float) -> torch.Tensor:
    """1 - cos(4 pi (p - c)): mean 1, zero at the two double-support centres c and c + 0.5, so a
    heading change happens while one foot carries the body (no twisting of two planted feet)."""
    return 1.0 - torch.cos(2 * TWO_PI * (phase - double_support))


def _stance_twist(phase: torch.Tensor, contact: float, lift: float, turn_per_cycle: float, centre: float) -> torch.Tensor:
    """Heading turned since this foot's contact (rad), while it is planted, then unwound over the
    swing: the hip twist that keeps a planted foot from pivoting while the body turns.

    The heading rate is ``turn_per_cycle * (1 - cos(4 pi (p - centre)))`` per cycle of phase
    (see :func:`_gait_modulation`), so the heading accrued since ``contact`` has a closed form.
    """
    if turn_per_cycle == 0.0:
        return torch.zeros_like(phase)
    q = torch.remainder(phase - contact, 1.0)
    stance = lift - contact

    def accrued(x):  # heading from contact to contact + x, x in phase units
        S = lambda u: torch.sin(2 * TWO_PI * (u - centre)) / (2 * TWO_PI)  # noqa: E731
        return turn_per_cycle * (x - (S(contact + x) - S(torch.as_tensor(contact, dtype=_DTYPE))))

    total = accrued(torch.as_tensor(stance, dtype=_DTYPE))
    unwind = total * (1 - smootherstep((q - stance) / (1 - stance)))
    return torch.where(q < stance, accrued(q), unwind)


class Walk(Action):
    """Walking forward, backward (the forward gait run backward in time) or along a curve."""

    name = "walk"
    gait = True

    def sample_params(self, rng, style, duration):
        return {"speed": float(rng.uniform(0.85, 1.15)), "direction": "forward", "turn_rate": 0.0}

    def frequency(self, params, style):
        return style.cadence * params.get("speed", 1.0) ** 0.4

    def pose(self, x):
        st, prm = x.style, x.params
        back = prm.get("direction", "forward") == "backward"
        p = -x.phase if back else x.phase
        gain = st.stride * prm.get("speed", 1.0) ** 0.6 * (0.8 if back else 1.0)
        pb = PoseBuilder(x.n)
        turn = prm.get("turn_rate", 0.0)
        per_cycle = 0.0 if back else turn / self.frequency(prm, st)
        for side, off, sgn in (("left", 0.0, -1.0), ("right", 0.5, 1.0)):
            q = p + off
            hip = deg(_WALK_HIP.scaled(gain)(q))
            knee = deg(_WALK_KNEE(q)) * st.knee
            twist = sgn * _stance_twist(q, 0.12, 0.62, per_cycle, 0.12)
            pb.leg(side, flex=hip, abd=deg(_WALK_ABD(q)) + st.step_width, twist=twist, knee=knee,
                   dorsi=deg(_WALK_ANKLE(q)), toe=deg(_WALK_TOE(q)))
        c = torch.cos(TWO_PI * p)
        yaw = deg(-4.0) * c * gain
        roll = deg(-3.0) * torch.sin(TWO_PI * (p + 0.1)) + 0.06 * turn
        pb.root(pitch=deg(3.0), roll=roll, yaw=yaw)
        lean = st.lean + (deg(-3.0) if back else deg(2.0))
        pb.spine(flex=lean, bend=-0.7 * roll, twist=deg(5.0) * c * st.arm_swing - 0.8 * yaw)
        pb.head(flex=-0.4 * lean, twist=0.3 * yaw)
        swing = deg(16.0) * st.arm_swing * gain
        for side, sgn in (("left", 1.0), ("right", -1.0)):
            pb.arm(side, flex=-sgn * swing * c + deg(2.0), abd=deg(8.0), twist=deg(5.0),
                   elbow=st.elbow + deg(10.0) * (1 - sgn * c) / 2)
        return pb.rot

    def heading_rate(self, x):
        rate = x.params.get("turn_rate", 0.0)
        if rate == 0.0:
            return torch.zeros(x.n, dtype=_DTYPE)
        p = -x.phase if x.params.get("direction") == "backward" else x.phase
        return rate * _gait_modulation(p, 0.12)


class WalkBackward(Walk):
    name = "walk_backward"

    def sample_params(self, rng, style, duration):
        return {"speed": float(rng.uniform(0.8, 1.0)), "direction": "backward", "turn_rate": 0.0}


class WalkCurved(Walk):
    name = "walk_curved"

    def sample_params(self, rng, style, duration):
        rate = float(rng.uniform(0.3, 0.7)) * (1 if rng.random() < 0.5 else -1)
        return {"speed": float(rng.uniform(0.85, 1.1)), "direction": "forward", "turn_rate": rate}


class Run(Action):
    """Running (and jogging, a gentler run): stance 37% of the cycle, two flight phases."""

    name = "run"
    gait = True
    _gain = 1.0
    _flight = (0.37, 0.5)

    def sample_params(self, rng, style, duration):
        rate = 0.0
        if rng.random() < 0.25:
            rate = float(rng.uniform(0.25, 0.6)) * (1 if rng.random() < 0.5 else -1)
        return {"speed": float(rng.uniform(0.9, 1.1)), "turn_rate": rate}

    def frequency(self, params, style):
        return style.run_cadence * (0.9 if self._gain < 1 else 1.0) * params.get("speed", 1.0) ** 0.3

    def pose(self, x):
        st, prm = x.style, x.params
        p = x.phase
        gain = self._gain * st.stride * prm.get("speed", 1.0) ** 0.7
        per_cycle = prm.get("turn_rate", 0.0) / self.frequency(prm, st)
        pb = PoseBuilder(x.n)
        for side, off, sgn in (("left", 0.0, -1.0), ("right", 0.5, 1.0)):
            q = p + off
            knee = deg(_RUN_KNEE.scaled(0.75 + 0.25 * gain)(q)) * st.knee
            twist = sgn * _stance_twist(q, 0.0, self._flight[0], per_cycle, 0.18)
            pb.leg(side, flex=deg(_RUN_HIP.scaled(gain)(q)), abd=deg(2.0) + 0.5 * st.step_width, twist=twist,
                   knee=knee, dorsi=deg(_RUN_ANKLE(q)), toe=deg(_RUN_TOE(q)))
        c = torch.cos(TWO_PI * p)
        yaw = deg(-6.0) * c * gain
        turn = prm.get("turn_rate", 0.0)
        roll = deg(-3.0) * torch.sin(TWO_PI * (p + 0.1)) + 0.15 * turn
        pb.root(pitch=deg(6.0), roll=roll, yaw=yaw)
        lean = st.lean + deg(6.0) * gain
        pb.spine(flex=lean, bend=-0.6 * roll, twist=deg(8.0) * c - 0.8 * yaw)
        pb.head(flex=-0.5 * lean, twist=0.3 * yaw)
        swing = deg(32.0) * st.arm_swing * gain
        for side, sgn in (("left", 1.0), ("right", -1.0)):
            pb.arm(side, flex=-sgn * swing * c + deg(8.0), abd=deg(12.0), twist=deg(20.0),
                   elbow=deg(80.0) + deg(12.0) * sgn * c)
        return pb.rot

    def airborne(self, x):
        q = torch.remainder(x.phase, 0.5)  # both half-cycles: left then right stance
        a, b = self._flight
        return ((q >= a) & (q < b)).to(_DTYPE)

    def heading_rate(self, x):
        rate = x.params.get("turn_rate", 0.0)
        if rate == 0.0:
            return torch.zeros(x.n, dtype=_DTYPE)
        return rate * _gait_modulation(x.phase, 0.18)


class Jog(Run):
    name = "jog"
    _gain = 0.72
    _flight = (0.41, 0.5)


class Skip(Action):
    """Skipping: step-hop on each foot, high knee of the swinging leg, large arm swing."""

    name = "skip"
    gait = True

    def sample_params(self, rng, style, duration):
        return {"speed": float(rng.uniform(0.9, 1.1))}

    def frequency(self, params, style):
        return 1.05 * style.tempo * params.get("speed", 1.0) ** 0.3

    def pose(self, x):
        st = x.style
        p = x.phase
        pb = PoseBuilder(x.n)
        for side, off in (("left", 0.0), ("right", 0.5)):
            q = p + off
            pb.leg(side, flex=deg(_SKIP_HIP.scaled(st.stride)(q)), abd=deg(2.0) + st.step_width,
                   knee=deg(_SKIP_KNEE(q)) * st.knee, dorsi=deg(_SKIP_ANKLE(q)))
        c = torch.cos(TWO_PI * (p - 0.32))
        pb.root(pitch=deg(4.0), yaw=deg(-6.0) * torch.cos(TWO_PI * p))
        pb.spine(flex=st.lean + deg(4.0), twist=deg(6.0) * torch.cos(TWO_PI * p))
        swing = deg(45.0) * st.arm_swing
        for side, sgn in (("left", 1.0), ("right", -1.0)):
            pb.arm(side, flex=sgn * swing * c + deg(15.0), abd=deg(12.0), twist=deg(15.0), elbow=deg(60.0))
        return pb.rot

    def airborne(self, x):
        q = torch.remainder(x.phase, 0.5)
        return ((q >= 0.17) & (q < 0.36)).to(_DTYPE)


class Turn(Action):
    """Turning on the spot: stepping in place while the heading turns (during single support)."""

    name = "turn"
    gait = True

    def sample_params(self, rng, style, duration):
        angle = float(rng.choice([0.5, 0.75, 1.0])) * math.pi * (1 if rng.random() < 0.5 else -1)
        return {"turn_rate": angle / max(duration, 0.5)}

    def frequency(self, params, style):
        return style.cadence * 0.95

    def pose(self, x):
        st = x.style
        p = x.phase
        pb = PoseBuilder(x.n)
        for side, off in (("left", 0.0), ("right", 0.5)):
            q = p + off
            lift = bump(q, 0.78, 0.08)
            pb.leg(side, flex=deg(3.0) + deg(28.0) * lift, abd=deg(1.5) + st.step_width, knee=deg(5.0) + deg(50.0) * lift,
                   dorsi=deg(8.0) * lift, level=True)
        _relaxed_arms(pb, st)
        pb.spine(flex=st.lean, twist=0.08 * x.params.get("turn_rate", 0.0))
        pb.head(twist=0.15 * x.params.get("turn_rate", 0.0))
        return pb.rot

    def heading_rate(self, x):
        return x.params.get("turn_rate", 0.0) * _gait_modulation(x.phase, 0.025)


# ---------------------------------------------------------------------------------------- in place


class Idle(Action):
    """Standing: breathing, a slow weight shift, looking around."""

    name = "idle"

    def sample_params(self, rng, style, duration):
        return {"look": float(rng.uniform(-0.4, 0.4)), "phase": float(rng.uniform(0, 1))}

    def frequency(self, params, style):
        return 0.25

    def pose(self, x):
        st = x.style
        p = x.phase + x.params.get("phase", 0.0)
        pb = PoseBuilder(x.n)
        roll = deg(1.5) * torch.sin(TWO_PI * p)
        pb.root(roll=roll)
        for side, sgn in (("left", 1.0), ("right", -1.0)):
            pb.leg(side, abd=st.step_width + deg(2.0) + sgn * roll, knee=deg(3.0), level=True, plant=True)
        pb.spine(flex=st.lean + deg(1.0) * torch.sin(TWO_PI * 3 * p), bend=-roll)
        pb.head(twist=x.params.get("look", 0.0) * torch.sin(TWO_PI * 0.5 * p), flex=deg(3.0))
        _relaxed_arms(pb, st, swing=deg(2.0) * torch.sin(TWO_PI * p))
        return pb.rot


def _spread_profile(p: torch.Tensor, up: tuple[float, float], down: tuple[float, float]) -> torch.Tensor:
    """Periodic 0 -> 1 -> 0 profile: rises over ``up`` (phase interval), falls over ``down``."""
    q = torch.remainder(p, 1.0)
    rise = smootherstep((q - up[0]) / (up[1] - up[0]))
    fall = smootherstep((q - down[0]) / (down[1] - down[0]))
    return rise - fall


class Sidestep(Action):
    """Sidestepping: the legs spread (leading leg steps out) then close (trailing leg follows);
    the hip abduction only changes while one foot is in the air, so neither foot slides."""

    name = "sidestep"

    def sample_params(self, rng, style, duration):
        return {"mirror": bool(rng.random() < 0.5), "width": float(rng.uniform(0.85, 1.15))}

    def frequency(self, params, style):
        return 0.9 * style.tempo

    def pose(self, x):
        st = x.style
        p = x.phase
        pb = PoseBuilder(x.n)
        spread = _spread_profile(p, (0.15, 0.35), (0.65, 0.85))
        A = deg(13.0) * x.params.get("width", 1.0) * st.stride
        pb.root(pitch=deg(4.0))
        for side, start in (("left", 0.06), ("right", 0.56)):
            lift = window(p, start, start + 0.38, 0.09)  # the foot is up while the spread changes
            hip = deg(6.0) + deg(14.0) * lift
            knee = deg(14.0) + deg(30.0) * lift
            pb.leg(side, flex=hip, abd=st.step_width + A * spread, knee=knee, dorsi=deg(-6.0) * lift,
                   level=True, plant=True)
        pb.spine(flex=st.lean + deg(6.0))
        for side in ("left", "right"):
            pb.arm(side, flex=deg(15.0), abd=deg(14.0) + deg(10.0) * spread, twist=deg(20.0), elbow=deg(35.0))
        return pb.rot


# Jumping jacks, one cycle: land together at 0, push off at 0.32, spread in flight, land spread at
# 0.5, push off at 0.82, close in flight. Periodic keyframes (first value = last value).
_JJ_SPREAD = KeyframeCurve([(0, 0), (0.35, 0), (0.48, 1), (0.85, 1), (0.98, 0), (1, 0)])
_JJ_KNEE = KeyframeCurve([(0, 8), (0.08, 22), (0.18, 12), (0.3, 4), (0.4, 10), (0.5, 8), (0.58, 22), (0.68, 12),
                          (0.8, 4), (0.9, 10), (1, 8)])
_JJ_TOES = KeyframeCurve([(0, -10), (0.06, 0), (0.2, 0), (0.3, -28), (0.4, -20), (0.48, -15), (0.5, -10), (0.56, 0),
                          (0.7, 0), (0.8, -28), (0.9, -20), (0.98, -15), (1, -10)])
_JJ_ARMS = KeyframeCurve([(0, 0.08), (0.04, 0), (0.3, 0), (0.52, 1), (0.8, 1), (1, 0.08)])


class JumpingJacks(Action):
    """Jumping jacks: legs spread and close only in flight (so planted feet never slide), arms
    sweep overhead; push-off on the toes before each flight."""

    name = "jumping_jacks"

    def sample_params(self, rng, style, duration):
        return {"speed": float(rng.uniform(0.9, 1.1))}

    def frequency(self, params, style):
        return 1.1 * style.tempo * params.get("speed", 1.0)

    def pose(self, x):
        st = x.style
        p = torch.remainder(x.phase, 1.0)
        spread = _JJ_SPREAD(p)
        knee = deg(_JJ_KNEE(p)) * st.knee
        hip = deg(2.0) + 0.5 * knee
        pb = PoseBuilder(x.n)
        for side in ("left", "right"):
            pb.leg(side, flex=hip, abd=st.step_width + deg(16.0) * spread, knee=knee, dorsi=deg(_JJ_TOES(p)),
                   level=True, plant=True)
        arms = _JJ_ARMS(p)
        for side in ("left", "right"):
            pb.arm(side, flex=deg(4.0), abd=deg(12.0) + deg(150.0) * arms, twist=deg(-10.0) * arms, elbow=deg(12.0))
        pb.spine(flex=st.lean)
        return pb.rot

    def airborne(self, x):
        q = torch.remainder(x.phase, 0.5)
        return (q >= 0.32).to(_DTYPE)


class Squat(Action):
    """Squatting: pelvis tilts, hips and knees flex, heels stay down, arms reach forward."""

    name = "squat"

    def sample_params(self, rng, style, duration):
        return {"depth": float(rng.uniform(0.7, 1.0)), "period": float(rng.uniform(2.2, 3.0))}

    def frequency(self, params, style):
        return style.tempo / params.get("period", 2.5)

    def pose(self, x):
        st = x.style
        d = x.params.get("depth", 1.0)
        s = _spread_profile(x.phase, (0.08, 0.45), (0.55, 0.92)) * d
        r, h, k = deg(25.0) * s, deg(110.0) * s, deg(120.0) * s * st.knee
        pb = PoseBuilder(x.n)
        pb.root(pitch=r)
        for side in ("left", "right"):
            pb.leg(side, flex=h, abd=st.step_width + deg(6.0), knee=k, level=True, plant=True)
        pb.spine(flex=st.lean + deg(15.0) * s)
        pb.head(flex=deg(-20.0) * s)
        for side in ("left", "right"):
            pb.arm(side, flex=deg(120.0) * s, abd=deg(9.0) + deg(4.0) * s, twist=deg(5.0), elbow=st.elbow * (1 - s))
        return pb.rot


# Vertical jump (countermovement), one cycle: stand, crouch, push-off at 0.5, flight to 0.8, land.
_JUMP_PITCH = KeyframeCurve([(0, 0), (0.15, 0), (0.35, 25), (0.45, 12), (0.5, 3), (0.8, 3), (0.88, 15), (1.0, 0)])
_JUMP_HIP = KeyframeCurve([(0, 0), (0.15, 0), (0.35, 80), (0.45, 35), (0.5, 2), (0.6, 20), (0.7, 30), (0.78, 15),
                           (0.88, 60), (1.0, 0)])
_JUMP_KNEE = KeyframeCurve([(0, 3), (0.15, 3), (0.35, 90), (0.45, 45), (0.5, 3), (0.6, 30), (0.7, 50), (0.78, 15),
                            (0.88, 75), (1.0, 3)])
_JUMP_TOES = KeyframeCurve([(0, 0), (0.42, 0), (0.5, -35), (0.55, -30), (0.65, -15), (0.76, -25), (0.8, -5),
                            (0.83, 0), (1.0, 0)])
_JUMP_ARM = KeyframeCurve([(0, 0), (0.15, 0), (0.35, -50), (0.5, 150), (0.65, 140), (0.8, 60), (0.9, 20), (1.0, 0)])


class Jump(Action):
    """Countermovement jump, in place or forward (more lean in the crouch), repeated per cycle."""

    name = "jump"
    _flight = (0.5, 0.8)

    def sample_params(self, rng, style, duration):
        return {"period": float(rng.uniform(1.5, 1.8)), "forward": float(rng.uniform(0.0, 1.0)),
                "height": float(rng.uniform(0.85, 1.15))}

    def frequency(self, params, style):
        return 1.0 / params.get("period", 1.6)

    def pose(self, x):
        st = x.style
        p = torch.remainder(x.phase, 1.0)
        fwd = x.params.get("forward", 0.0)
        e = st.energy
        r = deg(_JUMP_PITCH(p)) * (1 + 0.6 * fwd)
        h = deg(_JUMP_HIP(p)) * e
        k = deg(_JUMP_KNEE(p)) * e
        pb = PoseBuilder(x.n)
        pb.root(pitch=r)
        for side in ("left", "right"):
            pb.leg(side, flex=h, abd=st.step_width + deg(3.0), knee=k, dorsi=deg(_JUMP_TOES(p)), level=True, plant=True)
        pb.spine(flex=st.lean + 0.5 * r)
        pb.head(flex=-0.5 * r)
        for side in ("left", "right"):
            pb.arm(side, flex=deg(_JUMP_ARM(p)) * e, abd=deg(10.0), twist=deg(5.0), elbow=deg(15.0))
        return pb.rot

    def airborne(self, x):
        p = torch.remainder(x.phase, 1.0)
        return ((p >= self._flight[0]) & (p < self._flight[1])).to(_DTYPE)


# ---------------------------------------------------------------------------------------- fighting

# Arm targets (flex, abd, twist, elbow) in degrees, and trunk twist, for an orthodox boxer.
_GUARD = {"lead": (40.0, 15.0, 30.0, 115.0), "rear": (30.0, 20.0, 40.0, 125.0)}
_PUNCHES = {
    "jab": ("lead", (85.0, 10.0, 10.0, 5.0), -8.0, 0.30),
    "cross": ("rear", (88.0, 5.0, 5.0, 5.0), 30.0, 0.38),
    "lead_hook": ("lead", (70.0, 70.0, 80.0, 90.0), -30.0, 0.40),
    "rear_hook": ("rear", (70.0, 70.0, 80.0, 90.0), 35.0, 0.42),
    "lead_uppercut": ("lead", (60.0, 10.0, -20.0, 85.0), -12.0, 0.40),
    "rear_uppercut": ("rear", (60.0, 10.0, -20.0, 85.0), 18.0, 0.42),
}
_PUNCH_PROFILE = KeyframeCurve([(0.0, 0.0), (0.4, 1.0), (0.55, 1.0), (1.0, 0.0)])


def _event_weights(t: torch.Tensor, events: list, profile: KeyframeCurve) -> list[torch.Tensor]:
    """Per event (start, duration, ...): its profile over t (T,), 0 outside [start, start + duration]."""
    out = []
    for ev in events:
        u = (t - ev["start"]) / ev["duration"]
        inside = (u > 0) & (u < 1)
        out.append(torch.where(inside, profile(u.clamp(0, 1)), torch.zeros_like(u)))
    return out


class Boxing(Action):
    """Boxing: guard stance, a light bounce, and combinations of punches (jab, cross, hooks,
    uppercuts) drawn per segment; southpaw boxers are the mirror image."""

    name = "boxing"

    def sample_params(self, rng, style, duration):
        events, t = [], float(rng.uniform(0.2, 0.6))
        last_end = {"lead": -1.0, "rear": -1.0}
        names = list(_PUNCHES)
        while t < duration + 0.5:
            n = int(rng.integers(1, 5))
            for _ in range(n):
                kind = _rng_choice(rng, names, p=[0.3, 0.25, 0.15, 0.12, 0.09, 0.09])
                arm, _, _, dur = _PUNCHES[kind]
                dur = dur / style.tempo
                start = max(t, last_end[arm] + 0.02)
                events.append({"kind": kind, "start": round(start, 4), "duration": round(dur, 4)})
                last_end[arm] = start + dur
                t = start + dur * float(rng.uniform(0.55, 0.8))
            t = max(last_end.values()) + float(rng.uniform(0.5, 1.2))
        return {"mirror": bool(style.southpaw), "events": events, "bounce": float(rng.uniform(1.6, 2.0))}

    def frequency(self, params, style):
        return params.get("bounce", 1.8)

    def pose(self, x):
        st = x.style
        pb = PoseBuilder(x.n)
        bounce = torch.sin(TWO_PI * x.phase)
        twist = torch.zeros(x.n, dtype=_DTYPE)
        arms = {k: [deg(torch.full((x.n,), v, dtype=_DTYPE)) for v in g] for k, g in _GUARD.items()}
        weights = _event_weights(x.time, x.params.get("events", []), _PUNCH_PROFILE)
        dip = torch.zeros(x.n, dtype=_DTYPE)
        for ev, w in zip(x.params.get("events", []), weights):
            arm, target, tw, _ = _PUNCHES[ev["kind"]]
            w = w * st.energy
            for i in range(4):
                arms[arm][i] = arms[arm][i] + w * (deg(target[i]) - deg(_GUARD[arm][i]))
            twist = twist + w * deg(tw)
            if "uppercut" in ev["kind"]:
                dip = dip + w
        r = deg(5.0)
        pb.root(pitch=r, yaw=deg(-25.0))
        k_lead = deg(26.0) + deg(3.0) * bounce * st.knee + deg(8.0) * dip
        pb.leg("left", flex=deg(14.0), abd=st.step_width + deg(5.0), knee=k_lead, level=True, plant=True)
        pb.leg_matching("right", "left", x.joints, flex=deg(-6.0), abd=st.step_width + deg(5.0), twist=deg(-8.0))
        pb.spine(flex=st.lean + deg(8.0), twist=deg(15.0) + twist)
        pb.head(flex=deg(5.0), twist=deg(10.0) - 0.3 * twist)
        for side, arm in (("left", "lead"), ("right", "rear")):
            f, a, tw, e = arms[arm]
            pb.arm(side, flex=f, abd=a, twist=tw, elbow=e)
        return pb.rot


# Kicks: keyframes (degrees, over the kick's duration) added to the stance: hip flex, abd, twist,
# knee, foot pitch, root pitch, roll, yaw; all start and end at 0 so a kick blends in continuously.
_KICKS = {
    "front": {
        "flex": [(0, 0), (0.25, 75), (0.45, 85), (0.6, 80), (0.8, 40), (1, 0)],
        "abd": [(0, 0), (1, 0)],
        "twist": [(0, 0), (1, 0)],
        "knee": [(0, 0), (0.25, 95), (0.45, 5), (0.6, 90), (0.8, 55), (1, 0)],
        "toe": [(0, 0), (0.45, -30), (0.8, -10), (1, 0)],
        "pitch": [(0, 0), (0.45, -10), (1, 0)],
        "roll": [(0, 0), (1, 0)],
        "yaw": [(0, 0), (1, 0)],
    },
    "side": {
        "flex": [(0, 0), (0.25, 60), (0.45, 15), (0.6, 50), (1, 0)],
        "abd": [(0, 0), (0.25, 40), (0.45, 70), (0.6, 50), (0.85, 15), (1, 0)],
        "twist": [(0, 0), (0.45, 20), (1, 0)],
        "knee": [(0, 0), (0.25, 105), (0.45, 0), (0.6, 95), (0.85, 35), (1, 0)],
        "toe": [(0, 0), (0.45, 10), (1, 0)],
        "pitch": [(0, 0), (1, 0)],
        "roll": [(0, 0), (0.45, -25), (1, 0)],
        "yaw": [(0, 0), (1, 0)],
    },
    "roundhouse": {
        "flex": [(0, 0), (0.3, 60), (0.5, 55), (0.7, 55), (1, 0)],
        "abd": [(0, 0), (0.3, 50), (0.5, 60), (0.7, 45), (1, 0)],
        "twist": [(0, 0), (0.5, 40), (1, 0)],
        "knee": [(0, 0), (0.3, 105), (0.5, 10), (0.7, 85), (1, 0)],
        "toe": [(0, 0), (0.5, -30), (1, 0)],
        "pitch": [(0, 0), (1, 0)],
        "roll": [(0, 0), (0.5, -15), (1, 0)],
        "yaw": [(0, 0), (0.5, -35), (1, 0)],
    },
}
_KICK_CURVES = {k: {c: KeyframeCurve(v) for c, v in d.items()} for k, d in _KICKS.items()}


class Kick(Action):
    """Kicking: front, side and roundhouse kicks with either leg from a square fighting stance."""

    name = "kick"

    def sample_params(self, rng, style, duration):
        events, t = [], float(rng.uniform(0.2, 0.6))
        while t < duration + 0.5:
            kind = _rng_choice(rng, list(_KICKS), p=[0.45, 0.25, 0.3])
            dur = float(rng.uniform(0.9, 1.3)) / style.tempo
            events.append({"kind": kind, "start": round(t, 4), "duration": round(dur, 4),
                           "leg": "left" if rng.random() < 0.5 else "right",
                           "height": round(float(rng.uniform(0.75, 1.05)), 4)})
            t += dur + float(rng.uniform(0.35, 0.9))
        return {"events": events}

    def frequency(self, params, style):
        return 1.5

    def pose(self, x):
        st = x.style
        n = x.n
        z = torch.zeros(n, dtype=_DTYPE)
        legs = {s: {"flex": deg(8.0) + z, "abd": st.step_width + deg(5.0) + z, "twist": z.clone(),
                    "knee": deg(16.0) + deg(3.0) * torch.sin(TWO_PI * x.phase), "toe": z.clone()} for s in ("left", "right")}
        root = {"pitch": deg(4.0) + z, "roll": z.clone(), "yaw": z.clone()}
        for ev in x.params.get("events", []):
            u = (x.time - ev["start"]) / ev["duration"]
            inside = ((u > 0) & (u < 1)).to(_DTYPE)
            uc = u.clamp(0, 1)
            cv = _KICK_CURVES[ev["kind"]]
            side = ev["leg"]
            sgn = 1.0 if side == "left" else -1.0
            hgt = ev.get("height", 1.0) * st.energy
            for c in ("flex", "abd", "twist", "knee"):
                gain = hgt if c in ("flex", "abd") else 1.0
                legs[side][c] = legs[side][c] + inside * deg(cv[c](uc)) * gain
            legs[side]["toe"] = legs[side]["toe"] + inside * deg(cv["toe"](uc))
            root["pitch"] = root["pitch"] + inside * deg(cv["pitch"](uc))
            root["roll"] = root["roll"] + inside * deg(cv["roll"](uc)) * sgn
            root["yaw"] = root["yaw"] + inside * deg(cv["yaw"](uc)) * sgn
            other = "right" if side == "left" else "left"
            legs[other]["knee"] = legs[other]["knee"] + inside * deg(6.0) * torch.sin(math.pi * uc)
        pb = PoseBuilder(n)
        r = root["pitch"]
        pb.root(pitch=r, roll=root["roll"], yaw=root["yaw"])
        for side in ("left", "right"):
            L = legs[side]
            pb.leg(side, flex=L["flex"], abd=L["abd"], twist=L["twist"], knee=L["knee"], dorsi=L["toe"], level=True)
        pb.spine(flex=st.lean + deg(6.0), bend=-0.5 * root["roll"], twist=-0.5 * root["yaw"])
        pb.head(twist=-0.4 * root["yaw"], bend=-0.3 * root["roll"])
        for side in ("left", "right"):
            pb.arm(side, flex=deg(45.0), abd=deg(20.0), twist=deg(30.0), elbow=deg(110.0))
        return pb.rot


# ---------------------------------------------------------------------------------------- gestures


class Wave(Action):
    """Waving one raised hand, forearm swinging side to side."""

    name = "wave"

    def sample_params(self, rng, style, duration):
        return {"mirror": bool(rng.random() < 0.5), "rate": float(rng.uniform(1.6, 2.4)),
                "height": float(rng.uniform(0.8, 1.1))}

    def frequency(self, params, style):
        return params.get("rate", 2.0)

    def pose(self, x):
        st = x.style
        pb = PoseBuilder(x.n)
        for side in ("left", "right"):
            pb.leg(side, abd=st.step_width + deg(2.0), knee=deg(3.0), level=True, plant=True)
        osc = torch.sin(TWO_PI * x.phase)
        pb.arm("left", flex=deg(25.0), abd=deg(120.0) * x.params.get("height", 1.0), twist=deg(-80.0),
               elbow=deg(55.0) + deg(25.0) * osc)
        pb.arm("right", abd=deg(9.0), twist=deg(5.0), elbow=st.elbow)
        pb.spine(flex=st.lean, bend=deg(-3.0))
        pb.head(twist=deg(10.0), flex=deg(-3.0))
        return pb.rot


class Reach(Action):
    """Reaching with one arm to targets around the body (forward, up, to the side, low with a
    forward bend), one after another."""

    name = "reach"

    def sample_params(self, rng, style, duration):
        events, t = [], float(rng.uniform(0.1, 0.4))
        while t < duration + 0.5:
            dur = float(rng.uniform(1.3, 2.0)) / style.tempo
            events.append({"start": round(t, 4), "duration": round(dur, 4),
                           "arm": "left" if rng.random() < 0.5 else "right",
                           "flex": round(float(rng.uniform(40, 160)), 2), "abd": round(float(rng.uniform(0, 70)), 2),
                           "bend": round(float(rng.uniform(0, 1)) ** 2, 4)})
            t += dur + float(rng.uniform(0.1, 0.6))
        return {"events": events}

    def frequency(self, params, style):
        return 0.5

    def pose(self, x):
        st = x.style
        n = x.n
        z = torch.zeros(n, dtype=_DTYPE)
        arm = {s: {"flex": z.clone(), "abd": deg(9.0) + z, "elbow": st.elbow + z} for s in ("left", "right")}
        bend = z.clone()
        profile = KeyframeCurve([(0, 0), (0.35, 1), (0.65, 1), (1, 0)])
        for ev, w in zip(x.params.get("events", []), _event_weights(x.time, x.params.get("events", []), profile)):
            a = arm[ev["arm"]]
            a["flex"] = a["flex"] + w * deg(ev["flex"])
            a["abd"] = a["abd"] + w * deg(ev["abd"])
            a["elbow"] = a["elbow"] * (1 - w) + w * deg(8.0)
            bend = bend + w * ev["bend"] * max(0.0, (100.0 - ev["flex"]) / 60.0)
        trunk = deg(35.0) * bend
        r = deg(10.0) * bend
        h = deg(25.0) * bend
        k = deg(30.0) * bend
        pb = PoseBuilder(n)
        pb.root(pitch=r)
        for side in ("left", "right"):
            pb.leg(side, flex=h, abd=st.step_width + deg(3.0), knee=k + deg(3.0), level=True, plant=True)
            pb.arm(side, flex=arm[side]["flex"], abd=arm[side]["abd"], twist=deg(5.0), elbow=arm[side]["elbow"])
        pb.spine(flex=st.lean + trunk)
        return pb.rot


# ---------------------------------------------------------------------------------------- cartwheel

# Cartwheel toward the body's left (+x), as functions of the roll angle u in degrees (0 -> 360):
# support passes left foot -> left hand -> right hand -> right foot.
_CW_LEG_L = KeyframeCurve([(0, 30), (40, 38), (100, 45), (180, 50), (260, 45), (330, 22), (360, 10)])
_CW_LEG_R = KeyframeCurve([(0, 4), (30, 12), (100, 45), (180, 50), (260, 50), (310, 42), (360, 12)])
_CW_ARM_L = KeyframeCurve([(0, 170), (60, 140), (100, 102), (180, 180), (260, 172), (360, 170)])
_CW_ARM_R = KeyframeCurve([(0, 170), (100, 172), (180, 180), (260, 102), (300, 140), (360, 170)])
_CW_ROLL = (0.16, 0.84)  # phase interval of the roll
_CW_PROGRESS = KeyframeCurve([(0, 0), (0.15, 0.088), (0.85, 0.912), (1, 1)])  # near-constant roll rate


class Cartwheel(Action):
    """A cartwheel: preparation (arms up, leading leg out), a full roll about the facing axis
    over hands and feet, recovery (arms down, trailing step). The hands are contact points like
    the feet (the contact solver pins whichever is lowest), so no part goes through the floor."""

    name = "cartwheel"
    one_shot = True

    def sample_params(self, rng, style, duration):
        return {"mirror": bool(rng.random() < 0.5), "duration": float(duration)}

    def frequency(self, params, style):
        return 1.0 / params.get("duration", 2.5)

    def pose(self, x):
        st = x.style
        p = x.phase.clamp(0.0, 1.0)
        roll_s = _CW_PROGRESS((p - _CW_ROLL[0]) / (_CW_ROLL[1] - _CW_ROLL[0]))
        u = 360.0 * roll_s
        prep = smootherstep(p / _CW_ROLL[0])  # arms up
        rec = smootherstep((p - _CW_ROLL[1]) / (1.0 - _CW_ROLL[1]))  # arms down
        lift_in = window(p, 0.0, 0.15, 0.04)  # leading leg lifts and steps out ...
        step_in = smootherstep((p - 0.04) / 0.07)  # ... while it is in the air
        lift_out = window(p, 0.85, 0.99, 0.04)  # trailing leg lifts and steps in ...
        step_out = smootherstep((p - 0.89) / 0.07)
        width = st.step_width + deg(2.0)
        abd_l = torch.where(p < _CW_ROLL[0], width + (deg(30.0) - width) * step_in, deg(_CW_LEG_L(u)))
        abd_l = torch.where(p > _CW_ROLL[1], deg(10.0) + (width - deg(10.0)) * step_out, abd_l)
        abd_r = torch.where(p < _CW_ROLL[0], width + (deg(4.0) - width) * step_in, deg(_CW_LEG_R(u)))
        abd_r = torch.where(p > _CW_ROLL[1], deg(12.0) + (width - deg(12.0)) * step_out, abd_r)
        arm_l = torch.where(p < _CW_ROLL[0], deg(9.0) + (deg(170.0) - deg(9.0)) * prep, deg(_CW_ARM_L(u)))
        arm_l = torch.where(p > _CW_ROLL[1], deg(170.0) + (deg(9.0) - deg(170.0)) * rec, arm_l)
        arm_r = torch.where(p < _CW_ROLL[0], deg(9.0) + (deg(170.0) - deg(9.0)) * prep, deg(_CW_ARM_R(u)))
        arm_r = torch.where(p > _CW_ROLL[1], deg(170.0) + (deg(9.0) - deg(170.0)) * rec, arm_r)
        step_l, step_r = lift_in + lift_out, torch.zeros_like(p)
        pb = PoseBuilder(x.n)
        pb.root(roll=deg(u))
        for side, step, abd in (("left", step_l, abd_l), ("right", step_r, abd_r)):
            flex, knee = deg(12.0) * step, deg(5.0) + deg(35.0) * step
            pb.leg(side, flex=flex, abd=abd, knee=knee, dorsi=deg(3.0) + knee - flex)  # sole parallel to the pelvis
        pb.arm("left", abd=arm_l, twist=deg(0.0), elbow=deg(5.0))
        pb.arm("right", abd=arm_r, twist=deg(0.0), elbow=deg(5.0))
        pb.head(flex=deg(5.0))
        return pb.rot


# ---------------------------------------------------------------------------------------- registry

ACTIONS: dict[str, Action] = {
    a.name: a
    for a in (
        Idle(), Walk(), WalkBackward(), WalkCurved(), Jog(), Run(), Sidestep(), Skip(), JumpingJacks(),
        Boxing(), Kick(), Turn(), Squat(), Jump(), Cartwheel(), Wave(), Reach(),
    )
}


def get_action(name: str) -> Action:
    if name not in ACTIONS:
        import difflib

        close = difflib.get_close_matches(name, ACTIONS, n=3)
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        raise KeyError(f"unknown synthetic action {name!r}{hint}; known: {', '.join(sorted(ACTIONS))}")
    return ACTIONS[name]
