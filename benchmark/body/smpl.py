"""SMPL / SMPL-H / SMPL-X bodies from model files the user holds, behind :class:`BodyModel`.

Linear blend skinning exactly as the reference SMPL (smplx ``lbs.py``), batched over (B, T):

    v_shaped = v_template + shapedirs . beta                     (per shape, in ``prepare``)
    J        = J_regressor . v_shaped                            (per shape)
    v_posed  = v_shaped + posedirs . (R_j - I)_{j=1..J-1}        (per frame)
    A_j      = FK over the kinematic tree, as rest -> posed transforms
    v        = sum_j w_j A_j v_posed + trans

The interface drives the 22 body joints; every other joint of the file (SMPL hands 22-23, SMPL-H
fingers, SMPL-X jaw / eyes / fingers) keeps the identity rotation. Two exact simplifications
follow, and make the per-frame work independent of the file's joint count:

- an identity joint adds nothing to the pose feature (R - I = 0), so only the first 21 x 9
  columns of ``posedirs`` are kept;
- a joint whose local rotations, up to its nearest body ancestor, are all identity has the same
  skinning transform as that ancestor (A_j x = G_a (x - J_a) + P_a), so its skinning weights are
  added to the ancestor's and FK runs over the 22 body joints only.

The tests compare this against a plain full-tree reference (all J joints, all of ``posedirs``).
The model frame is SMPL's: y up, facing +z, left at +x, which is the project's convention.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from benchmark.body.base import BodyModel, BodyOutput, RestState
from benchmark.body.landmarks import select_landmarks
from benchmark.body.lbs import forward_kinematics, linear_blend_skinning, skinning_transforms
from benchmark.body.smpl_files import BodyModelData, read_body_model_file
from benchmark.core.skeleton import NUM_JOINTS, PARENTS


def fold_skinning_weights(weights: np.ndarray, parents: np.ndarray, num_body_joints: int = NUM_JOINTS) -> np.ndarray:
    """(V, J) weights -> (V, num_body_joints): each extra joint's weight added to its nearest body ancestor."""
    folded = weights[:, :num_body_joints].copy()
    for j in range(num_body_joints, len(parents)):
        a = j
        while a >= num_body_joints:
            a = int(parents[a])
        folded[:, a] += weights[:, j]
    return folded


