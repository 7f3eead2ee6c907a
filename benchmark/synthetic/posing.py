"""Anatomical joint angles -> SMPL-22 local rotation matrices (the generator's pose vocabulary).

Local rotations follow the SMPL convention (docs/protocol.md): relative to a T-pose whose joint
frames are aligned with the world axes (y up, facing +z, left at +x). The angles below are
anatomical and mirror-symmetric: a positive value means the same movement on either side.

Legs (hip, knee, ankle, toes), side sign s = +1 left, -1 right:
    hip   = Rx(-flex) Rz(s abd) Ry(s twist)  flex > 0 swings the thigh forward, abd > 0 outward,
                                              twist > 0 turns the knee inward
    knee  = Rx(knee)                          knee > 0 bends (shank backward)
    ankle = Rx(-dorsi)                        dorsi > 0 lifts the toes
    foot  = Rx(-toe)                          toe > 0 extends the toes (push-off)
Arms (shoulder, elbow, wrist):
    shoulder = Rx(-flex) Rz(s (abd - 90deg)) Rx(twist)
        with flex = abd = 0 the arm hangs down; abd = 90 deg is the T-pose; flex = 90 deg points
        the arm forward, 180 deg overhead; twist > 0 rotates the arm inward (internal rotation)
    elbow = Ry(-s elbow)                      elbow > 0 bends the forearm (forward when hanging)
    collar = Rz(s elevation)                  shrug
Trunk and head: R = Ry(twist) Rz(-bend) Rx(flex), flex > 0 forward, bend > 0 toward the left,
twist > 0 turns the front toward the left (+x); spine angles are shared 40/30/30 over
spine1/spine2/spine3, neck angles 50/50 over neck/head.
Root (pelvis, relative to the heading frame): Ry(yaw) Rz(-roll) Rx(pitch), same signs as trunk.

All angles in radians, tensors of shape (T,) (or scalars); everything is batched over T.
"""

from __future__ import annotations

import math

import roma
import torch

from benchmark.core.skeleton import JOINT_INDEX, MIRROR, NUM_JOINTS

_DTYPE = torch.float64
_HALF_PI = math.pi / 2
_SIDE = {"left": 1.0, "right": -1.0}
_MIRROR_INDEX = torch.tensor(MIRROR)
_MIRROR_M = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=_DTYPE))


_AXES = {"X": 0, "Y": 1, "Z": 2}


def _euler(angles: torch.Tensor, order: str) -> torch.Tensor:
    """(T, 3) angles -> (T, 3, 3) = R_order[0](a0) R_order[1](a1) R_order[2](a2) (intrinsic, as
    :func:`benchmark.core.rotations.euler_to_matrix`), from three batched Rodrigues conversions."""
    rv = angles.new_zeros(*angles.shape[:-1], 3, 3)
    for k, axis in enumerate(order):
        rv[..., k, _AXES[axis]] = angles[..., k]
    R = roma.rotvec_to_rotmat(rv)  # (T, 3, 3, 3): one rotation per axis
    return R[..., 0, :, :] @ R[..., 1, :, :] @ R[..., 2, :, :]


def _angles(n: int, *values) -> torch.Tensor:
    """Stack scalars / (n,) tensors into (n, len(values)) float64."""
    return torch.stack([torch.as_tensor(v, dtype=_DTYPE).expand(n) for v in values], dim=-1)


