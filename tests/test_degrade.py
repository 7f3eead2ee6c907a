"""Degradation (frames kept, fresh point subsets) and observation fingerprints."""

from __future__ import annotations

import hashlib
import logging
import struct

import pytest
import torch

from benchmark.data.degrade import capture_rate, degrade, fingerprint, temporal_stride
from benchmark.data.observations import Landmarks, NoisyJoints, PointCloudSequence


def labelled_scans(B=2, T=200, N=300, fps=50.0) -> PointCloudSequence:
    """Point (b, t, n) = (b, t, n) as coordinates, so every kept point says where it came from.

    Sequence 1 has 150 real frames (the rest padding); frame (0, 30) has only 50 points.
    """
    b, t, n = torch.meshgrid(torch.arange(B), torch.arange(T), torch.arange(N), indexing="ij")
    points = torch.stack([b, t, n], dim=-1).float()
    lengths = torch.full((B, T), N)
    frame_mask = torch.ones(B, T, dtype=torch.bool)
    if T > 30:
        lengths[0, 30] = 50
        points[0, 30, 50:] = 0
    if B > 1:
        frame_mask[1, 150:] = False
        lengths[1, 150:] = 0
        points[1, 150:] = 0
    timestamps = 1.5 + torch.arange(T, dtype=torch.float64)[None].expand(B, T) / fps
    return PointCloudSequence(points=points, lengths=lengths, timestamps=timestamps, frame_mask=frame_mask)


def test_temporal_keeps_every_kth_frame_from_frame_zero():
    scans = labelled_scans()
    assert abs(capture_rate(scans) - 50.0) < 1e-9
    five = degrade(scans, None, 5.0)
    assert five.points.shape == (2, 20, 300, 3)
    assert torch.equal(five.points[0, :, 0, 1], torch.arange(0, 200, 10).float())  # frames 0, 10, 20, ...
    assert torch.allclose(five.timestamps[0], 1.5 + torch.arange(0, 200, 10, dtype=torch.float64) / 50)
    assert torch.equal(five.frame_mask[1], torch.arange(0, 200, 10) < 150)
    ten = degrade(scans, None, 10.0)
    assert torch.equal(ten.points[0, :, 0, 1], torch.arange(0, 200, 5).float())  # frames 0, 5, 10, ...
    assert torch.equal(degrade(scans, None, 50.0).points, scans.points)


def test_non_integer_ratio_names_both_rates():
    with pytest.raises(ValueError, match=r"50 fps capture to 7 fps.*not an integer.*50, 25, 10, 5, 2, 1 fps"):
        degrade(labelled_scans(), None, 7.0)
    with pytest.raises(ValueError, match="100 fps"):
        temporal_stride(50.0, 100.0)
    assert temporal_stride(50.0, 5.0) == 10


def test_capture_rate_needs_uniform_timestamps_or_an_explicit_rate():
    scans = labelled_scans(B=1, T=20)
    scans.timestamps[0, 10:] += 0.5
    with pytest.raises(ValueError, match="not uniform.*capture_fps"):
        degrade(scans, None, 5.0)
    assert degrade(scans, None, 5.0, capture_fps=50.0).num_frames == 2
    one = labelled_scans(B=1, T=1)
    with pytest.raises(ValueError, match="capture_fps"):
        degrade(one, None, 5.0)


def test_spatial_subsets_are_fresh_distinct_and_from_their_frame():
    scans = labelled_scans()
    out = degrade(scans, 100, None, seed=3)
    assert out.points.shape == (2, 200, 100, 3)
    expected = scans.lengths.clamp(max=100)
    assert torch.equal(out.lengths, expected)
    assert out.lengths[0, 30] == 50, "a frame with fewer points keeps all of them"
    assert torch.equal(out.frame_points(0, 30)[:, 2], torch.arange(50).float())
    subsets = set()
    for b in range(2):
        for t in range(int(out.frame_mask[b].sum())):
            pts = out.frame_points(b, t)
            ids = pts[:, 2].long()
            assert bool((pts[:, 0] == b).all() & (pts[:, 1] == t).all()), "points come from their own frame"
            assert len(set(ids.tolist())) == len(ids), "without replacement"
            assert bool((ids[1:] > ids[:-1]).all()), "kept points stay in their original order"
            assert bool((ids < scans.lengths[b, t]).all()), "never a padding slot"
            subsets.add(tuple(ids.tolist()))
    assert len(subsets) == 350, "a fresh subset every frame"
    assert bool((out.points[1, 150:] == 0).all()) and bool((out.lengths[1, 150:] == 0).all())
    # uniform selection: each point index is kept about 100/300 of the time over the 349 full frames
    full = (scans.lengths == 300) & scans.frame_mask
    counts = torch.zeros(300)
    for b, t in full.nonzero().tolist():
        counts[out.frame_points(b, t)[:, 2].long()] += 1
    p, n = 1 / 3, int(full.sum())
    sd = (n * p * (1 - p)) ** 0.5
    assert ((counts - n * p).abs() < 5 * sd).all()


def test_short_frames_are_logged(caplog):
    with caplog.at_level(logging.WARNING, logger="benchmark.data.degrade"):
        degrade(labelled_scans(), 100, 5.0)  # frame 30 (50 points) is kept at 5 fps
    assert "1 of 35 frames have fewer than 100 points" in caplog.text


