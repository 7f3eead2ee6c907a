import math

import numpy as np
import pytest
import torch

from benchmark.core import rotations as rot

torch.manual_seed(0)


def rodrigues(aa: np.ndarray) -> np.ndarray:
    """Naive reference: R = I + sin(t) K + (1 - cos(t)) K^2, one vector at a time."""
    t = np.linalg.norm(aa)
    if t < 1e-12:
        return np.eye(3)
    k = aa / t
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K


def elementary(axis, a):
    c, s = math.cos(a), math.sin(a)
    return {
        "X": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "Y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "Z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def test_axis_angle_matches_rodrigues_and_round_trips_batched():
    aa = torch.randn(4, 5, 3, dtype=torch.float64)
    R = rot.axis_angle_to_matrix(aa)
    assert R.shape == (4, 5, 3, 3)
    for idx in [(0, 0), (2, 3), (3, 4)]:
        np.testing.assert_allclose(R[idx].numpy(), rodrigues(aa[idx].numpy()), atol=1e-12)
    back = rot.matrix_to_axis_angle(R)
    np.testing.assert_allclose(rot.axis_angle_to_matrix(back).numpy(), R.numpy(), atol=1e-12)


def test_matrix_to_axis_angle_near_pi():
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    axis = axis / axis.norm()
    for angle in [math.pi - 1e-6, math.pi - 1e-3, math.pi]:
        R = torch.from_numpy(rodrigues((axis * angle).numpy()))
        aa = rot.matrix_to_axis_angle(R)
        assert abs(aa.norm().item() - angle) < 1e-6
        # the axis is recovered up to sign (at exactly pi, +axis and -axis are the same rotation)
        assert abs(abs(float(aa @ axis)) - angle) < 1e-6
        np.testing.assert_allclose(rot.axis_angle_to_matrix(aa).numpy(), R.numpy(), atol=1e-9)


def test_quaternion_is_xyzw():
    # 90 deg about z: q = (0, 0, sin 45, cos 45) in XYZW
    R = torch.from_numpy(elementary("Z", math.pi / 2))
    q = rot.matrix_to_quaternion(R)
    q = q * torch.sign(q[3])
    np.testing.assert_allclose(q.numpy(), [0, 0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(rot.quaternion_to_matrix(q).numpy(), R.numpy(), atol=1e-12)


def test_sixd_interleaved_is_vposer_layout_by_hand():
    # VPoser: view the 6 numbers as a 3x2 row-major matrix -> column a1 = (0, 2, 4), a2 = (1, 3, 5).
    x = torch.tensor([1.0, 0.0, 0.0, 1.0, 0.0, 0.0], dtype=torch.float64)  # a1 = e_x, a2 = e_y
    np.testing.assert_allclose(rot.sixd_to_matrix(x, "interleaved").numpy(), np.eye(3), atol=1e-12)
    # a1 = (2, 0, 0) -> e_x; a2 = (1, 0, 3) -> orthogonal part e_z; b3 = e_x x e_z = -e_y
    x = torch.tensor([2.0, 1.0, 0.0, 0.0, 0.0, 3.0], dtype=torch.float64)
    expected = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=float)  # columns b1, b2, b3
    np.testing.assert_allclose(rot.sixd_to_matrix(x, "interleaved").numpy(), expected, atol=1e-12)
    R = torch.from_numpy(rodrigues(np.array([0.2, -0.7, 0.4])))
    s = rot.matrix_to_sixd(R, "interleaved")
    np.testing.assert_allclose(s.numpy(), R[:, :2].reshape(-1).numpy(), atol=0)  # R00 R01 R10 R11 R20 R21


def test_sixd_columns_is_hmvae_layout_by_hand():
    # HM-VAE: [col0 (3), col1 (3)]
    x = torch.tensor([2.0, 0.0, 0.0, 1.0, 0.0, 3.0], dtype=torch.float64)
    expected = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=float)
    np.testing.assert_allclose(rot.sixd_to_matrix(x, "columns").numpy(), expected, atol=1e-12)
    R = torch.from_numpy(rodrigues(np.array([0.2, -0.7, 0.4])))
    s = rot.matrix_to_sixd(R, "columns")
    np.testing.assert_allclose(s.numpy(), np.concatenate([R[:, 0].numpy(), R[:, 1].numpy()]), atol=0)
    # the two layouts differ on a generic rotation
    assert not torch.allclose(rot.matrix_to_sixd(R, "interleaved"), s)


@pytest.mark.parametrize("layout", ["interleaved", "columns"])
def test_sixd_round_trip_batched(layout):
    R = rot.axis_angle_to_matrix(torch.randn(3, 7, 3, dtype=torch.float64))
    s = rot.matrix_to_sixd(R, layout)
    assert s.shape == (3, 7, 6)
    np.testing.assert_allclose(rot.sixd_to_matrix(s, layout).numpy(), R.numpy(), atol=1e-12)
    # Gram-Schmidt makes a rotation of a perturbed 6D vector
    Rn = rot.sixd_to_matrix(s + 0.1 * torch.randn_like(s), layout)
    eye = torch.eye(3, dtype=torch.float64).expand_as(Rn)
    np.testing.assert_allclose((Rn.transpose(-1, -2) @ Rn).numpy(), eye.numpy(), atol=1e-12)
    np.testing.assert_allclose(torch.linalg.det(Rn).numpy(), 1.0, atol=1e-12)


def test_sixd_unknown_layout_lists_both():
    with pytest.raises(ValueError, match="interleaved.*columns"):
        rot.sixd_to_matrix(torch.zeros(6), "rows")


def test_geodesic_distance_and_slerp_midpoint():
    R0 = torch.from_numpy(elementary("Z", 0.2))
    R1 = torch.from_numpy(elementary("Z", 1.4))
    assert abs(rot.geodesic_distance(R0, R1).item() - 1.2) < 1e-9
    mid = rot.slerp_matrices(R0, R1, 0.5)
    np.testing.assert_allclose(mid.numpy(), elementary("Z", 0.8), atol=1e-12)
    # elementwise weights, batched
    A = rot.axis_angle_to_matrix(torch.randn(5, 3, dtype=torch.float64) * 0.5)
    B = rot.axis_angle_to_matrix(torch.randn(5, 3, dtype=torch.float64) * 0.5)
    w = torch.linspace(0, 1, 5, dtype=torch.float64)
    S = rot.slerp_matrices(A, B, w)
    np.testing.assert_allclose(S[0].numpy(), A[0].numpy(), atol=1e-12)
    np.testing.assert_allclose(S[-1].numpy(), B[-1].numpy(), atol=1e-12)
    d_total = rot.geodesic_distance(A, B)
    np.testing.assert_allclose(rot.geodesic_distance(A, S).numpy(), (w * d_total).numpy(), atol=1e-7)


@pytest.mark.parametrize("order", ["ZYX", "XYZ", "YXZ", "ZXY"])
def test_euler_composes_in_written_order(order):
    a = torch.tensor([0.3, -1.1, 0.7], dtype=torch.float64)
    expected = elementary(order[0], a[0]) @ elementary(order[1], a[1]) @ elementary(order[2], a[2])
    R = rot.euler_to_matrix(a, order)
    np.testing.assert_allclose(R.numpy(), expected, atol=1e-12)
    np.testing.assert_allclose(rot.matrix_to_euler(R, order).numpy(), a.numpy(), atol=1e-9)
    with pytest.raises(ValueError, match="Euler order"):
        rot.euler_to_matrix(a, "XXZ")


def test_rotation_between():
    a = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]], dtype=torch.float64)
    b = torch.tensor([[math.sin(0.35), -math.cos(0.35), 0.0], [-3.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    R = rot.rotation_between(a, b)
    np.testing.assert_allclose(R[0].numpy(), elementary("Z", 0.35), atol=1e-12)  # minimal: about z
    for i in range(3):
        np.testing.assert_allclose((R[i] @ a[i] / a[i].norm()).numpy(), (b[i] / b[i].norm()).numpy(), atol=1e-12)
    np.testing.assert_allclose(R[2].numpy(), np.eye(3), atol=1e-12)
