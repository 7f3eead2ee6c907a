"""Motion-DVAE's data side (pure torch, no I/O): the canonical frame, the state vectors the
networks read and write, the noisy copies of the denoising phase, and the body points of the loss.

See the package docstring (:mod:`priors.motion_dvae`) for the method; the networks are in
:mod:`priors.motion_dvae.model`.
"""

from __future__ import annotations

import math

import torch

from benchmark.body.lbs import forward_kinematics
from benchmark.core.frames import from_heading_frame, ground_origin, heading, to_heading_frame, yaw_matrix
from benchmark.core.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from benchmark.core.skeleton import NUM_JOINTS


FPS = 30.0
POSE_DIM = 3 + 3 + 3 * (NUM_JOINTS - 1)  # trans, root, 21 body joints = 69
STATE_DIM = 2 * POSE_DIM  # + velocities = 138
MARKER_OFFSET = 0.1  # metres, virtual markers along each joint frame's x and z axes
DENOISE_SIGMA_RANGE = (0.05, 0.25)  # rad, axis-angle noise of the denoising training copies


def canonicalise(rot: torch.Tensor, trans: torch.Tensor):
    """Remove the first frame's heading and ground-plane position (HuMoR's canonical frame, y up).

    rot (B, T, 22, 3, 3) local rotations (joint 0 = world root orientation), trans (B, T, 3).
    Returns (rot_c, trans_c, yaw (B,), origin (B, 3)) with ``R_root_c = Ry(-yaw) R_root`` and
    ``trans_c = Ry(-yaw) (trans - origin)``, origin = (x_0, 0, z_0): a rigid motion about a
    vertical axis, the same for every frame; :func:`uncanonicalise` inverts it.
    """
    yaw = heading(rot[:, 0, 0])
    origin = ground_origin(trans)
    rot_c, trans_c = to_heading_frame(rot, trans, yaw_matrix(-yaw), origin)  # Ry(-yaw), (B, 3, 3)
    return rot_c, trans_c, yaw, origin


def uncanonicalise(rot_c: torch.Tensor, trans_c: torch.Tensor, yaw: torch.Tensor, origin: torch.Tensor):
    """Inverse of :func:`canonicalise`."""
    return from_heading_frame(rot_c, trans_c, yaw_matrix(yaw), origin)


def unwrap_rotvec(aa: torch.Tensor) -> torch.Tensor:
    """(B, T, ..., 3) rotation vectors made continuous in time (dim 1).

    Each vector v (angle in [0, pi]) is replaced by its equivalent ``v - 2 pi v/|v|`` (angle - 2 pi)
    when that is closer to the previous frame's (already unwrapped) vector.
    """
    out = [aa[:, 0]]
    for t in range(1, aa.shape[1]):
        v = aa[:, t]
        n = v.norm(dim=-1, keepdim=True)
        alt = v - 2 * math.pi * v / n.clamp_min(1e-8)
        prev = out[-1]
        use_alt = ((alt - prev).norm(dim=-1, keepdim=True) < (v - prev).norm(dim=-1, keepdim=True)) & (n > 1e-8)
        out.append(torch.where(use_alt, alt, v))
    return torch.stack(out, dim=1)


def canonical_poses(windows: torch.Tensor, chunk: int = 2048) -> torch.Tensor:
    """(N, F, 69) raw windows (``priors.training.motion_windows``: axis-angle 22x3, translation) ->
    (N, F, 69) canonical pose sequences [trans (3), root aa (3), body aa (63)], unwrapped in time."""
    out = []
    for i in range(0, windows.shape[0], chunk):
        w = windows[i : i + chunk]
        poses = w[..., : NUM_JOINTS * 3].unflatten(-1, (NUM_JOINTS, 3))
        rot_c, trans_c, _, _ = canonicalise(axis_angle_to_matrix(poses), w[..., NUM_JOINTS * 3:])
        aa = unwrap_rotvec(matrix_to_axis_angle(rot_c))
        out.append(torch.cat([trans_c, aa.flatten(-2)], dim=-1))
    return torch.cat(out)


def pose_to_state(pos: torch.Tensor, fps: float = FPS) -> torch.Tensor:
    """(B, T, 69) pose sequences -> (B, T, 138) states (finite-difference velocities appended)."""
    vel = (pos[:, 1:] - pos[:, :-1]) * fps
    return torch.cat([pos, torch.cat([vel[:, :1], vel], dim=1)], dim=-1)


