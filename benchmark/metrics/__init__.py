"""Metrics: pure functions of batched tensors, metres in and out (docs/protocol.md, conventions).

- :mod:`.chamfer`: Chamfer distance / differentiable Chamfer loss (kdtree = pykdtree, scipy,
  tiled, naive backends; :class:`~.chamfer.StaticChamfer` for a fit against fixed points).
- :mod:`.surface`: point-to-surface Chamfer (exact point-to-triangle distances).
- :mod:`.pose`: MPJPE, PA-MPJPE, V2V, mean acceleration, acceleration error, frame reductions.
- :mod:`.perf`: side-by-side timing of the Chamfer backends (part of ``python -m benchmark perf``,
  :mod:`benchmark.tools.perf`).
"""

from benchmark.metrics.chamfer import chamfer_distance, chamfer_loss, nearest_neighbors
from benchmark.metrics.perf import chamfer_perf
from benchmark.metrics.pose import (
    acceleration_error,
    mean_acceleration,
    mpjpe,
    pa_mpjpe,
    procrustes_align,
    reduce_frames,
    v2v,
    valid_frame_counts,
)
from benchmark.metrics.surface import chamfer_surface_distance, point_triangle_distance, points_to_surface_distance

__all__ = [
    "acceleration_error",
    "chamfer_distance",
    "chamfer_loss",
    "chamfer_perf",
    "chamfer_surface_distance",
    "mean_acceleration",
    "mpjpe",
    "nearest_neighbors",
    "pa_mpjpe",
    "point_triangle_distance",
    "points_to_surface_distance",
    "procrustes_align",
    "reduce_frames",
    "v2v",
    "valid_frame_counts",
]
