"""The CSV form of a derived table (:func:`format_csv`; :mod:`benchmark.run.writers` writes it):
long format, one line per prior x cell x metric, with its interval and paired comparisons."""

from __future__ import annotations

import csv
import io
from typing import Mapping

from benchmark.core.work_units import grid_axes
from benchmark.run.table_derive import best_prior, cell_reason, metric_unit, ranked_cells


PAIRED_ROLES = {"no_prior": "vs_no_prior", "best": "vs_best"}  # cell["paired"][metric] key -> CSV column prefix
_PAIRED_FIELDS = ("diff", "ci95_lo", "ci95_hi", "significant", "better")


def _csv_number(value) -> str:
    return "" if value is None else repr(float(value))


def _csv_flag(value) -> str:
    return "" if value is None else str(bool(value)).lower()


def _paired_columns(cell: Mapping, metric: str, role: str) -> list[str]:
    c = ((cell.get("paired") or {}).get(metric) or {}).get(role)
    if not c:
        return [""] * len(_PAIRED_FIELDS)
    lo, hi = c["ci95"] if c.get("ci95") is not None else (None, None)
    return [_csv_number(c["diff"]), _csv_number(lo), _csv_number(hi), _csv_flag(c.get("significant")),
            _csv_flag(c.get("better"))]


def format_csv(table: Mapping) -> str:
    """Long format: one line per prior x cell x metric (``value``, ``std``, ``ci95_lo``,
    ``ci95_hi`` in ``unit``), then the paired comparisons: ``vs_no_prior_*`` (against no-prior),
    ``best_prior`` (the cell's best prior by the metric's mean) and ``vs_best_*`` (against it): the
    mean difference this prior minus the other, its interval, ``significant`` (the interval
    excludes 0) and ``better`` (``true`` / ``false``). Empty where it does not apply."""
    grid_keys = grid_axes(table)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["table", "protocol_version", "profile", "prior", *grid_keys, "metric", "unit", "value", "std",
                     "sequences", "frames", "na_reason", "ci95_lo", "ci95_hi",
                     *(f"vs_no_prior_{f}" for f in _PAIRED_FIELDS), "best_prior", *(f"vs_best_{f}" for f in _PAIRED_FIELDS)])
    best = _best_priors(table)
    for row in table["rows"]:
        for j, cell in enumerate(row["cells"]):
            for metric in table["metrics"]:
                name = metric["name"]
                reason = cell_reason(cell, name)
                value = "" if reason is not None else repr(float(cell[name]))
                std = cell.get(f"{name}_std")
                ci = cell.get(f"{name}_ci95") if reason is None else None
                writer.writerow([table["table"], table["protocol_version"], table["profile"], row["prior"],
                                 *(cell[k] for k in grid_keys), name, (metric_unit(name) or "").replace("mps2", "m/s^2"), value,
                                 "" if reason is not None or std is None else repr(float(std)),
                                 cell.get("sequences", ""), cell.get("frames", ""), reason or "",
                                 *((_csv_number(ci[0]), _csv_number(ci[1])) if ci is not None else ("", "")),
                                 *_paired_columns(cell, name, "no_prior"), best.get((j, name), ""),
                                 *_paired_columns(cell, name, "best")])
    return buf.getvalue()


def _best_priors(table: Mapping) -> dict[tuple[int, str], str]:
    """(cell index, metric) -> the cell's best prior by the rule of the paired comparisons
    (:func:`benchmark.run.table_derive.best_prior`), whether or not a comparison against it was
    made (cells seen on another observation are not paired); empty for a table derived before them."""
    out = {}
    rows = table["rows"]
    for j in range(len(rows[0]["cells"]) if rows else 0):
        for metric in table["metrics"]:
            best = best_prior(ranked_cells(rows, j, metric), metric)
            if best is not None:
                out[(j, metric["name"])] = best
    return out