def motion_state(rot_c: torch.Tensor, trans_c: torch.Tensor, fps: float = FPS) -> torch.Tensor:
    """Canonical rotations (B, T, 22, 3, 3) and translation (B, T, 3) -> states (B, T, 138)."""
    if rot_c.shape[1] < 2:
        raise ValueError(f"motion-dvae: a motion needs at least 2 frames, got {rot_c.shape[1]}")
    aa = unwrap_rotvec(matrix_to_axis_angle(rot_c))  # (B, T, 22, 3)
    return pose_to_state(torch.cat([trans_c, aa.flatten(-2)], dim=-1), fps)


def windows_to_state(windows: torch.Tensor, fps: float = FPS) -> torch.Tensor:
    """(N, F, 69) raw windows -> (N, F, 138) canonical states."""
    return pose_to_state(canonical_poses(windows), fps)


def noisy_poses(pos: torch.Tensor, generator: torch.Generator | None = None,
                sigma_range=DENOISE_SIGMA_RANGE, body_only: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Noisy copies of canonical pose sequences (N, F, 69) for the denoising phase.

    sigma ~ U(sigma_range) per sequence, times N(0, 1) on every joint's axis-angle (root included;
    translation clean), then re-canonicalised at the noisy first frame (its heading), as a noisy
    input is at test time. The noise is added to the canonical root rotation vector (the denoise
    table adds it to the world one: the same noise law up to the heading, a documented
    approximation that avoids a per-step conversion of all 22 joints). Returns (noisy, sigma (N,)).
    body_only: the 21 body joints only; root rotation and translation unchanged, so the copy stays
    in the window's canonical frame (the clean encoder's noisy training inputs).
    """
    N = pos.shape[0]
    lo, hi = sigma_range
    sigma = lo + (hi - lo) * torch.rand(N, generator=generator)
    first = 6 if body_only else 3
    noise = torch.randn(pos[..., first:].shape, generator=generator) * sigma[:, None, None]
    if body_only:
        return torch.cat([pos[..., :6], pos[..., 6:] + noise.to(pos)], -1), sigma
    aa = pos[..., 3:] + noise.to(pos.device)
    root = axis_angle_to_matrix(aa[..., :3])  # (N, F, 3, 3)
    Rinv = yaw_matrix(-heading(root[:, 0]))  # (N, 3, 3)
    root_aa = unwrap_rotvec(matrix_to_axis_angle(Rinv[:, None] @ root))
    trans = pos[..., :3] @ Rinv.transpose(-1, -2)  # frame 0 is at the origin of the ground plane already
    return torch.cat([trans, root_aa, aa[..., 3:]], dim=-1), sigma


def rotvec_to_matrix(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) rotation vectors -> (..., 3, 3) by Rodrigues' formula, written without reshapes to
    fixed batch sizes (ONNX-traceable with a dynamic batch) and smooth at 0 (angle sqrt(|v|^2 + 1e-12))."""
    theta = torch.sqrt((v * v).sum(-1, keepdim=True) + 1e-12)
    k = v / theta
    x, y, z = k[..., 0], k[..., 1], k[..., 2]
    o = x * 0.0  # not zeros_like: the ONNX exporter folds that into a constant of the example's batch
    K = torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).unflatten(-1, (3, 3))
    s, c = torch.sin(theta)[..., None], torch.cos(theta)[..., None]
    eye = torch.eye(3, dtype=v.dtype, device=v.device)
    return eye + s * K + (1 - c) * (K @ K)


def state_to_motion(state: torch.Tensor):
    """States (..., 138) -> local rotations (..., 22, 3, 3) and translation (..., 3) (positions and
    orientations of the state; its velocities are not used)."""
    trans = state[..., :3]
    aa = state[..., 3:POSE_DIM].unflatten(-1, (NUM_JOINTS, 3))
    return rotvec_to_matrix(aa), trans


def body_points(rot: torch.Tensor, trans: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """(..., 66, 3) body points: 22 FK joints on ``rest`` (22, 3) + 2 virtual markers per joint
    (``MARKER_OFFSET`` along the joint frame's x and z axes), translated by ``trans``."""
    g_rot, joints = forward_kinematics(rot, rest)
    joints = joints + trans[..., None, :]
    mx = joints + MARKER_OFFSET * g_rot[..., :, 0]
    mz = joints + MARKER_OFFSET * g_rot[..., :, 2]
    return torch.cat([joints, mx, mz], dim=-2)
