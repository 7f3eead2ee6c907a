"""The gait and standing actions (walk, walk backward, curved walk, run, jog, skip, turn on the
spot, idle): Fourier curves fitted to published gait curves, sharing the global gait phase (left
foot strike at phase 0). See :mod:`benchmark.synthetic.actions` for the conventions and registry.
"""

from __future__ import annotations

import math

import torch

from benchmark.synthetic.action_base import DTYPE, TWO_PI, Action, relaxed_arms
from benchmark.synthetic.curves import FourierCurve, bump, deg, smootherstep
from benchmark.synthetic.posing import PoseBuilder


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
        return turn_per_cycle * (x - (S(contact + x) - S(torch.as_tensor(contact, dtype=DTYPE))))

    total = accrued(torch.as_tensor(stance, dtype=DTYPE))
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
            return torch.zeros(x.n, dtype=DTYPE)
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
        return ((q >= a) & (q < b)).to(DTYPE)

    def heading_rate(self, x):
        rate = x.params.get("turn_rate", 0.0)
        if rate == 0.0:
            return torch.zeros(x.n, dtype=DTYPE)
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
        return ((q >= 0.17) & (q < 0.36)).to(DTYPE)


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
        relaxed_arms(pb, st)
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
        relaxed_arms(pb, st, swing=deg(2.0) * torch.sin(TWO_PI * p))
        return pb.rot
