"""The inputs of a completion work unit; shared by the synthetic
(:mod:`benchmark.protocols.completion_unit`) and captured-scan
(:mod:`benchmark.protocols.scan_completion`) data sources, which import it and not each other (the
seeds derived from a unit's coordinates: :func:`benchmark.core.work_units.stable_seed`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch


@dataclass
class UnitData:
    scans: object  # PointCloudSequence at the capture rate, for the window
    out_t: torch.Tensor  # (B, T_out) seconds from the window start
    gt_points: torch.Tensor  # (B, T_out, N, 3)
    gt_joints: torch.Tensor | None  # (B, T_out, 22, 3); None: captured scans (MPJPE n/a)
    row_extra: list | None = None  # per sequence: extra fields for its per_sequence row
    # Built once per batch of sequences (so once per table when a table's units share a batch) and
    # shared by every prior and cell: KD-trees of the ground-truth scans (see evaluate).
    cache: dict = field(default_factory=dict, repr=False, compare=False)