class PoseBuilder:
    """Accumulates local rotations (T, 22, 3, 3) for T time samples; unset joints stay identity."""

    def __init__(self, n: int):
        self.n = int(n)
        self.rot = torch.eye(3, dtype=_DTYPE).repeat(self.n, NUM_JOINTS, 1, 1)

    def _set(self, joint: str, order: str, *angles) -> None:
        self.rot[:, JOINT_INDEX[joint]] = _euler(_angles(self.n, *angles), order)

    def root(self, pitch=0.0, roll=0.0, yaw=0.0) -> PoseBuilder:
        self._set("pelvis", "YZX", yaw, -torch.as_tensor(roll, dtype=_DTYPE), pitch)
        return self

    def leg(self, side: str, flex=0.0, abd=0.0, twist=0.0, knee=0.0, dorsi=0.0, toe=0.0,
            level: bool = False, plant: bool = False) -> PoseBuilder:
        """Set one leg. ``level=True``: the foot is kept level with the floor whatever the hip,
        knee and root angles (the ankle rotation is solved), and ``dorsi`` is then the foot's
        pitch relative to the floor (toes up > 0); call :meth:`root` first. ``plant=True``: the
        hip abduction is corrected so that bending the knee and hip does not move the ankle
        sideways relative to the pelvis (it stays where the straight leg with abduction ``abd``
        puts it), so both feet of a symmetric squat or bounce stay planted."""
        s = _SIDE[side]
        n = self.n
        f = torch.as_tensor(flex, dtype=_DTYPE).expand(n)
        a = torch.as_tensor(abd, dtype=_DTYPE).expand(n)
        tw = torch.as_tensor(twist, dtype=_DTYPE).expand(n)
        k = torch.as_tensor(knee, dtype=_DTYPE).expand(n)
        if plant:
            a = _planted_abduction(a, tw * s, k, s)
        self._set(f"{side}_hip", "XZY", -f, s * a, s * tw)
        self._set(f"{side}_knee", "XYZ", k, 0.0, 0.0)
        d = torch.as_tensor(dorsi, dtype=_DTYPE).expand(n)
        if level:
            root = self.rot[:, 0]
            chain = root @ self.rot[:, JOINT_INDEX[f"{side}_hip"]] @ self.rot[:, JOINT_INDEX[f"{side}_knee"]]
            fwd = root[..., :, 2]  # the pelvis's forward axis; the foot keeps its yaw plus the hip twist
            yaw = torch.atan2(fwd[..., 0], fwd[..., 2]) - s * tw
            target = _euler(_angles(n, yaw, -d, 0.0), "YXZ")
            self.rot[:, JOINT_INDEX[f"{side}_ankle"]] = chain.transpose(-1, -2) @ target
        else:
            self._set(f"{side}_ankle", "XYZ", -d, 0.0, 0.0)
        self._set(f"{side}_foot", "XYZ", -torch.as_tensor(toe, dtype=_DTYPE), 0.0, 0.0)
        return self

    def ankle_height(self, side: str, rest_joints: torch.Tensor) -> torch.Tensor:
        """(T,) height of the ankle joint relative to the pelvis joint (m), from the root and leg
        rotations set so far and the rest skeleton's joints (22, 3)."""
        R_root = self.rot[:, 0]
        R_hip = self.rot[:, JOINT_INDEX[f"{side}_hip"]]
        R_knee = self.rot[:, JOINT_INDEX[f"{side}_knee"]]
        J = rest_joints.to(_DTYPE)
        hip = J[JOINT_INDEX[f"{side}_hip"]] - J[JOINT_INDEX["pelvis"]]
        thigh = J[JOINT_INDEX[f"{side}_knee"]] - J[JOINT_INDEX[f"{side}_hip"]]
        shank = J[JOINT_INDEX[f"{side}_ankle"]] - J[JOINT_INDEX[f"{side}_knee"]]
        v = hip + (R_hip @ (thigh + (R_knee @ shank[:, None])[..., 0])[..., None])[..., 0]
        return (R_root @ v[..., None])[..., 1, 0]

    def leg_matching(self, side: str, ref_side: str, rest_joints: torch.Tensor, flex=0.0, abd=0.0, twist=0.0,
                     dorsi=0.0, toe=0.0, iterations: int = 3) -> PoseBuilder:
        """Set a planted, level leg whose knee flexion puts its ankle at the height of the
        ``ref_side`` ankle (already set), so that both feet of an asymmetric stance stand on the
        floor. The knee is solved in closed form for the current hip rotation (ankle height is
        c + A cos k + B sin k in the knee angle k), a few times because the planted abduction
        depends on the knee."""
        target = self.ankle_height(ref_side, rest_joints)
        J = rest_joints.to(_DTYPE)
        hip = J[JOINT_INDEX[f"{side}_hip"]] - J[JOINT_INDEX["pelvis"]]
        thigh = J[JOINT_INDEX[f"{side}_knee"]] - J[JOINT_INDEX[f"{side}_hip"]]
        shank = J[JOINT_INDEX[f"{side}_ankle"]] - J[JOINT_INDEX[f"{side}_knee"]]
        knee = self._knee_of(ref_side)
        for _ in range(iterations):
            self.leg(side, flex=flex, abd=abd, twist=twist, knee=knee, dorsi=dorsi, toe=toe, level=True, plant=True)
            R = self.rot[:, 0] @ self.rot[:, JOINT_INDEX[f"{side}_hip"]]  # (T, 3, 3)
            row = R[:, 1, :]  # y row
            c = (self.rot[:, 0] @ hip)[:, 1] + row @ thigh + row[:, 0] * shank[0]
            # Rx(k) shank = (sx, sy cos k - sz sin k, sy sin k + sz cos k)
            A = row[:, 1] * shank[1] + row[:, 2] * shank[2]
            B = -row[:, 1] * shank[2] + row[:, 2] * shank[1]
            r = torch.sqrt(A * A + B * B)
            phi = torch.atan2(B, A)
            base = torch.arccos(((target - c) / r).clamp(-1.0, 1.0))
            cands = torch.stack([phi + base, phi - base], dim=-1)
            cands = torch.remainder(cands + math.pi, 2 * math.pi) - math.pi
            pick = (cands - knee[..., None]).abs().argmin(dim=-1, keepdim=True)
            knee = cands.gather(-1, pick)[..., 0].clamp(min=0.0)
        self.leg(side, flex=flex, abd=abd, twist=twist, knee=knee, dorsi=dorsi, toe=toe, level=True, plant=True)
        return self

    def _knee_of(self, side: str) -> torch.Tensor:
        R = self.rot[:, JOINT_INDEX[f"{side}_knee"]]
        return torch.atan2(R[:, 2, 1], R[:, 1, 1])

    def arm(self, side: str, flex=0.0, abd=0.0, twist=0.0, elbow=0.0, shrug=0.0, wrist=0.0) -> PoseBuilder:
        s = _SIDE[side]
        self._set(f"{side}_collar", "ZYX", s * torch.as_tensor(shrug, dtype=_DTYPE), 0.0, 0.0)
        self._set(f"{side}_shoulder", "XZX", -torch.as_tensor(flex, dtype=_DTYPE),
                  s * (torch.as_tensor(abd, dtype=_DTYPE) - _HALF_PI), twist)
        self._set(f"{side}_elbow", "YXZ", -s * torch.as_tensor(elbow, dtype=_DTYPE), 0.0, 0.0)
        self._set(f"{side}_wrist", "XYZ", -torch.as_tensor(wrist, dtype=_DTYPE), 0.0, 0.0)
        return self

    def spine(self, flex=0.0, bend=0.0, twist=0.0) -> PoseBuilder:
        for joint, share in (("spine1", 0.4), ("spine2", 0.3), ("spine3", 0.3)):
            self._set(joint, "YZX", share * torch.as_tensor(twist, dtype=_DTYPE),
                      -share * torch.as_tensor(bend, dtype=_DTYPE), share * torch.as_tensor(flex, dtype=_DTYPE))
        return self

    def head(self, flex=0.0, bend=0.0, twist=0.0) -> PoseBuilder:
        for joint in ("neck", "head"):
            self._set(joint, "YZX", 0.5 * torch.as_tensor(twist, dtype=_DTYPE),
                      -0.5 * torch.as_tensor(bend, dtype=_DTYPE), 0.5 * torch.as_tensor(flex, dtype=_DTYPE))
        return self


