"""The inputs of a completion work unit; shared by the synthetic
(:mod:`benchmark.protocols.completion_unit`) and captured-scan
(:mod:`benchmark.protocols.scan_completion`) data sources, which import it and not each other (the
seeds derived from a unit's coordinates: :func:`benchmark.core.work_units.stable_seed`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from benchmark.core.work_units import spec_source, stable_seed


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


SEED_RULES = ("batch", "sequence")  # data.seeds: what a synthetic capture's and a cell's random draws are seeded by


def seed_rule(table_spec: dict) -> str:
    """The spec's ``data.seeds`` (default ``batch``): ``batch``, the capture, the ground-truth scan
    and each cell's point subset of a unit drawn from seeds of its whole batch of sequences
    (table1 versions 1-8: a sequence's observation depends on the sequences it is batched with);
    ``sequence``, each sequence from seeds of its own id (the same observation whatever the batch
    size or the sequences beside it)."""
    rule = (table_spec.get("data") or {}).get("seeds", "batch")
    if rule not in SEED_RULES:
        raise ValueError(f"{spec_source(table_spec)}: field 'data.seeds' must be one of {', '.join(SEED_RULES)}; got "
                         f"{rule!r} ('sequence': each sequence's draws seeded by its own id; 'batch': by its unit's "
                         "sequences, the rule of table1 versions 1-8)")
    return rule


def unit_seeds(kind: str, seed: int, sequence_ids, *parts, rule: str = "batch"):
    """The seed of a unit's ``kind`` of draw (``capture``, ``gt-scan``, ``degrade``): under
    :func:`seed_rule` ``batch`` one int from the unit's sequences, under ``sequence`` a list of one
    int per sequence from its own id."""
    if rule == "sequence":
        return [stable_seed(kind, seed, *parts, sid) for sid in sequence_ids]
    return stable_seed(kind, seed, *parts, *sequence_ids)


def cell_degrade_seed(seed: int, points, fps, sequence_ids, rule: str = "batch"):
    """The seed of a cell's degradation of these sequences (the table seed, the cell as the grid
    writes it, the sequences; never the prior: every prior of a cell sees one observation); a list
    of one per sequence under the :func:`seed_rule` ``sequence``."""
    return unit_seeds("degrade", seed, sequence_ids, points, fps, rule=rule)
