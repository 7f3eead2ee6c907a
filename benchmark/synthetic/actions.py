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

import torch

from benchmark.synthetic.action_base import DTYPE, TWO_PI, Action
from benchmark.synthetic.curves import KeyframeCurve, deg, event_weights, smootherstep, window
from benchmark.synthetic.fighting import Boxing, Kick
from benchmark.synthetic.gaits import Idle, Jog, Run, Skip, Turn, Walk, WalkBackward, WalkCurved
from benchmark.synthetic.posing import PoseBuilder

# The base class lives in benchmark.synthetic.action_base, the gaits in benchmark.synthetic.gaits,
# boxing and kicks in benchmark.synthetic.fighting; this module holds the other actions and the
# registry of all of them (ACTIONS, get_action).
__all__ = ["ACTIONS", "Cartwheel", "Jump", "JumpingJacks", "Reach", "Sidestep", "Squat", "Wave", "get_action"]

# ---------------------------------------------------------------------------------------- other actions


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
        return (q >= 0.32).to(DTYPE)


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
        return ((p >= self._flight[0]) & (p < self._flight[1])).to(DTYPE)


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
        z = torch.zeros(n, dtype=DTYPE)
        arm = {s: {"flex": z.clone(), "abd": deg(9.0) + z, "elbow": st.elbow + z} for s in ("left", "right")}
        bend = z.clone()
        profile = KeyframeCurve([(0, 0), (0.35, 1), (0.65, 1), (1, 0)])
        for ev, w in zip(x.params.get("events", []), event_weights(x.time, x.params.get("events", []), profile)):
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
