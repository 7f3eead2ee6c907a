"""Rotation conversions, batched over any leading dimensions (thin, documented wrappers of roma).

Conventions used throughout the harness:

- Rotation matrices act on column vectors: ``x_world = R @ x_local``; shape ``(..., 3, 3)``.
- Axis-angle (rotation vector): ``(..., 3)``, direction = axis, norm = angle in radians.
- Quaternions follow roma's **XYZW** convention (scalar last): ``(..., 4)`` = ``(x, y, z, w)``.
- 6D representations come in two layouts (see :func:`sixd_to_matrix`); the layout is always an
  explicit argument because mixing them up silently produces wrong rotations.
- Euler angles are radians, intrinsic, applied in the order the letters are written:
  ``order="ZYX"`` means ``R = Rz(a0) @ Ry(a1) @ Rx(a2)`` (the BVH channel order
  ``Zrotation Yrotation Xrotation``).
"""

from __future__ import annotations

import roma
import torch

SIXD_LAYOUTS = ("interleaved", "columns")


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """(..., 3) rotation vectors (radians) -> (..., 3, 3) rotation matrices."""
    return roma.rotvec_to_rotmat(axis_angle)


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 3) rotation vectors with angle in [0, pi].

    Uses roma's quaternion-based conversion, which stays accurate near an angle of pi
    (where the naive ``acos((tr R - 1) / 2)`` / skew-part formula loses the axis).
    """
    return roma.rotmat_to_rotvec(R)


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) unit quaternions in roma's XYZW order (scalar last) -> (..., 3, 3)."""
    return roma.unitquat_to_rotmat(q)


def matrix_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions, XYZW order (scalar last)."""
    return roma.rotmat_to_unitquat(R)


def _check_layout(layout: str) -> None:
    if layout not in SIXD_LAYOUTS:
        raise ValueError(
            f"unknown 6D layout {layout!r}; expected one of {SIXD_LAYOUTS}: 'interleaved' "
            "(VPoser / Xu et al.: the 6 numbers are a row-major 3x2 matrix, columns = elements "
            "(0, 2, 4) and (1, 3, 5)) or 'columns' (HM-VAE: [column 0, column 1] concatenated)"
        )


def sixd_to_matrix(x: torch.Tensor, layout: str) -> torch.Tensor:
    """(..., 6) 6D rotations -> (..., 3, 3) rotation matrices by Gram-Schmidt.

    layout:
        "interleaved": VPoser v1/v2 and Xu et al. The 6 numbers are viewed as a 3x2 matrix in
            row-major order, so the first column a1 = x[..., (0, 2, 4)] and the second
            a2 = x[..., (1, 3, 5)].
        "columns": HM-VAE. x = [a1 (3), a2 (3)] concatenated.
    Both then apply ``roma.special_gramschmidt`` to [a1, a2]: b1 = a1/|a1|,
    b2 = normalised part of a2 orthogonal to b1, b3 = b1 x b2; R = [b1 b2 b3] (columns).
    """
    _check_layout(layout)
    if x.shape[-1] != 6:
        raise ValueError(f"6D rotations must end in 6, got shape {tuple(x.shape)}")
    if layout == "interleaved":
        M = x.unflatten(-1, (3, 2))
    else:
        M = x.unflatten(-1, (2, 3)).transpose(-1, -2)
    return roma.special_gramschmidt(M)


def matrix_to_sixd(R: torch.Tensor, layout: str) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 6), the inverse of :func:`sixd_to_matrix`.

    "interleaved": the first two columns as a row-major 3x2 matrix
        (R00, R01, R10, R11, R20, R21); "columns": (R00, R10, R20, R01, R11, R21).
    """
    _check_layout(layout)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must end in (3, 3), got shape {tuple(R.shape)}")
    cols = R[..., :, :2]  # (..., 3, 2)
    if layout == "interleaved":
        return cols.flatten(-2)
    return cols.transpose(-1, -2).flatten(-2)


def geodesic_distance(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3), (..., 3, 3) -> (...) angle of R1^T R2 in radians, in [0, pi]."""
    return roma.rotmat_geodesic_distance(R1, R2)


def slerp_matrices(R0: torch.Tensor, R1: torch.Tensor, w: torch.Tensor | float) -> torch.Tensor:
    """Elementwise spherical interpolation along the shortest arc.

    R0, R1: (..., 3, 3); w: scalar or tensor broadcastable to R0.shape[:-2]; 0 gives R0, 1 gives
    R1. Returns R0 @ exp(w * log(R0^T R1)), shape (...broadcast..., 3, 3). Unlike roma's
    ``rotmat_slerp`` (which takes the outer product of steps and rotations), every rotation
    pair gets its own weight. At an exact half-turn the arc is ambiguous; roma's log picks one.
    """
    w = torch.as_tensor(w, dtype=R0.dtype, device=R0.device)
    rel = R0.transpose(-1, -2) @ R1
    step = roma.rotmat_to_rotvec(rel) * w[..., None]
    return R0 @ roma.rotvec_to_rotmat(step)


def _check_order(order: str) -> str:
    up = order.upper()
    if len(up) != 3 or set(up) - set("XYZ") or up[0] == up[1] or up[1] == up[2]:
        raise ValueError(
            f"Euler order {order!r} must be three letters from X, Y, Z with no two consecutive "
            "letters equal (e.g. 'ZYX', 'XYZ', 'ZXY')"
        )
    return up


def euler_to_matrix(angles: torch.Tensor, order: str = "ZYX") -> torch.Tensor:
    """(..., 3) Euler angles in radians -> (..., 3, 3).

    ``angles[..., k]`` is the rotation about axis ``order[k]``, and the rotations compose in the
    written order: order="ZYX" gives R = Rz(a0) @ Ry(a1) @ Rx(a2), which is what a BVH joint with
    ``CHANNELS 3 Zrotation Yrotation Xrotation`` means (intrinsic rotations, roma's upper case).
    """
    return roma.euler_to_rotmat(_check_order(order), angles)


def matrix_to_euler(R: torch.Tensor, order: str = "ZYX") -> torch.Tensor:
    """(..., 3, 3) -> (..., 3) Euler angles in radians, the inverse of :func:`euler_to_matrix`."""
    return roma.rotmat_to_euler(_check_order(order), R)


def rotation_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(..., 3), (..., 3) directions (any length > 0) -> (..., 3, 3) the minimal rotation R
    with R @ a/|a| = b/|b| (rotation about a x b). For opposite directions the half-turn axis is
    an arbitrary axis perpendicular to a."""
    a = a / a.norm(dim=-1, keepdim=True)
    b = b / b.norm(dim=-1, keepdim=True)
    cross = torch.linalg.cross(a, b, dim=-1)
    sin = cross.norm(dim=-1, keepdim=True)
    cos = (a * b).sum(-1, keepdim=True)
    angle = torch.atan2(sin, cos)
    # Fallback axis for a x b = 0: a x e, with e the basis vector least aligned with a.
    eye = torch.eye(3, dtype=a.dtype, device=a.device)
    e = eye[a.abs().argmin(dim=-1)]
    perp = torch.linalg.cross(a, e, dim=-1)
    perp = perp / perp.norm(dim=-1, keepdim=True)
    axis = torch.where(sin > 1e-9, cross / sin.clamp_min(1e-12), perp)
    return roma.rotvec_to_rotmat(axis * angle)
