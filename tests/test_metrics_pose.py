"""Pose metrics: hand-computed cases, an independent Procrustes reference, invariances, masks."""

import math

import numpy as np
import pytest
import roma
import torch

from benchmark.metrics import (
    acceleration_error,
    mean_acceleration,
    mpjpe,
    pa_mpjpe,
    procrustes_align,
    reduce_frames,
    v2v,
    valid_frame_counts,
)


def random_joints(seed, b=2, t=5, j=22):
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(b, t, j, 3, generator=gen, dtype=torch.float64) * 0.3


def umeyama_numpy(x, y):
    """Independent reference: similarity (s, R, t) minimising |s R x + t - y|^2, no reflection."""
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    cov = yc.T @ xc / len(x)
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    sign[2, 2] = np.sign(np.linalg.det(u) * np.linalg.det(vt))
    r = u @ sign @ vt
    s = np.trace(np.diag(d) @ sign) / (xc**2).sum(1).mean()
    return s, r, my - s * r @ mx


def random_similarity(seed, batch_shape):
    gen = torch.Generator().manual_seed(seed)
    rot = roma.random_rotmat(batch_shape, dtype=torch.float64)
    scale = 0.5 + torch.rand(batch_shape, generator=gen, dtype=torch.float64) * 1.5
    trans = torch.randn(*batch_shape, 3, generator=gen, dtype=torch.float64) * 2.0
    return rot, scale, trans


def apply_similarity(x, rot, scale, trans):
    return scale[..., None, None] * torch.einsum("...ij,...nj->...ni", rot, x) + trans[..., None, :]


# ----------------------------------------------------------------------------- MPJPE / V2V


def test_mpjpe_hand_cases():
    gt = random_joints(0, b=2, t=3, j=4)
    pred = gt + torch.tensor([0.03, 0.04, 0.0], dtype=torch.float64)  # every joint 5 cm off
    torch.testing.assert_close(mpjpe(pred, gt), torch.full((2,), 0.05, dtype=torch.float64))
    pred = gt.clone()
    pred[..., :2, 1] += 0.1  # half the joints 10 cm off, half exact: mean 5 cm
    torch.testing.assert_close(mpjpe(pred, gt), torch.full((2,), 0.05, dtype=torch.float64))
    assert mpjpe(pred, gt, reduction="mean").item() == pytest.approx(0.05)
    assert mpjpe(pred, gt, reduction="frame").shape == (2, 3)


def test_v2v_hand_case_and_mask():
    gt = torch.zeros(1, 4, 6, 3, dtype=torch.float64)
    pred = gt.clone()
    pred[0, :, :, 2] = torch.tensor([0.01, 0.02, 0.03, 1e3])[:, None]  # frame 3 is garbage, masked out
    mask = torch.tensor([[True, True, True, False]])
    assert v2v(pred, gt, mask).item() == pytest.approx(0.02)
    per_frame = v2v(pred, gt, mask, reduction="frame")
    torch.testing.assert_close(per_frame[0, :3], torch.tensor([0.01, 0.02, 0.03], dtype=torch.float64))
    assert torch.isnan(per_frame[0, 3])


def test_mean_is_frame_weighted_not_mean_of_sequence_means():
    gt = torch.zeros(2, 4, 3, 3, dtype=torch.float64)
    pred = gt.clone()
    pred[0, :, :, 0] = 0.01  # sequence 0: 1 cm, 4 valid frames
    pred[1, :, :, 0] = 0.04  # sequence 1: 4 cm, 1 valid frame
    mask = torch.tensor([[True] * 4, [True, False, False, False]])
    torch.testing.assert_close(mpjpe(pred, gt, mask), torch.tensor([0.01, 0.04], dtype=torch.float64))
    assert mpjpe(pred, gt, mask, reduction="mean").item() == pytest.approx((4 * 0.01 + 0.04) / 5)
    sums = mpjpe(pred, gt, mask, reduction="sum")
    counts = valid_frame_counts(mask, 2, 4)
    torch.testing.assert_close(sums / counts, mpjpe(pred, gt, mask))