class SMPLBody(BodyModel):
    """A body from an SMPL-family model file; shape = the first ``num_betas`` shape coefficients.

    Buffers (``dtype``, float32 by default): ``v_template`` (V, 3), ``shapedirs`` (S, 3V),
    ``posedirs`` (189, 3V), ``J_regressor`` (J, V), ``weights`` (V, 22), ``faces`` (F, 3) long,
    ``landmark_indices`` (16,) long.
    """

    def __init__(
        self,
        data: BodyModelData,
        num_betas: int = 10,
        name: str | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        super().__init__()
        if tuple(int(p) for p in data.parents[:NUM_JOINTS]) != PARENTS:
            raise ValueError(
                f"{data.path}: the first {NUM_JOINTS} joints of the kinematic tree are not the SMPL body "
                f"(parents {data.parents[:NUM_JOINTS].tolist()}, expected {list(PARENTS)})"
            )
        if not 1 <= num_betas <= data.num_betas:
            raise ValueError(
                f"{data.path}: num_betas={num_betas} but the file holds {data.num_betas} shape components; "
                f"choose 1..{data.num_betas}"
            )
        self.name = name or data.model_type
        self.model_type = data.model_type
        self.source_path = Path(data.path)
        self.shape_dim = int(num_betas)
        self.num_file_joints = data.num_joints
        V = data.num_vertices

        def to_tensor(a):  # the file's float64 arrays, stored at ``dtype``
            return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype)

        self.register_buffer("v_template", to_tensor(data.v_template))
        self.register_buffer("shapedirs", to_tensor(data.shapedirs[:, :, :num_betas].reshape(V * 3, num_betas).T))
        body_pose_dim = 9 * (NUM_JOINTS - 1)
        self.register_buffer("posedirs", to_tensor(data.posedirs[:, :, :body_pose_dim].reshape(V * 3, body_pose_dim).T))
        self.register_buffer("J_regressor", to_tensor(data.J_regressor))
        self.register_buffer("weights", to_tensor(fold_skinning_weights(data.weights, data.parents)))
        self.register_buffer("faces", torch.as_tensor(data.faces, dtype=torch.long))
        rest_vertices = torch.as_tensor(data.v_template)
        rest_joints = torch.as_tensor(data.J_regressor[:NUM_JOINTS]) @ rest_vertices
        self.register_buffer("landmark_indices", select_landmarks(rest_vertices, rest_joints))

    @classmethod
    def from_file(
        cls, path: str | Path, num_betas: int = 10, name: str | None = None, dtype: torch.dtype = torch.float32
    ) -> "SMPLBody":
        """Read an ``.npz`` / ``.pkl`` SMPL, SMPL-H or SMPL-X model file."""
        return cls(read_body_model_file(path), num_betas=num_betas, name=name, dtype=dtype)

    @property
    def num_vertices(self) -> int:
        return self.v_template.shape[0]

    def default_shape(self, batch_size: int = 1) -> torch.Tensor:
        """(B, num_betas) zeros: the mean shape."""
        return self.v_template.new_zeros(batch_size, self.shape_dim)

    def prepare(self, shape: torch.Tensor) -> RestState:
        """Per-shape rest state for betas (B, S).

        Returns RestState(vertices = v_shaped (B, V, 3), joints = first 22 rest joints (B, 22, 3),
        extra = {"all_joints": (B, J, 3) every rest joint of the file}).
        """
        if shape.dim() != 2 or shape.shape[1] != self.shape_dim:
            raise ValueError(f"{self.name}: shape must be (batch, {self.shape_dim}) betas, got {tuple(shape.shape)}")
        B = shape.shape[0]
        v_shaped = self.v_template + (shape.to(self.shapedirs) @ self.shapedirs).view(B, -1, 3)
        all_joints = torch.einsum("jv,bvc->bjc", self.J_regressor, v_shaped)
        return RestState(vertices=v_shaped, joints=all_joints[:, :NUM_JOINTS], extra={"all_joints": all_joints})

    def skin(self, rest: RestState, rotations: torch.Tensor, trans: torch.Tensor,
             vertex_indices: torch.Tensor | None = None) -> BodyOutput:
        """Pose a rest state: rotations (B, T, 22, 3, 3) local, trans (B, T, 3) metres.

        Returns vertices (B, T, V, 3) and the 22 joints (B, T, 22, 3), both translated by ``trans``.
        The rest state's batch may be B or 1. ``vertex_indices`` (K,) poses only those vertices.
        """
        if rotations.dim() != 5 or rotations.shape[2:] != (NUM_JOINTS, 3, 3):
            raise ValueError(f"{self.name}: rotations must be (B, T, 22, 3, 3), got {tuple(rotations.shape)}")
        B, T = rotations.shape[:2]
        if trans.shape != (B, T, 3):
            raise ValueError(f"{self.name}: trans must be (B, T, 3) = {(B, T, 3)}, got {tuple(trans.shape)}")
        eye = torch.eye(3, dtype=rotations.dtype, device=rotations.device)
        pose_feature = (rotations[:, :, 1:] - eye).flatten(2)  # (B, T, 189)
        posedirs, rest_vertices, weights = self.posedirs, rest.vertices, self.weights
        if vertex_indices is not None:
            posedirs = posedirs.view(posedirs.shape[0], -1, 3)[:, vertex_indices].flatten(1)
            rest_vertices, weights = rest_vertices[:, vertex_indices], weights[vertex_indices]
        pose_offsets = (pose_feature @ posedirs).view(B, T, -1, 3)
        v_posed = rest_vertices[:, None] + pose_offsets  # (B, T, V, 3)
        rest_joints = rest.joints[:, None]  # (B|1, 1, 22, 3)
        global_rot, joints = forward_kinematics(rotations, rest_joints, PARENTS)
        transforms = skinning_transforms(global_rot, joints, rest_joints)
        vertices = linear_blend_skinning(v_posed, weights, transforms)
        offset = trans[:, :, None, :]
        return BodyOutput(vertices=vertices + offset, joints=joints + offset)
