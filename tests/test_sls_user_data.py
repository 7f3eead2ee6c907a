"""sls on user motions (``--data``): which cutter a motion gets, what is left out and why. A motion
without the generator's plan is cut by the pose-signal period detector (its periodicity and
pose-closure checks), never the hip crossings of ``detect_cycles``; a cycle across a hole in the
timestamps or a teleport is left out with its reason; a motion without a cycle is named with its
reason. Tiny handmade motions, no body model."""

import copy
import logging
import math

import numpy as np
import pytest
import torch

from benchmark.core.motion import Motion
from benchmark.protocols import sls, sls_cycles
from benchmark.run.catalog import load_table_spec


def walk(seconds=4.0, fps=30.0, freq=1.0, source="walk.npz") -> Motion:
    t = torch.arange(int(round(seconds * fps)), dtype=torch.float64) / fps
    ph = 2 * math.pi * freq * t
    poses = torch.zeros(len(t), 22, 3, dtype=torch.float64)
    poses[:, 1, 0], poses[:, 2, 0] = -0.5 * torch.sin(ph), 0.5 * torch.sin(ph)
    poses[:, 4, 0], poses[:, 5, 0] = 0.4 * (1 + torch.sin(ph + 1)), 0.4 * (1 - torch.sin(ph + 1))
    poses[:, 16, 2], poses[:, 17, 2] = -1.2, 1.2
    trans = torch.stack([0 * t, 0.9 + 0.02 * torch.cos(2 * ph), 1.2 * t], -1)
    return Motion(poses=poses.float(), trans=trans.float(), timestamps=t, source=source)


def noise(seconds=5.0, fps=30.0, source="noise.npz") -> Motion:
    """Independent random joint rotations at every frame: nothing repeats."""
    m = walk(seconds, fps, source=source)
    rng = np.random.default_rng(0)
    poses = torch.as_tensor(rng.normal(0.0, 0.3, tuple(m.poses.shape)), dtype=torch.float32)
    return Motion(poses=poses, trans=m.trans, timestamps=m.timestamps, source=source)


def cut(motions, per_motion=4):
    skipped = {}
    cycles, cutter = sls_cycles.cut_cycles(motions, 100, 0.3, 3.0, per_motion, skipped=skipped)
    return cycles, cutter, skipped


def test_motion_that_does_not_repeat_yields_no_cycle():
    # the hip-crossing detector found a 0.30 s "cycle" at 4.38 s in this noise
    cycles, cutter, skipped = cut([noise()])
    assert cycles == [[]] and cutter.startswith("sls.fallback_cycles")
    assert "do not repeat a movement" in skipped[0][0]


def test_user_motions_are_cut_by_the_period_detector():
    cycles, cutter, skipped = cut([walk()])
    assert cutter.startswith("sls.fallback_cycles") and not skipped
    assert len(cycles[0]) == 3
    for w in cycles[0]:
        c = w.meta["cycle"]
        assert c["kind"] == "fallback" and c["cutter"].startswith("sls.fallback_cycles")
        assert c["end"] - c["start"] == pytest.approx(1.0, abs=0.04)  # the 1 s stride, to a frame


def test_a_faster_stretch_is_cut_into_single_strides_not_pairs():
    """A walk (1 s strides) then a run (0.59 s strides): the period detector finds the walk's 1 s,
    and pairs of run strides (1.18 s) close like a cycle; each such pair is cut into its two strides.
    A motion of one cadence is cut as before (the half-cycle repeat test never fires on a stride,
    whose left and right limbs swap at half the period)."""
    a, b = walk(6.0, freq=1.0), walk(6.0, freq=1.7)
    run = b.poses.clone()
    run[:, 1:3] *= 1.6  # a wider hip swing
    mixed = Motion(poses=torch.cat([a.poses, run]), trans=torch.cat([a.trans, b.trans + a.trans[-1]]),
                   timestamps=torch.cat([a.timestamps, b.timestamps + 6.0]), source="walk_then_run.npz")
    cycles = sls_cycles.fallback_cycles(mixed)
    walks = [t1 - t0 for t0, t1 in cycles if t1 <= 6.0]
    runs = [t1 - t0 for t0, t1 in cycles if t0 >= 6.0]
    assert len(walks) == 5 and all(d == pytest.approx(1.0, abs=0.04) for d in walks)
    assert len(runs) == 6 and all(d == pytest.approx(1 / 1.7, abs=0.04) for d in runs)  # was 3 of 1.17 s
    assert all(t1 <= u0 + 1e-9 for (_, t1), (u0, _) in zip(cycles, cycles[1:]))  # in order, never overlapping
    for freq in (0.5, 1.0, 1.7):  # one cadence: every cycle one stride
        assert {round((t1 - t0) * freq) for t0, t1 in sls_cycles.fallback_cycles(walk(8.0, freq=freq))} == {1}