# ----------------------------------------------------------------------------- PA-MPJPE


def test_procrustes_matches_numpy_umeyama():
    gt = random_joints(1, b=1, t=3)
    pred = random_joints(2, b=1, t=3)
    aligned = procrustes_align(pred, gt)
    for t in range(3):
        s, r, tr = umeyama_numpy(pred[0, t].numpy(), gt[0, t].numpy())
        expected = s * pred[0, t].numpy() @ r.T + tr
        np.testing.assert_allclose(aligned[0, t].numpy(), expected, atol=1e-10)
    per_frame = pa_mpjpe(pred, gt, reduction="frame")
    for t in range(3):
        s, r, tr = umeyama_numpy(pred[0, t].numpy(), gt[0, t].numpy())
        err = np.linalg.norm(s * pred[0, t].numpy() @ r.T + tr - gt[0, t].numpy(), axis=1).mean()
        assert per_frame[0, t].item() == pytest.approx(err, abs=1e-10)


def test_pa_mpjpe_invariant_to_similarity_of_prediction():
    gt = random_joints(3)
    pred = gt + 0.05 * random_joints(4)
    rot, scale, trans = random_similarity(5, (2, 5))  # a different similarity per frame
    moved = apply_similarity(pred, rot, scale, trans)
    base = pa_mpjpe(pred, gt, reduction="frame")
    torch.testing.assert_close(pa_mpjpe(moved, gt, reduction="frame"), base, rtol=1e-9, atol=1e-12)
    assert (mpjpe(moved, gt) > 10 * pa_mpjpe(moved, gt)).all()  # the plain MPJPE does see the transform
    # A similarity of the ground truth itself aligns to zero error.
    torch.testing.assert_close(pa_mpjpe(apply_similarity(gt, rot, scale, trans), gt),
                               torch.zeros(2, dtype=torch.float64), rtol=0, atol=1e-12)
    # PA-MPJPE never exceeds MPJPE (identity is one of the candidate alignments).
    assert (pa_mpjpe(pred, gt, reduction="frame") <= mpjpe(pred, gt, reduction="frame") + 1e-15).all()


def test_pa_mpjpe_does_not_align_a_reflection():
    gt = random_joints(6, b=1, t=2)
    mirrored = gt * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    assert (pa_mpjpe(mirrored, gt, reduction="frame") > 0.05).all()


def test_pa_mpjpe_ignores_degenerate_padded_frames():
    gt = random_joints(7, b=2, t=4)
    pred = gt + 0.02 * random_joints(8, b=2, t=4)
    mask = torch.tensor([[True, True, False, False], [True, True, True, True]])
    padded_pred, padded_gt = pred.clone(), gt.clone()
    padded_pred[0, 2:] = 0.0  # all-zero padding: a degenerate Procrustes problem
    padded_gt[0, 2:] = math.nan
    got = pa_mpjpe(padded_pred, padded_gt, mask)
    assert torch.isfinite(got).all()
    expected0 = pa_mpjpe(pred[:1, :2], gt[:1, :2])
    torch.testing.assert_close(got[:1], expected0)


# ----------------------------------------------------------------------------- acceleration


def test_constant_acceleration_trajectory():
    fps = 30.0
    t = torch.arange(12, dtype=torch.float64) / fps
    acc = torch.tensor([0.0, -9.81, 0.0], dtype=torch.float64)
    vel = torch.tensor([1.0, 2.0, -0.5], dtype=torch.float64)
    start = torch.randn(3, 3, dtype=torch.float64)  # 3 joints
    x = start[None, :, :] + t[:, None, None] * vel + 0.5 * t[:, None, None] ** 2 * acc  # (T, J, 3)
    x = x[None]  # (1, T, J, 3)
    assert mean_acceleration(x, fps).item() == pytest.approx(9.81, rel=1e-9)
    assert mean_acceleration(x, fps, reduction="frame").shape == (1, 10)
    # Uniform motion has zero acceleration; the error between the two is the constant 9.81 m/s^2.
    linear = start[None, :, :] + t[:, None, None] * vel
    assert mean_acceleration(linear[None], fps).item() == pytest.approx(0.0, abs=1e-9)
    assert acceleration_error(x, linear[None], fps).item() == pytest.approx(9.81, rel=1e-9)
    assert acceleration_error(x, x, fps).item() == 0.0


