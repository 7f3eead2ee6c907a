"""The action protocol: what an action sees (:class:`ActionInput`) and the :class:`Action` base
class every procedural action subclasses, plus small helpers the actions share.

See :mod:`benchmark.synthetic.actions` for the conventions (phase, airborne, heading rate) and the
registry of actions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from benchmark.synthetic.curves import deg
from benchmark.synthetic.posing import PoseBuilder, mirror_pose

DTYPE = torch.float64
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

            return torch.tensor(CANONICAL_JOINTS, dtype=DTYPE)
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
        return torch.zeros(x.n, dtype=DTYPE)

    def heading_rate(self, x: ActionInput) -> torch.Tensor:
        """(T,) rad/s, positive turns the facing direction toward the body's left (+x)."""
        return torch.zeros(x.n, dtype=DTYPE)

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


def relaxed_arms(pb: PoseBuilder, style, abd=None, swing=0.0) -> None:
    abd = deg(9.0) if abd is None else abd
    for side, sgn in (("left", 1.0), ("right", -1.0)):
        pb.arm(side, flex=sgn * swing, abd=abd, twist=deg(5.0), elbow=style.elbow)


def rng_choice(rng, options, p=None):
    return options[int(rng.choice(len(options), p=p))]


# ---------------------------------------------------------------------------------------- gaits

# Walking, left leg (degrees), shaped after Winter's normative gait curves and adjusted so that on