def test_cycle_across_missing_frames_is_left_out():
    m = walk(seconds=4.0)
    t = m.timestamps.clone()
    t[60:] += 1.0  # a 1 s hole: 30 frames lost at 2 s
    m = Motion(poses=m.poses, trans=m.trans, timestamps=t, source=m.source)
    cycles, _, skipped = cut([m])
    for w in cycles[0]:
        a, b = w.meta["cycle"]["start"], w.meta["cycle"]["end"]
        assert not (a < 2.5 < b), (a, b)  # no cycle spans the hole
        assert b - a == pytest.approx(1.0, abs=0.04)
    assert len(skipped[0]) == 1 and "frames are missing between 1.967 s and 3.000 s" in skipped[0][0]


def test_cycle_with_a_teleport_is_left_out():
    m = walk(seconds=4.0)
    trans = m.trans.clone()
    trans[50:, 0] += 5.0  # the root jumps 5 m in one frame at 1.65 s
    m = Motion(poses=m.poses, trans=trans, timestamps=m.timestamps, source=m.source)
    cycles, _, skipped = cut([m])
    assert cycles[0] and all(not (w.meta["cycle"]["start"] < 1.65 < w.meta["cycle"]["end"]) for w in cycles[0])
    assert "the root moves 5.00 m between 1.633 s and 1.667 s" in skipped[0][0]
    steps = torch.cat([w.trans.diff(dim=0).norm(dim=-1) for w in cycles[0]])
    assert float(steps.max()) < 0.1  # no anchor-to-anchor jump left in a kept cycle


def test_generator_motions_keep_the_plan_cutter():
    from benchmark.synthetic.generator import Segment, SequencePlan, SyntheticSequence
    from benchmark.synthetic.rest import CanonicalSkeletons
    from benchmark.synthetic.subjects import Style, Subject

    subject = Subject("t", (0.0, 0.67, 0.5, 0.5, 0.45, 0.5), Style())
    plan = SequencePlan(subject=subject, seed=1, phase0=0.3, kind="test",
                        segments=[Segment("walk", 0.0, 3.0, {"speed": 1.0, "direction": "forward", "turn_rate": 0.0})])
    seq = SyntheticSequence(plan, CanonicalSkeletons().rest_skeleton(subject.phenotype))
    synthetic = seq.to_motion(50.0, meta={"subject_info": subject.to_meta()})
    cycles, cutter, _ = cut([walk(), synthetic])
    assert "cycle_windows (1 motions with the generator's plan)" in cutter
    assert cycles[1] and all(w.meta["cycle"]["kind"] == "gait" and w.meta["cycle"]["motion_index"] == 1 for w in cycles[1])
    assert cycles[0] and all(w.meta["cycle"]["kind"] == "fallback" for w in cycles[0])
    alone, cutter, _ = cut([synthetic])  # a split of synthetic motions only: as before
    assert cutter == "benchmark.synthetic.cycles.cycle_windows"
    assert [w.meta["cycle"]["start"] for w in alone[0]] == [w.meta["cycle"]["start"] for w in cycles[1]]


def _load(monkeypatch, motions):
    monkeypatch.setattr(sls, "source_motions", lambda data, body: motions)
    return sls.load_motions(copy.deepcopy(load_table_spec("sls")), "/data/mine", None)


def test_each_motion_left_out_is_named_with_its_reason(monkeypatch, caplog):
    still = walk(seconds=3.0, source="still.npz")
    still = Motion(poses=torch.zeros_like(still.poses), trans=still.trans, timestamps=still.timestamps)
    motions = {"walk.npz": walk(), "still.npz": still, "short.npz": walk(seconds=0.4), "noise.npz": noise()}
    with caplog.at_level(logging.WARNING, logger="benchmark.protocols.sls"):
        out = _load(monkeypatch, motions)
    assert sorted(out) == ["walk.npz#c0", "walk.npz#c1", "walk.npz#c2"]
    text = caplog.text
    assert "3 of 4 motions have no usable motion cycle" in text
    assert "still.npz (no joint moves" in text and "short.npz (lasts 0.37 s" in text
    assert "noise.npz (its joints do not repeat" in text
    with pytest.raises(ValueError, match=r"--data /data/mine: sls found no usable motion cycle .*short\.npz \(lasts "
                                         r"0\.37 s .*still\.npz \(no joint moves"):
        _load(monkeypatch, {k: motions[k] for k in ("still.npz", "short.npz")})


def test_user_subjects_of_any_json_kind_are_selected_from(monkeypatch):
    # a user file's meta {"subject": 3} beside one without a subject raised TypeError (str < int),
    # a record {"name": ...} "unhashable type: 'dict'"
    from benchmark.core.work_units import select_sequences

    def motion(subject):
        m = walk(seconds=1.0)
        return Motion(poses=m.poses, trans=m.trans, timestamps=m.timestamps, meta=subject)

    motions = {"a.npz#c0": motion({"subject": 3}), "b.npz#c0": motion({}), "c.npz#c0": motion({"subject": {"name": "x"}}),
               "d.npz#c0": motion({"subject": 3}), "e.npz#c0": motion({"subject": "s1"})}
    assert select_sequences(motions, 4) == ["a.npz#c0", "b.npz#c0", "c.npz#c0", "e.npz#c0"]
    synthetic = {f"m{i}": motion({"subject": s}) for i, s in enumerate(["f1", "f1", "m1", "m2", "m2", "m2"])}
    assert select_sequences(synthetic, 3) == ["m0", "m2", "m3"]  # string subjects: as before
