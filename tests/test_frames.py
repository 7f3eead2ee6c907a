"""benchmark.core.frames: the heading-frame and traceable 6D helpers the priors share."""

import math

import roma
import torch

from benchmark.core.frames import (
    from_heading_frame,
    ground_origin,
    heading,
    matrix_to_sixd_columns,
    sixd_columns_to_matrix,
    to_heading_frame,
    yaw_matrix,
)
from benchmark.core.rotations import sixd_to_matrix


def test_yaw_matrix_turns_forward_by_the_angle_and_heading_reads_it_back():
    yaw = torch.tensor([0.0, 0.5, -2.0, math.pi / 2], dtype=torch.float64)
    R = yaw_matrix(yaw)
    ez = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(R @ ez, torch.stack([yaw.sin(), torch.zeros_like(yaw), yaw.cos()], -1))
    torch.testing.assert_close(R.transpose(-1, -2) @ R, torch.eye(3, dtype=torch.float64).expand(4, 3, 3))
    torch.testing.assert_close(heading(R), yaw)
    # the heading ignores pitch and roll applied in the body frame (R = R_y(c) R_x(b) R_z(a))
    tilt = roma.euler_to_rotmat("XZ", torch.tensor([[0.3, -0.4]], dtype=torch.float64).expand(4, 2))
    torch.testing.assert_close(heading(R @ tilt), yaw)


def test_heading_frame_round_trip_and_first_frame_faces_plus_z():
    g = torch.Generator().manual_seed(0)
    rot = roma.rotvec_to_rotmat(torch.randn(2, 5, 22, 3, generator=g, dtype=torch.float64))
    trans = torch.randn(2, 5, 3, generator=g, dtype=torch.float64)
    yaw, origin = heading(rot[:, 0, 0]), ground_origin(trans)
    assert torch.equal(origin[:, 1], torch.zeros(2, dtype=torch.float64))
    rot_c, trans_c = to_heading_frame(rot, trans, yaw_matrix(-yaw), origin)
    torch.testing.assert_close(heading(rot_c[:, 0, 0]), torch.zeros(2, dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close(trans_c[:, 0, [0, 2]], torch.zeros(2, 2, dtype=torch.float64), atol=1e-12, rtol=0)
    assert torch.equal(rot_c[:, :, 1:], rot[:, :, 1:])  # local joint rotations untouched
    back_rot, back_trans = from_heading_frame(rot_c, trans_c, yaw_matrix(yaw), origin)
    torch.testing.assert_close(back_rot, rot)
    torch.testing.assert_close(back_trans, trans)


def test_traceable_gram_schmidt_matches_roma_and_inverts_matrix_to_sixd():
    x = torch.randn(4, 7, 6, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    R = sixd_columns_to_matrix(x)
    torch.testing.assert_close(R, sixd_to_matrix(x, "columns"))
    torch.testing.assert_close(sixd_columns_to_matrix(matrix_to_sixd_columns(R)), R)
    assert torch.equal(matrix_to_sixd_columns(R), R[..., :, :2].transpose(-1, -2).flatten(-2))
