"""Heading frames and traceable rotation helpers that more than one prior needs.

World convention: y up, a body faces its root's +z axis. The *heading* of a root rotation R is
the yaw about +y of that forward axis projected on the ground, ``atan2(R[0, 2], R[2, 2])``.
A *heading frame* removes a yaw and a ground-plane origin from a motion: the root rotation
becomes ``H @ R_root`` and the translation ``H @ (trans - origin)`` with ``H = R_y(-yaw)``; the
other joints' rotations are local and stay as they are.

Everything here is written with explicit elementwise tensor ops (no ``torch.linalg.cross``, no
reshapes to fixed batch sizes), so that a prior's decoder that calls it traces to ONNX with
dynamic batch dimensions; :mod:`benchmark.core.rotations` holds the general (roma-based)
conversions. Embedded weights and golden numbers depend on these exact ops and their order:
change them only with a retraining and new goldens.
"""

from __future__ import annotations

import torch


# Fixed z-up -> y-up rotation (AMASS and other z-up worlds into the project's y-up world): -90 degrees
# about x, (x, y, z) -> (x, z, -y).
Z_UP_TO_Y_UP = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], dtype=torch.float64)


def yaw_matrix(yaw: torch.Tensor) -> torch.Tensor:
    """(...,) angles about +y (radians) -> (..., 3, 3) rotations R_y: x' = cos x + sin z,
    z' = -sin x + cos z, so that R_y(a) e_z = (sin a, 0, cos a)."""
    c, s = torch.cos(yaw), torch.sin(yaw)
    o, z = torch.ones_like(c), torch.zeros_like(c)
    return torch.stack([c, z, s, z, o, z, -s, z, c], dim=-1).unflatten(-1, (3, 3))


def heading(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) root rotations -> (...) yaw of the body's forward (+z) axis about +y
    (0 = facing +z); R = R_y(heading) R_x(b) R_z(a) in scipy's ``'zxy'`` terms."""
    fwd = R[..., :, 2]
    return torch.atan2(fwd[..., 0], fwd[..., 2])


def ground_origin(trans: torch.Tensor) -> torch.Tensor:
    """(B, T, 3) translations -> (B, 3) the first frame's ground-plane position (x_0, 0, z_0)."""
    return trans[:, 0] * trans.new_tensor([1.0, 0.0, 1.0])


def to_heading_frame(rot: torch.Tensor, trans: torch.Tensor, H: torch.Tensor, origin: torch.Tensor):
    """Rigidly move motions by ``H`` about ``origin``: rot (B, T, J, 3, 3) local rotations (joint 0 the
    root), trans (B, T, 3), H (B, 3, 3) (usually ``yaw_matrix(-yaw)``), origin (B, 3) ->
    (rot with root ``H @ R_root``, ``(trans - origin) @ H^T``). :func:`from_heading_frame` with
    ``H^T`` inverts it."""
    root = H[:, None] @ rot[:, :, 0]
    rot = torch.cat([root[:, :, None], rot[:, :, 1:]], dim=2)
    trans = ((trans - origin[:, None]) @ H.transpose(-1, -2).to(trans.dtype))
    return rot, trans


def from_heading_frame(rot: torch.Tensor, trans: torch.Tensor, H: torch.Tensor, origin: torch.Tensor):
    """The way back from a heading frame: root ``H @ R_root``, translation ``trans @ H^T + origin``
    (H (B, 3, 3) usually ``yaw_matrix(yaw)``, origin (B, 3))."""
    root = H[:, None] @ rot[:, :, 0]
    rot = torch.cat([root[:, :, None], rot[:, :, 1:]], dim=2)
    return rot, trans @ H.transpose(-1, -2).to(trans.dtype) + origin[:, None]


def sixd_columns_to_matrix(x: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """(..., 6) "columns" 6D [a1, a2] -> (..., 3, 3) by Gram-Schmidt, elementwise ops only.

    b1 = a1 / |a1|, b2 = the normalised part of a2 orthogonal to b1, b3 = b1 x b2; R = [b1 b2 b3]
    (columns); norms are clamped at ``eps``. Same map as
    ``benchmark.core.rotations.sixd_to_matrix(x, "columns")`` (up to rounding), but ONNX-traceable
    with every batch dimension dynamic.
    """
    a1, a2 = x[..., 0:3], x[..., 3:6]
    b1 = a1 / a1.norm(dim=-1, keepdim=True).clamp_min(eps)
    b2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = b2 / b2.norm(dim=-1, keepdim=True).clamp_min(eps)
    b3 = torch.stack([
        b1[..., 1] * b2[..., 2] - b1[..., 2] * b2[..., 1],
        b1[..., 2] * b2[..., 0] - b1[..., 0] * b2[..., 2],
        b1[..., 0] * b2[..., 1] - b1[..., 1] * b2[..., 0],
    ], dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


def matrix_to_sixd_columns(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 6) = [R[:, 0], R[:, 1]], the inverse of :func:`sixd_columns_to_matrix`."""
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)


__all__ = ["yaw_matrix", "heading", "ground_origin", "to_heading_frame", "from_heading_frame",
           "sixd_columns_to_matrix", "matrix_to_sixd_columns"]
