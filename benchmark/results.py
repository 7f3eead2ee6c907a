"""Work units, their stored results, and the table derived from them.

A table run is split into independent *work units*: one prior x one grid cell x one batch of
sequences (:class:`WorkUnit`, planned by :func:`plan_units`). Each unit is fitted and evaluated by
the protocol (an ``execute(unit) -> dict`` callable that the caller provides) and its result is
stored as one JSON file per unit (:mod:`benchmark.runner` writes them). The public table is
*derived* from those per-sequence rows (:func:`derive_table`), never accumulated by hand.

Unit-result dict (what ``execute`` returns; validated by :func:`validate_unit_result`)::

    {"unit_id": str, "spec_hash": str, "prior": str, "cell": {...}, "sequence_ids": [str],
     "fingerprint": str,                 # hash of the degraded observation this unit saw
     "per_sequence": [{"id": str, "frames": int,
                       "sums": {"chamfer_m": float, "chamfer_surface_m": float, "mpjpe_m": float}}],
     "timings": {"fit_s": float, "eval_s": float},
     "device": str,
     "na_reason": None | str}            # a unit whose prior cannot serve the cell: reason, no rows

Metric sums are SI (metres) summed over the output frames of one sequence, so merging is
addition: the mean over all frames of all sequences is ``total sum / total frames``. This module
is the one place that converts to reported units (``chamfer_m`` -> ``chamfer_mm``).
"""

# The code lives in benchmark.work_units (hashing, atomic files, spec helpers, planning, unit results)
# and benchmark.table_derive (the table); this module re-exports their names.

import os as _os

from benchmark.table_derive import (
    STD_DEFINITION,
    derive_table,
)
from benchmark.work_units import (
    CHECKSUM_KEY,
    NON_RULE_KEYS,
    NON_SIZE_PROFILE_KEYS,
    RESULT_KEYS,
    TABLE_FORMAT_VERSION,
    UNIT_CONVERSIONS,
    WorkUnit,
    atomic_write_json,
    atomic_write_text,
    canonical_json,
    checksum_problem,
    derive_seed,
    grid_cells,
    load_unit_results,
    make_unit_id,
    metric_specs,
    plan_units,
    profile_sizes,
    sha256_json,
    si_metric,
    spec_source,
    table_rules,
    unit_checksum,
    unit_path,
    validate_unit_result,
    with_checksum,
)

# Kept as an attribute: callers and tests patch results.os.fsync (the one shared os module).
os = _os

__all__ = [
    "CHECKSUM_KEY",
    "NON_RULE_KEYS",
    "NON_SIZE_PROFILE_KEYS",
    "RESULT_KEYS",
    "STD_DEFINITION",
    "TABLE_FORMAT_VERSION",
    "UNIT_CONVERSIONS",
    "WorkUnit",
    "atomic_write_json",
    "atomic_write_text",
    "canonical_json",
    "checksum_problem",
    "derive_seed",
    "derive_table",
    "grid_cells",
    "load_unit_results",
    "make_unit_id",
    "metric_specs",
    "plan_units",
    "profile_sizes",
    "sha256_json",
    "si_metric",
    "spec_source",
    "table_rules",
    "unit_checksum",
    "unit_path",
    "validate_unit_result",
    "with_checksum",
]
