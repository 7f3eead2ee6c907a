"""Pure batched tensor functions for forward kinematics and linear blend skinning.

No state, no modules: the body models call these with their buffers.
"""

from __future__ import annotations

import torch

from benchmark.core.skeleton import PARENTS


def kinematic_levels(parents=PARENTS) -> list[list[int]]:
    """Joints grouped by depth, so FK takes one batched product per level."""
    depth = []
    for j, p in enumerate(parents):
        depth.append(0 if p < 0 else depth[p] + 1)
    return [[j for j in range(len(parents)) if depth[j] == d] for d in range(max(depth) + 1)]


_PARENT_INDEX: dict = {}


def _parent_index(parents: tuple, device) -> torch.Tensor:
    """The parents' index tensor on ``device``, made once (a host-to-device copy per call on CUDA)."""
    key = (parents, str(device))
    if key not in _PARENT_INDEX:
        _PARENT_INDEX[key] = torch.tensor([max(p, 0) for p in parents], device=device)
    return _PARENT_INDEX[key]


def forward_kinematics(
    rotations: torch.Tensor, rest_joints: torch.Tensor, parents=PARENTS
) -> tuple[torch.Tensor, torch.Tensor]:
    """Global rotations and joint positions for local rotations about a rest skeleton.

    rotations: (..., J, 3, 3) local rotations in world-aligned rest frames.
    rest_joints: (..., J, 3) rest joint positions (broadcastable against rotations' batch dims).
    Returns (global_rotations (..., J, 3, 3), joints (..., J, 3)), root at its rest position.
    """
    batch = rotations.shape[:-3]
    rest_joints = rest_joints.expand(*batch, *rest_joints.shape[-2:])
    J = len(parents)
    offsets = rest_joints.clone()
    par = _parent_index(tuple(parents), rest_joints.device)
    offsets[..., 1:, :] = rest_joints[..., 1:, :] - rest_joints[..., par[1:], :]
    g_rot = [None] * J
    g_pos = [None] * J
    for level in kinematic_levels(parents):
        for j in level:
            p = parents[j]
            if p < 0:
                g_rot[j] = rotations[..., j, :, :]
                g_pos[j] = rest_joints[..., j, :]
            else:
                g_rot[j] = g_rot[p] @ rotations[..., j, :, :]
                g_pos[j] = g_pos[p] + (g_rot[p] @ offsets[..., j, :, None])[..., 0]
    return torch.stack(g_rot, dim=-3), torch.stack(g_pos, dim=-2)


def skinning_transforms(global_rotations: torch.Tensor, joints: torch.Tensor, rest_joints: torch.Tensor) -> torch.Tensor:
    """(..., J, 3, 4) transforms mapping rest-pose points to posed points, per joint."""
    rest_joints = rest_joints.expand_as(joints)
    t = joints - (global_rotations @ rest_joints[..., None])[..., 0]
    return torch.cat([global_rotations, t[..., None]], dim=-1)


def linear_blend_skinning(vertices: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Dense LBS.

    vertices: (..., V, 3) rest vertices; weights: (V, J) dense; transforms: (..., J, 3, 4).
    Returns (..., V, 3).
    """
    flat = transforms.flatten(-2)  # (..., J, 12)
    per_vertex = torch.matmul(weights, flat).unflatten(-1, (3, 4))  # (..., V, 3, 4)
    return (per_vertex[..., :3] @ vertices[..., None])[..., 0] + per_vertex[..., 3]


def shared_rest_blend_skinning(vertices: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Dense LBS of one rest mesh per sequence posed in every frame, as one matrix product.

    vertices: (B, V, 3) rest vertices; weights: (V, J); transforms: (B, T, J, 3, 4).
    Returns (B, T, V, 3), equal to ``linear_blend_skinning(vertices[:, None], weights, transforms)``
    up to rounding (float32: about 1e-7 of the coordinates).

    posed_v = sum_j w_vj G_j [v; 1] = sum_(j, k) (w_vj [v; 1]_k) G_j[:, k]: the (V, J x 4) products
    of each vertex's weights and homogeneous rest position times the (J x 4, T x 3) transforms of
    every frame. The reference form builds a 3 x 4 matrix per vertex and frame and applies it with a
    batch of B x T x V 3 x 3 products, forward and backward; this one is a single GEMM per sequence
    each way (7 x faster forward + backward for 8 sequences x 100 frames x 3,016 vertices on one
    CPU thread).
    """
    B, V = vertices.shape[0], vertices.shape[-2]
    T, J = transforms.shape[1], transforms.shape[2]
    homogeneous = torch.cat([vertices, torch.ones_like(vertices[..., :1])], dim=-1)  # (B, V, 4)
    products = (weights[:, :, None] * homogeneous[:, :, None, :]).reshape(B, V, J * 4)
    per_joint = transforms.permute(0, 2, 4, 1, 3).reshape(B, J * 4, T * 3)  # [(j, k), (t, i)] = G_tj[i, k]
    return (products @ per_joint).unflatten(-1, (T, 3)).transpose(1, 2)