def _planted_abduction(abd: torch.Tensor, twist: torch.Tensor, knee: torch.Tensor, s: float) -> torch.Tensor:
    """Hip abduction that keeps the ankle's sideways offset from the hip (pelvis frame) at the
    straight leg's value 2 sin(abd) (thigh and shank of equal length), given knee flexion.

    The hip is Rx(-flex) Rz(s a) Ry(s twist) and Rx leaves x alone, so the offset is the x of
    Rz(s a) w with w = Ry(s twist) (down + Rx(knee) down): w_x cos(s a) - w_y sin(s a) = target.
    """
    w_x = -torch.sin(knee) * torch.sin(twist)
    w_y = -1.0 - torch.cos(knee)
    target = s * 2.0 * torch.sin(abd)
    r = torch.sqrt(w_x**2 + w_y**2)
    phi = torch.atan2(w_y, w_x)
    base = torch.arccos((target / r).clamp(-1.0, 1.0))
    cands = torch.stack([base - phi, -base - phi], dim=-1)
    cands = torch.remainder(cands + math.pi, 2 * math.pi) - math.pi
    pick = (cands - s * abd[..., None]).abs().argmin(dim=-1, keepdim=True)
    return s * cands.gather(-1, pick)[..., 0]


def mirror_pose(rot: torch.Tensor) -> torch.Tensor:
    """Left/right mirror of local rotations (..., 22, 3, 3) about the body's sagittal plane x = 0.

    The mirrored joint j takes the rotation of its mirror joint, conjugated by diag(-1, 1, 1).
    """
    M = _MIRROR_M.to(rot)
    return M @ rot[..., _MIRROR_INDEX.to(rot.device), :, :] @ M
