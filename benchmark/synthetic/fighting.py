"""The fighting actions of the synthetic generator: boxing (guard, bounce, combinations of
punches) and kicks (front, side, roundhouse, ...), each with its events drawn per segment. The
conventions (phase, airborne, heading rate) and the registry: :mod:`benchmark.synthetic.actions`.
"""

from __future__ import annotations

import math

import torch

from benchmark.synthetic.action_base import DTYPE, TWO_PI, Action, rng_choice
from benchmark.synthetic.curves import KeyframeCurve, deg, event_weights
from benchmark.synthetic.posing import PoseBuilder


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
                kind = rng_choice(rng, names, p=[0.3, 0.25, 0.15, 0.12, 0.09, 0.09])
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
        twist = torch.zeros(x.n, dtype=DTYPE)
        arms = {k: [deg(torch.full((x.n,), v, dtype=DTYPE)) for v in g] for k, g in _GUARD.items()}
        weights = event_weights(x.time, x.params.get("events", []), _PUNCH_PROFILE)
        dip = torch.zeros(x.n, dtype=DTYPE)
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
            kind = rng_choice(rng, list(_KICKS), p=[0.45, 0.25, 0.3])
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
        z = torch.zeros(n, dtype=DTYPE)
        legs = {s: {"flex": deg(8.0) + z, "abd": st.step_width + deg(5.0) + z, "twist": z.clone(),
                    "knee": deg(16.0) + deg(3.0) * torch.sin(TWO_PI * x.phase), "toe": z.clone()} for s in ("left", "right")}
        root = {"pitch": deg(4.0) + z, "roll": z.clone(), "yaw": z.clone()}
        for ev in x.params.get("events", []):
            u = (x.time - ev["start"]) / ev["duration"]
            inside = ((u > 0) & (u < 1)).to(DTYPE)
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
