"""Sequence programs: which actions a sequence holds, for how long, with which parameters.

Everything random about a sequence is drawn here, from the sequence's own seed
(``numpy.random.default_rng(SeedSequence([split_seed, index]))``), into a
:class:`~benchmark.synthetic.generator.SequencePlan`; generating motion from a plan is then a
pure function. Two kinds of programs:

- :data:`TEST_PROGRAMS`: the short single-activity sequences of the test split (boxing, kicking,
  sidestepping, kinds of walking and running, one cartwheel), mirroring the paper's test set;
- :func:`random_program`: long sequences of random actions with cross-faded transitions, for
  the training and validation splits (every action appears).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from benchmark.synthetic.actions import ACTIONS, get_action
from benchmark.synthetic.generator import FADE, Segment, SequencePlan
from benchmark.synthetic.subjects import Subject


def sequence_rng(split_seed: int, index: int) -> np.random.Generator:
    """The random generator of sequence ``index`` of a split seeded ``split_seed``."""
    return np.random.default_rng(np.random.SeedSequence([int(split_seed), int(index)]))


def sequence_seed(split_seed: int, index: int) -> int:
    """A 32-bit integer naming sequence ``index`` of a split (recorded in the motion's meta)."""
    return int(np.random.SeedSequence([int(split_seed), int(index)]).generate_state(1)[0])


def build_segments(rng: np.random.Generator, subject: Subject, parts: list[tuple[str, float, dict]]) -> list[Segment]:
    """Segments from (action, duration s, parameter overrides) parts laid end to end.

    Parameters are drawn by each action's ``sample_params`` for the time it is active; a one-shot
    action (the cartwheel) gets the cycle duration that ends it before the next cross-fade.
    """
    segs, t = [], 0.0
    half = FADE / 2
    for i, (name, dur, overrides) in enumerate(parts):
        action = get_action(name)
        start, end = t, t + dur
        anchor = 0.0 if i == 0 else start - half
        active_end = end if i == len(parts) - 1 else end - half
        params = action.sample_params(rng, subject.style, active_end - anchor)
        if action.one_shot:
            params["duration"] = round(active_end - anchor, 6)
        params.update(overrides)
        segs.append(Segment(name, round(start, 6), round(end, 6), params))
        t = end
    return segs


# ---------------------------------------------------------------------------------------- test


def _single(action: str, **overrides) -> Callable:
    def program(rng, subject, duration):
        return [(action, duration, dict(overrides))]

    return program


def _sidestep(rng, subject, duration):
    if rng.random() < 0.4:  # left then right (or the reverse)
        first = bool(rng.random() < 0.5)
        cut = round(float(rng.uniform(0.4, 0.6)) * duration, 3)
        return [("sidestep", cut, {"mirror": first}), ("sidestep", duration - cut, {"mirror": not first})]
    return [("sidestep", duration, {})]


def _lead_in(action: str, p: float = 0.3) -> Callable:
    """The action, preceded with probability p by a short stand."""

    def program(rng, subject, duration):
        if rng.random() < p:
            idle = round(float(rng.uniform(0.6, 1.0)), 3)
            return [("idle", idle, {}), (action, duration - idle, {})]
        return [(action, duration, {})]

    return program


def _switch(first: str, second: str) -> Callable:
    def program(rng, subject, duration):
        cut = round(float(rng.uniform(1.4, 2.4)), 3)
        return [(first, cut, {}), (second, duration - cut, {})]

    return program


def _cartwheel(rng, subject, duration):
    walk = round(float(rng.uniform(0.9, 1.1)), 3)
    cart = round(float(rng.uniform(2.5, 2.7)), 3)  # leaves >= 0.6 s of standing in 4.4 s
    return [("walk", walk, {}), ("cartwheel", cart, {}), ("idle", duration - walk - cart, {})]


TEST_PROGRAMS: dict[str, Callable] = {
    "boxing": _lead_in("boxing"),
    "kicking": _lead_in("kick"),
    "sidestep": _sidestep,
    "walk": _lead_in("walk", 0.2),
    "walk_backward": _single("walk_backward"),
    "walk_curved": _single("walk_curved"),
    "jog": _single("jog"),
    "run": _single("run"),
    "walk_to_run": _switch("walk", "run"),
    "run_to_walk": _switch("run", "walk"),
    "cartwheel": _cartwheel,
}

# The paper's test set: 170 sequences of 4 subjects: boxing, kicking, sidestepping, several kinds
# of walking and running, one cartwheel.
TEST_COMPOSITION: dict[str, int] = {
    "boxing": 24, "kicking": 20, "sidestep": 20, "walk": 18, "walk_backward": 12, "walk_curved": 14,
    "jog": 16, "run": 16, "walk_to_run": 14, "run_to_walk": 15, "cartwheel": 1,
}
TEST_DURATION = 4.4  # s: a 4 s window fits with margin


def plan_test_split(subjects: list[Subject], seed: int, duration: float = TEST_DURATION) -> list[SequencePlan]:
    """The test split's plans: TEST_COMPOSITION kinds in a seeded order, subjects in turn."""
    kinds = [k for k, n in TEST_COMPOSITION.items() for _ in range(n)]
    order = np.random.default_rng(np.random.SeedSequence([int(seed), 104729])).permutation(len(kinds))
    plans = []
    for i, j in enumerate(order):
        kind = kinds[int(j)]
        subject = subjects[i % len(subjects)]
        rng = sequence_rng(seed, i)
        parts = TEST_PROGRAMS[kind](rng, subject, duration)
        plans.append(SequencePlan(
            subject=subject, segments=build_segments(rng, subject, parts), seed=sequence_seed(seed, i),
            heading0=float(rng.uniform(-math.pi, math.pi)), phase0=float(rng.uniform(0, 1)), kind=kind,
        ))
    return plans


# ---------------------------------------------------------------------------------------- train


# Segment durations (s) per action in random programs; the cartwheel is one cycle.
SEGMENT_DURATIONS: dict[str, tuple[float, float]] = {
    "idle": (0.8, 2.5), "walk": (2.0, 5.0), "walk_backward": (1.5, 3.5), "walk_curved": (2.0, 5.0),
    "jog": (2.0, 4.0), "run": (2.0, 4.0), "sidestep": (1.8, 4.0), "skip": (2.0, 3.5),
    "jumping_jacks": (2.0, 4.0), "boxing": (3.0, 6.0), "kick": (3.0, 6.0), "turn": (1.2, 2.5),
    "squat": (2.5, 6.0), "jump": (1.7, 3.4), "cartwheel": (2.5, 3.0), "wave": (2.0, 4.0), "reach": (3.0, 5.0),
}
_IN_PLACE = {"boxing", "kick", "squat", "jump", "cartwheel", "wave", "reach", "jumping_jacks"}


def random_program(rng: np.random.Generator, duration: float, first: str | None = None) -> list[tuple[str, float, dict]]:
    """Random actions filling ``duration`` seconds, starting with ``first`` if given. In-place
    actions are preceded by a short stand half of the time when they follow locomotion."""
    names = sorted(ACTIONS)
    parts, t, prev = [], 0.0, None
    while duration - t > 1e-9:
        name = first if (first is not None and not parts) else names[int(rng.integers(len(names)))]
        if name == prev:
            continue
        if parts and name in _IN_PLACE and prev not in _IN_PLACE | {"idle"} and rng.random() < 0.5:
            name_seq = [("idle", float(rng.uniform(0.6, 1.2))), (name, None)]
        else:
            name_seq = [(name, None)]
        for n, d in name_seq:
            lo, hi = SEGMENT_DURATIONS[n]
            d = float(rng.uniform(lo, hi)) if d is None else d
            d = round(min(d, duration - t), 3)
            if d < 1.0:  # too short to stand on its own: lengthen the previous segment
                if parts:
                    pn, pd, po = parts[-1]
                    parts[-1] = (pn, round(pd + (duration - t), 3), po)
                else:
                    parts.append((n, round(duration - t, 3), {}))
                t = duration
                break
            parts.append((n, d, {}))
            t += d
            prev = n
    # a one-shot action that got shortened below its cycle or ended up last is replaced by a stand
    return [(n if not (get_action(n).one_shot and d < SEGMENT_DURATIONS[n][0]) else "idle", d, o) for n, d, o in parts]


def plan_random_split(subjects: list[Subject], seed: int, per_subject: int, duration: tuple[float, float]) -> list[SequencePlan]:
    """Plans of random programs: ``per_subject`` sequences per subject, durations drawn in
    ``duration`` (s); sequence i starts with action i (mod the number of actions), so that every
    action appears for every subject when per_subject >= the number of actions."""
    names = sorted(ACTIONS)
    plans = []
    i = 0
    for s_idx, subject in enumerate(subjects):
        for k in range(per_subject):
            rng = sequence_rng(seed, i)
            dur = round(float(rng.uniform(*duration)), 3)
            first = names[(k + s_idx) % len(names)]
            parts = random_program(rng, dur, first=first)
            plans.append(SequencePlan(
                subject=subject, segments=build_segments(rng, subject, parts), seed=sequence_seed(seed, i),
                heading0=float(rng.uniform(-math.pi, math.pi)), phase0=float(rng.uniform(0, 1)),
                kind="random",
            ))
            i += 1
    return plans
