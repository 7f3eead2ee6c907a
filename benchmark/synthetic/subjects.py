"""Synthetic subjects: an Anny phenotype (body shape) and a movement style.

The phenotype is the embedded body's shape vector, 6 values in [0, 1] in Anny's order
[gender, age, muscle, weight, height, proportions]. In Anny, gender 0 is male and 1 is female
(its phenotype anchors are ``gender=["male", "female"]`` at 0 and 1, and its shape sampler draws
"boys" for gender <= 0.5); age 2/3 is Anny's "young adult" anchor (0 newborn .. 1 old).

The style sets how a subject moves (cadence, stride, arm swing, posture, ...); the actions read
it (see :mod:`benchmark.synthetic.actions`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

PHENOTYPE_LABELS = ("gender", "age", "muscle", "weight", "height", "proportions")


@dataclass(frozen=True)
class Style:
    """Per-subject movement style. Angles in radians, frequencies in cycles per second."""

    cadence: float = 0.93  # walking stride frequency (one stride = two steps), Hz
    run_cadence: float = 1.42  # running stride frequency, Hz
    stride: float = 1.0  # gain on hip swing amplitudes
    knee: float = 1.0  # gain on knee flexion
    arm_swing: float = 1.0  # gain on arm swing
    lean: float = 0.03  # trunk forward flexion, rad
    step_width: float = 0.02  # hip abduction offset, rad
    elbow: float = 0.2  # resting elbow flexion, rad
    energy: float = 1.0  # gain on punches, kicks, jumps
    tempo: float = 1.0  # speed factor for non-gait actions
    southpaw: bool = False  # boxing stance (mirror image)

    @classmethod
    def sample(cls, rng: np.random.Generator) -> Style:
        return cls(
            cadence=float(rng.uniform(0.86, 1.0)),
            run_cadence=float(rng.uniform(1.32, 1.5)),
            stride=float(rng.uniform(0.85, 1.15)),
            knee=float(rng.uniform(0.9, 1.1)),
            arm_swing=float(rng.uniform(0.6, 1.4)),
            lean=float(rng.uniform(-0.02, 0.09)),
            step_width=float(rng.uniform(0.0, 0.05)),
            elbow=float(rng.uniform(0.1, 0.4)),
            energy=float(rng.uniform(0.85, 1.15)),
            tempo=float(rng.uniform(0.88, 1.12)),
            southpaw=bool(rng.random() < 0.2),
        )


@dataclass(frozen=True)
class Subject:
    """A synthetic person: name, Anny phenotype (6 values in [0, 1]) and movement style."""

    name: str
    phenotype: tuple[float, ...]
    style: Style = field(default_factory=Style)

    def __post_init__(self):
        ph = tuple(float(x) for x in self.phenotype)
        if len(ph) != len(PHENOTYPE_LABELS) or not all(0.0 <= x <= 1.0 and math.isfinite(x) for x in ph):
            raise ValueError(
                f"Subject {self.name!r}: phenotype must be {len(PHENOTYPE_LABELS)} values in [0, 1] "
                f"({', '.join(PHENOTYPE_LABELS)}), got {self.phenotype}"
            )
        object.__setattr__(self, "phenotype", ph)

    @property
    def sex(self) -> str:
        """'male' for gender < 0.5 (Anny's gender 0 is male), else 'female'."""
        return "male" if self.phenotype[0] < 0.5 else "female"

    def to_meta(self) -> dict:
        return {"name": self.name, "sex": self.sex, "phenotype": dict(zip(PHENOTYPE_LABELS, self.phenotype)),
                "style": asdict(self.style)}


# The test subjects mirror the paper's test set (datasets/synthetic.md): 2 male, 2 female, of
# different heights and weights. Standing heights on the embedded Anny body: 1.86 m, 1.70 m,
# 1.69 m, 1.56 m.
TEST_SUBJECTS = (
    Subject("test_m1", (0.0, 0.67, 0.6, 0.5, 0.45, 0.5),
            Style(cadence=0.92, run_cadence=1.38, stride=1.05, arm_swing=1.0, lean=0.04, step_width=0.02,
                  elbow=0.2, energy=1.05, tempo=1.0)),
    Subject("test_m2", (0.1, 0.7, 0.5, 0.7, 0.3, 0.5),
            Style(cadence=0.95, run_cadence=1.45, stride=0.95, arm_swing=0.8, lean=0.06, step_width=0.04,
                  elbow=0.3, energy=0.95, tempo=0.95, southpaw=True)),
    Subject("test_f1", (1.0, 0.65, 0.4, 0.4, 0.42, 0.5),
            Style(cadence=0.97, run_cadence=1.46, stride=1.0, arm_swing=1.2, lean=0.02, step_width=0.01,
                  elbow=0.15, energy=1.0, tempo=1.05)),
    Subject("test_f2", (0.9, 0.7, 0.4, 0.65, 0.3, 0.5),
            Style(cadence=1.0, run_cadence=1.5, stride=0.92, arm_swing=0.9, lean=0.05, step_width=0.03,
                  elbow=0.25, energy=0.9, tempo=1.08)),
)


def sample_subjects(n: int, seed: int, prefix: str) -> list[Subject]:
    """``n`` adult subjects, alternately male and female, phenotypes and styles drawn from ``seed``.

    Heights cover about 1.50-1.95 m on the embedded body; weights, muscle and proportions vary.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7919]))
    out = []
    for i in range(n):
        female = i % 2 == 1
        gender = float(rng.uniform(0.85, 1.0) if female else rng.uniform(0.0, 0.15))
        phenotype = (
            gender,
            float(rng.uniform(0.58, 0.85)),
            float(rng.uniform(0.25, 0.8)),
            float(rng.uniform(0.25, 0.8)),
            float(rng.uniform(0.2, 0.6)),
            float(rng.uniform(0.35, 0.65)),
        )
        out.append(Subject(f"{prefix}_{i:02d}", tuple(round(x, 4) for x in phenotype), Style.sample(rng)))
    return out
