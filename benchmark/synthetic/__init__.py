"""The project's own synthetic motion data: a procedural, seeded motion generator and its splits.

- :mod:`~benchmark.synthetic.actions`: the actions (walking, running, boxing, kicking, a cartwheel,
  ...) as smooth joint-angle curves of a phase (the gaits in :mod:`~benchmark.synthetic.gaits`, boxing
  and kicks in :mod:`~benchmark.synthetic.fighting`); :mod:`~benchmark.synthetic.posing` turns
  anatomical angles into SMPL-22 local rotations.
- :mod:`~benchmark.synthetic.generator`: a plan of actions -> a sequence queryable at any
  timestamp (cross-faded transitions) -> :class:`~benchmark.core.motion.Motion`.
- :mod:`~benchmark.synthetic.contact`: the ground-contact solver that stands the body on the floor.
- :mod:`~benchmark.synthetic.rest`: the subject's rest skeleton and foot/hand contact points.
- :mod:`~benchmark.synthetic.subjects`, :mod:`~benchmark.synthetic.plans`,
  :mod:`~benchmark.synthetic.splits`: subjects, sequence programs, the test/train/val splits and
  their cache; :mod:`~benchmark.synthetic.quality`: foot sliding and floor penetration.

See ``datasets/synthetic.md`` for the dataset card.
"""

from benchmark.synthetic.generator import GENERATOR_VERSION, Segment, SequencePlan, SyntheticSequence
from benchmark.synthetic.quality import foot_metrics
from benchmark.synthetic.splits import build_split, generate_split, split_plans

__all__ = [
    "GENERATOR_VERSION", "Segment", "SequencePlan", "SyntheticSequence", "build_split", "generate_split",
    "split_plans", "foot_metrics",
]