def test_acceleration_scales_with_fps_squared():
    x = random_joints(9, b=1, t=6)
    assert mean_acceleration(x, 60).item() == pytest.approx(4 * mean_acceleration(x, 30).item())


def test_acceleration_mask_needs_three_consecutive_frames():
    fps = 10.0
    x = torch.zeros(1, 6, 2, 3, dtype=torch.float64)
    x[0, :, :, 0] = torch.tensor([0.0, 0.0, 0.01, 0.03, 5.0, -7.0])[:, None]  # frames 4, 5: garbage
    mask = torch.tensor([[True, True, True, True, False, False]])
    # valid second differences: centred on frames 1 and 2: 0.01 and 0.01 (m / frame^2) * fps^2 = 1 m/s^2
    assert mean_acceleration(x, fps, mask).item() == pytest.approx(1.0)
    per = mean_acceleration(x, fps, mask, reduction="frame")
    assert torch.isnan(per[0, 2:]).all() and not torch.isnan(per[0, :2]).any()
    assert valid_frame_counts(mask, 1, 6, acceleration=True).tolist() == [2]
    with pytest.raises(ValueError, match="no valid frame"):
        mean_acceleration(x, fps, torch.tensor([[True, True, False, True, True, False]]))


# ----------------------------------------------------------------------------- reductions and errors


def test_reduce_frames():
    values = torch.tensor([[1.0, 2.0, 100.0], [4.0, 5.0, 6.0]])
    valid = torch.tensor([[True, True, False], [True, True, True]])
    torch.testing.assert_close(reduce_frames(values, valid), torch.tensor([1.5, 5.0]))
    assert reduce_frames(values, valid, "mean").item() == pytest.approx(18.0 / 5)
    torch.testing.assert_close(reduce_frames(values, valid, "sum"), torch.tensor([3.0, 15.0]))
    assert torch.isnan(reduce_frames(values, valid, "frame")[0, 2])


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda p, g: mpjpe(p[0], g[0]), r"`pred` must have shape \(B, T, J, 3\)"),
        (lambda p, g: mpjpe(p, g[:, :2]), "same shape"),
        (lambda p, g: mpjpe(p, g, torch.ones(2, 3)), "`mask` must be a \\(B, T\\) bool"),
        (lambda p, g: mpjpe(p, g, torch.ones(2, 4, dtype=torch.bool)), r"`mask` must have shape \(B, T\) = \(2, 3\)"),
        (lambda p, g: mpjpe(p, g, torch.zeros(2, 3, dtype=torch.bool)), "no valid frame"),
        (lambda p, g: mpjpe(p, g, reduction="median"), "`reduction` must be one of"),
        (lambda p, g: v2v(p[..., :2], g[..., :2]), r"`pred` must have shape \(B, T, V, 3\)"),
        (lambda p, g: pa_mpjpe(p[:, :, :2], g[:, :, :2]), "at least 3 joints"),
        (lambda p, g: mean_acceleration(p, 0), "`fps` must be a positive number"),
        (lambda p, g: mean_acceleration(p[:, :2], 30), "T >= 3"),
        (lambda p, g: acceleration_error(p, g, float("nan")), "`fps` must be a positive number"),
        (lambda p, g: mpjpe(p.long(), g.long()), "floating-point"),
    ],
)
def test_errors(call, match):
    pred, gt = random_joints(10, b=2, t=3, j=4), random_joints(11, b=2, t=3, j=4)
    with pytest.raises(ValueError, match=match):
        call(pred, gt)
