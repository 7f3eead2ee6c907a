"""The body-model interface every body (embedded Anny body, SMPL files) implements.

A body maps, batched over (batch, time):
    rotations  (B, T, 22, 3, 3) local joint rotations (or (B, T, 22, 6) 6D, see ``sixd_layout``)
    trans      (B, T, 3)        root translation in metres (y up)
    shape      (B, S)           body-shape vector, constant over a sequence
to a :class:`BodyOutput` with vertices (B, T, V, 3) and the 22 joint positions (B, T, 22, 3).

Rotations are local, relative to a T-pose rest whose joint frames are aligned with the world
axes (the SMPL convention, docs/protocol.md); with zero rotations and zero translation the body
stands in its T-pose. The shape-dependent rest state (rest mesh, rest joints, per-joint rest
transforms) is computed once per shape by :meth:`BodyModel.prepare` and shared by all frames.
"""

from __future__ import annotations

import copy
import weakref
from dataclasses import dataclass

import torch

from benchmark.core.skeleton import LANDMARK_NAMES, NUM_JOINTS


@dataclass
class BodyOutput:
    vertices: torch.Tensor  # (B, T, V, 3)
    joints: torch.Tensor  # (B, T, 22, 3)


@dataclass
class RestState:
    """Shape-dependent quantities, computed once per shape (batch B), never per frame."""

    vertices: torch.Tensor  # (B, V, 3) the mesh the skinning transforms act on
    joints: torch.Tensor  # (B, 22, 3) T-pose joint positions at zero translation
    pre_transforms: torch.Tensor | None = None  # (B, 22, 4, 4) maps `vertices` into the T-pose per joint
    extra: dict | None = None  # body-specific (e.g. SMPL pose blend shapes)


class BodyModel(torch.nn.Module):
    """Abstract batched, differentiable body model (see module docstring)."""

    name: str = "body"
    shape_dim: int = 0

    # Subclasses register buffers: `faces` (F, 3) long, `landmark_indices` (16,) long.
    faces: torch.Tensor
    landmark_indices: torch.Tensor

    @property
    def num_vertices(self) -> int:
        raise NotImplementedError

    def on_cpu(self) -> "BodyModel":
        """This body on the CPU: itself when it is there, else a copy made once and kept (the body
        itself is not moved). The tables build their data (captures, ground truth, observations) on
        it whatever the run's device, so a GPU run fits and scores the very observations a CPU run
        does, with the same fingerprints (a GPU's rounding would otherwise move every scan point)."""
        if self.faces.device.type == "cpu":
            return self
        kept = _CPU_COPIES.get(self)
        if kept is None:
            kept = copy.deepcopy(self)
            kept.__dict__.pop("_loss_subsets", None)  # made on the device: the CPU copy makes its own
            kept = kept.to("cpu")
            _CPU_COPIES[self] = kept
        return kept

    @property
    def landmark_names(self) -> tuple[str, ...]:
        return LANDMARK_NAMES

    def default_shape(self, batch_size: int = 1) -> torch.Tensor:
        """(B, S) the body's neutral shape vector."""
        raise NotImplementedError

    def prepare(self, shape: torch.Tensor) -> RestState:
        """Shape-dependent rest state for a (B, S) shape batch; differentiable in shape."""
        raise NotImplementedError

    def skin(self, rest: RestState, rotations: torch.Tensor, trans: torch.Tensor,
             vertex_indices: torch.Tensor | None = None) -> BodyOutput:
        """Pose a prepared rest state: rotations (B, T, 22, 3, 3), trans (B, T, 3).

        ``vertex_indices`` (K,) poses only those vertices (vertices (B, T, K, 3)); joints are always all 22.
        """
        raise NotImplementedError

    def forward(
        self,
        rotations: torch.Tensor,
        trans: torch.Tensor | None = None,
        shape: torch.Tensor | None = None,
        rest: RestState | None = None,
        sixd_layout: str = "columns",
    ) -> BodyOutput:
        rotations = as_rotation_matrices(rotations, sixd_layout)
        if rotations.dim() != 5 or rotations.shape[2] != NUM_JOINTS:
            raise ValueError(
                f"{type(self).__name__}: rotations must be (batch, time, 22, 3, 3) matrices or "
                f"(batch, time, 22, 6) 6D, got shape {tuple(rotations.shape)}"
            )
        B, T = rotations.shape[:2]
        if trans is None:
            trans = rotations.new_zeros(B, T, 3)
        if trans.shape != (B, T, 3):
            raise ValueError(f"trans must be (batch, time, 3) = {(B, T, 3)}, got {tuple(trans.shape)}")
        if rest is None:
            if shape is None:
                shape = self.default_shape(B).to(rotations)
            if shape.dim() != 2 or shape.shape[1] != self.shape_dim:
                raise ValueError(
                    f"shape must be (batch, {self.shape_dim}) for body {self.name!r}, got {tuple(shape.shape)}"
                )
            rest = self.prepare(shape)
        return self.skin(rest, rotations, trans)

    def rest_joints(self, shape: torch.Tensor) -> torch.Tensor:
        """(B, 22, 3) T-pose joint positions at zero translation."""
        return self.prepare(shape).joints

    def loss_vertex_indices(self, count: int | None) -> torch.Tensor | None:
        """A fixed, evenly spread subset of ``count`` vertices (farthest-point sample of the T-pose,
        chosen on the CPU: the same vertices on every device), or None for all."""
        if count is None or count >= self.num_vertices:
            return None
        cache = self.__dict__.setdefault("_loss_subsets", {})
        hit = cache.get(count)
        if hit is not None and hit.device == self.faces.device:  # (a copy moved to another device chooses again)
            return hit
        if self.faces.device.type != "cpu":
            cache[count] = self.on_cpu().loss_vertex_indices(count).to(self.faces.device)
            return cache[count]
        from benchmark.core.surface_sampling import farthest_point_indices

        with torch.no_grad():
            rest = self.prepare(self.default_shape(1))
            eye = torch.eye(3).expand(1, 1, NUM_JOINTS, 3, 3)
            tpose = self.skin(rest, eye, torch.zeros(1, 1, 3)).vertices[0, 0]
        cache[count] = farthest_point_indices(tpose, count)
        return cache[count]

    def landmarks(self, vertices: torch.Tensor) -> torch.Tensor:
        """(..., V, 3) -> (..., 16, 3) the landmark vertices, in LANDMARK_NAMES order."""
        return vertices.index_select(-2, self.landmark_indices)


def as_rotation_matrices(rotations: torch.Tensor, sixd_layout: str = "columns") -> torch.Tensor:
    """Accept (..., 3, 3) matrices or (..., 6) 6D; return matrices."""
    if rotations.shape[-1] == 6:
        from benchmark.core.rotations import sixd_to_matrix

        return sixd_to_matrix(rotations, layout=sixd_layout)
    if rotations.shape[-2:] != (3, 3):
        raise ValueError(f"rotations must end in (3, 3) or (6,), got shape {tuple(rotations.shape)}")
    return rotations


# BodyModel.on_cpu's copies, by body (a body on a device keeps its CPU copy while it lives)
_CPU_COPIES: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