def test_degrade_is_deterministic_from_the_seed():
    scans = labelled_scans()
    a = degrade(scans, 100, 10.0, seed=1)
    b = degrade(scans, 100, 10.0, seed=1)
    c = degrade(scans, 100, 10.0, seed=2)
    assert torch.equal(a.points, b.points) and torch.equal(a.lengths, b.lengths)
    assert not torch.equal(a.points, c.points)
    assert fingerprint(a) == fingerprint(b) != fingerprint(c)
    assert degrade(scans, 1000, None).points.shape[2] == 300  # more than there are: keep all
    with pytest.raises(ValueError, match="points_per_frame"):
        degrade(scans, 0, None)


def test_a_seed_per_sequence_draws_each_subset_whatever_the_batch():
    scans = labelled_scans(B=2, T=40)
    both = degrade(scans, 100, 10.0, seed=[5, 6])
    second = PointCloudSequence(points=scans.points[1:], lengths=scans.lengths[1:], timestamps=scans.timestamps[1:],
                                frame_mask=scans.frame_mask[1:])
    alone = degrade(second, 100, 10.0, seed=[6])
    assert torch.equal(both.points[1:], alone.points) and torch.equal(both.lengths[1:], alone.lengths)
    # one seed for the batch: sequence 1 draws after sequence 0, another subset than on its own
    assert not torch.equal(degrade(scans, 100, 10.0, seed=6).points[1:], alone.points)
    with pytest.raises(ValueError, match=r"degrade: `seed` must be an int or a list of 2 ints"):
        degrade(scans, 100, 10.0, seed=[5])


# --------------------------------------------------------------------------- fingerprints
def tiny_scans() -> PointCloudSequence:
    points = torch.tensor([[[[0.0, 0.5, 1.0], [0.25, -1.0, 2.0], [0.0, 0.0, 0.0]],
                            [[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]]])
    return PointCloudSequence(points=points, lengths=torch.tensor([[2, 1]]),
                              timestamps=torch.tensor([[0.0, 0.02]], dtype=torch.float64))


def test_fingerprint_is_stable_and_padding_independent():
    obs = tiny_scans()
    # golden: regenerate only when the fingerprint format changes on purpose
    assert fingerprint(obs) == "f79c457c516ddb9ff817b8b88dab31326b77d9ed6f9d589503fb77998b2989c3"
    # the documented format, written out by hand: class name, then per array |name:shape:dtype| + LE bytes
    parts = [b"PointCloudSequence"]
    for name, shape, fmt, values in [
        ("batch_size", (1,), "<i8", [1]),
        ("frames", (2, 2), "<i8", [0, 0, 0, 1]),
        ("timestamps", (2,), "<f8", [0.0, 0.02]),
        ("lengths", (2,), "<i8", [2, 1]),
        ("points", (3, 3), "<f4", [0.0, 0.5, 1.0, 0.25, -1.0, 2.0, 1.0, 1.0, 1.0]),
    ]:
        parts.append(f"|{name}:{shape}:{fmt}|".encode())
        code = {"<i8": "q", "<f8": "d", "<f4": "f"}[fmt]
        parts.append(struct.pack("<" + code * len(values), *values))
    assert fingerprint(obs) == hashlib.sha256(b"".join(parts)).hexdigest()
    padded = PointCloudSequence(
        points=torch.cat([obs.points, torch.full((1, 2, 4, 3), 7.0)], dim=2).double(),  # junk padding, float64
        lengths=obs.lengths, timestamps=obs.timestamps,
    )
    assert fingerprint(padded) == fingerprint(obs)
    more_frames = PointCloudSequence(
        points=torch.cat([obs.points, torch.ones(1, 1, 3, 3)], dim=1), lengths=torch.tensor([[2, 1, 3]]),
        timestamps=torch.tensor([[0.0, 0.02, 0.04]], dtype=torch.float64),
        frame_mask=torch.tensor([[True, True, False]]),
    )
    assert fingerprint(more_frames) == fingerprint(obs), "padded frames do not count"
    negative_zero = tiny_scans()
    negative_zero.points[0, 0, 0, 0] = -0.0
    assert fingerprint(negative_zero) == fingerprint(obs)


def test_fingerprint_sees_every_change():
    base = fingerprint(tiny_scans())
    point = tiny_scans()
    point.points[0, 1, 0, 2] += 1e-4
    stamp = tiny_scans()
    stamp.timestamps[0, 1] = 0.021
    length = tiny_scans()
    length.lengths[0, 0] = 3
    mask = tiny_scans()
    mask.frame_mask[0, 1] = False
    digests = {base, fingerprint(point), fingerprint(stamp), fingerprint(length), fingerprint(mask)}
    assert len(digests) == 5


def test_fingerprint_of_other_observations():
    ts = torch.zeros(1, 2, dtype=torch.float64)
    lm = Landmarks(positions=torch.zeros(1, 2, 16, 3), timestamps=ts)
    moved = Landmarks(positions=torch.zeros(1, 2, 16, 3), timestamps=ts)
    moved.positions[0, 1, 5, 0] = 0.001
    assert fingerprint(lm) != fingerprint(moved)
    nj = NoisyJoints(rotations=torch.zeros(1, 2, 22, 3), joints=torch.zeros(1, 2, 22, 3),
                     markers=torch.zeros(1, 2, 4, 3), marker_indices=torch.arange(4), trans=torch.zeros(1, 2, 3),
                     shapes=torch.zeros(1, 6), timestamps=ts)
    assert len(fingerprint(nj)) == 64 and fingerprint(nj) != fingerprint(lm)
    with pytest.raises(TypeError, match="not an observation"):
        fingerprint(torch.zeros(3))
