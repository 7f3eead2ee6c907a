"""Replacing some priors' rows of a table with a new run of those priors (:func:`replace_rows`).

When one prior's code or weights change, only its units are stale: the others measured the same
thing. A run of that prior alone under the same rules (profile, sequences, seed, grid, metrics) gives
its new row, and :func:`replace_rows` puts it into the table in place of the old one. What crosses
rows is derived again from the per-sequence values every row keeps: each cell's paired comparisons
against ``no-prior`` and against the cell's best prior (the best may change). The table's provenance
keeps its own run and lists, per replacement, the priors and the run they came from.

A new run under a larger step cap (the profile's ``steps``, the cap of the plateau rule) may replace
rows of a table made under a smaller one, where every fit of every kept row converged before that
cap and the protocol declares such fits cap-independent (:mod:`benchmark.run.cap_carry`): the kept
rows are then, value for value, what the larger cap computes. The table takes the new profile, and
its provenance records the raise.

Used by the quick regression (``BENCHMARK_REGENERATE_PRIORS``, tests/test_quick_tables.py) and by
``python -m benchmark merge-rows``.
"""

from __future__ import annotations

import copy
import itertools
import math
import re
from typing import Mapping

from benchmark.core.work_units import grid_axes, grid_cells
from benchmark.run.same_cells import copy_same_cells
from benchmark.run.table_derive import add_paired

# what must agree for two tables' rows to be measurements of one protocol on one test set
SAME = ("table", "protocol", "protocol_version", "profile", "profile_sizes", "seed", "sequences", "spec", "grid",
        "metrics", "data", "body", "format_version")


def replace_rows(base: Mapping, new: Mapping, source: str = "new", base_source: str = "base") -> dict:
    """``base`` with every row of ``new`` in place of its prior's row (a prior ``base`` lacks is
    appended), the paired comparisons and counts derived again. Refuses tables whose rules, profile,
    sequences, seed, grid, metrics, data or body differ, naming the field; ``source`` and
    ``base_source`` name the two tables in that message (their files)."""
    raise_cap = _cap_raise(base, new, source, base_source)
    for key in SAME:
        if key == "profile_sizes" and raise_cap:
            continue
        if base.get(key) != new.get(key):
            raise ValueError(f"{source}: field {key!r} differs from {base_source}'s ({_short(new.get(key))} against "
                             f"{_short(base.get(key))}): its rows measure something else; rerun those priors with "
                             f"{base_source}'s table, profile and seed")
    base, new = _cells_by_coordinates(base, base_source), _cells_by_coordinates(new, source, like=base)
    if not new["rows"]:
        raise ValueError(f"{source}: holds no row; give the table of a run of the priors whose rows to replace")
    replaced = [row["prior"] for row in new["rows"]]
    if len(set(replaced)) != len(replaced):
        raise ValueError(f"{source}: a prior has two rows: {replaced}")
    kept = [row for row in base["rows"] if row["prior"] not in replaced]
    if raise_cap:
        _check_kept_converged(kept, raise_cap, grid_axes(base), base_source)
    out = copy.deepcopy(dict(base))
    if raise_cap:
        out["profile_sizes"] = copy.deepcopy(new["profile_sizes"])
        out["profile_description"] = new.get("profile_description", out.get("profile_description"))
    differ = _fingerprints_that_differ(kept, new["rows"], grid_axes(base))
    by_prior = {row["prior"]: i for i, row in enumerate(out["rows"])}
    for row in new["rows"]:
        row = copy.deepcopy(row)
        if row["prior"] in by_prior:
            out["rows"][by_prior[row["prior"]]] = row
        else:
            out["rows"].append(row)
        out.setdefault("prior_info", {})[row["prior"]] = copy.deepcopy(new.get("prior_info", {}).get(row["prior"]))
    # the grid in its spec's order, as the rows' cells are (a table read back from JSON lists it sorted)
    cells = grid_cells({"grid": {k: out["grid"][k] for k in grid_axes(out)}})
    for row in out["rows"]:
        for cell in row["cells"]:
            cell.pop("paired", None)
    add_paired(out["rows"], cells, out["metrics"], out["seed"])
    copy_same_cells(out, out.get("same_cells") or [])  # a copied column stays its source's, comparisons included

    all_cells = [c for row in out["rows"] for c in row["cells"]]
    out["counts"] = {
        "units_planned": sum(c.get("units", 0) for c in all_cells),
        "units_done": sum(_units_done(c) for c in all_cells),
        "cells": len(all_cells),
        "cells_na": sum(1 for c in all_cells if c.get("na_reason")),
    }
    out["unit_devices"] = sorted(set(base.get("unit_devices") or []) | set(new.get("unit_devices") or []))
    provenance = out.setdefault("provenance", {})
    timings = provenance.setdefault("timings", {})
    timings["fit_s"] = math.fsum(c.get("fit_s", 0.0) for c in all_cells)
    timings["eval_s"] = math.fsum(c.get("eval_s", 0.0) for c in all_cells)
    timings.pop("wall_s", None)  # two runs: no one wall time
    provenance.setdefault("rows_replaced", []).append(
        {"priors": replaced, "observation_fingerprints_differ": differ,
         **({"step_cap_raised": {"from": raise_cap[0], "to": raise_cap[1], "rows_kept": [r["prior"] for r in kept]}}
            if raise_cap else {}),
         "provenance": {k: v for k, v in (new.get("provenance") or {}).items() if k != "rows_replaced"}})
    return out


def _cells_by_coordinates(table: Mapping, source: str, like: Mapping | None = None) -> dict:
    """A copy of ``table`` whose every row holds one cell per grid cell, in the order of the first
    row of ``like`` (or of its own): rows are matched cell by cell by their coordinates, never by
    position. A row that is not a table row, lacks a cell, repeats one or has one off the grid is
    refused, naming ``source``, the prior and the cell."""
    table = copy.deepcopy(dict(table))
    rows = table["rows"]
    for i, row in enumerate(rows):
        if not isinstance(row, Mapping) or not isinstance(row.get("prior"), str) or not isinstance(row.get("cells"), list) \
                or not all(isinstance(c, Mapping) for c in row["cells"]):
            raise ValueError(f"{source}: row {i} is not a table row (a 'prior' name and a list of 'cells'); give a "
                             "table JSON written by `python -m benchmark run`")
    ref = like if like is not None else table
    if not ref["rows"]:
        return table
    axes = list(ref["grid"]) if isinstance(ref.get("grid"), Mapping) else []
    order = [tuple(c.get(k) for k in axes) for c in ref["rows"][0]["cells"]]
    grid = [tuple(c) for c in itertools.product(*(ref["grid"][k] for k in axes))] if axes else []
    if not axes or sorted(map(repr, order)) != sorted(map(repr, grid)):
        raise ValueError(f"{source}: the cells of its first row are not the grid {ref.get('grid')!r}, "
                         "cell for cell; give a table JSON written by `python -m benchmark run`")
    names = [m.get("name") for m in table.get("metrics") or [] if isinstance(m, Mapping)]
    for row in rows:
        by = {}
        for cell in row["cells"]:
            key = tuple(cell.get(k) for k in axes)
            for name in names:
                v = cell.get(name)
                if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)):
                    raise ValueError(f"{source}: row {row['prior']!r}, cell {dict(zip(axes, key))}: {name} is {v!r:.40}, "
                                     "not a finite number; give a table JSON written by `python -m benchmark run`")
            if key in by:
                raise ValueError(f"{source}: row {row['prior']!r} holds the cell {dict(zip(axes, key))} twice")
            by[key] = cell
        if set(by) != set(order):
            wrong = [dict(zip(axes, k)) for k in order if k not in by] or [dict(zip(axes, k)) for k in by if k not in order]
            raise ValueError(f"{source}: row {row['prior']!r} does not hold the grid's cells (e.g. {wrong[0]}); "
                             "give a table JSON written by `python -m benchmark run` for the same table")
        row["cells"] = [by[k] for k in order]
    return table


def _cap_raise(base: Mapping, new: Mapping, source: str, base_source: str) -> tuple[int, int] | None:
    """(old cap, new cap) where ``new`` differs from ``base`` in its profile's step cap alone and
    the cap rose under rules whose converged fits do not depend on it; else None (the sizes must
    then agree)."""
    old, now = dict(base.get("profile_sizes") or {}), dict(new.get("profile_sizes") or {})
    if old == now or old.pop("steps", None) is None or {k: v for k, v in now.items() if k != "steps"} != old:
        return None
    a, b = base["profile_sizes"]["steps"], now.get("steps")
    if not isinstance(b, int) or b <= a:
        return None
    from benchmark.protocols.registry import make_protocol

    try:
        problem = make_protocol(base.get("protocol")).carry_problem(base.get("spec") or {})
    except KeyError as exc:
        problem = str(exc)
    if problem:
        raise ValueError(f"{source}: its step cap rose ({a} -> {b} steps) but {base_source}'s rows cannot stand for "
                         f"the larger cap: {problem}; rerun every row under the new profile")
    return a, b


def _check_kept_converged(kept: list, cap: tuple[int, int], axes, base_source: str) -> None:
    """Refuse a cap raise when a kept row has a cell with a fit that did not converge (it would go on)."""
    open_cells = [f"{row['prior']} {', '.join(f'{k}={cell[k]}' for k in axes)} ({cell['diagnostics'].get('not_converged')} of "
                  f"{cell['diagnostics'].get('sequences')})"
                  for row in kept for cell in row["cells"]
                  if not cell.get("na_reason") and (cell.get("diagnostics") or {}).get("not_converged", 1) != 0]
    if open_cells:
        raise ValueError(f"{base_source}: the step cap rose ({cap[0]} -> {cap[1]} steps), but the kept rows have fits "
                         f"that did not converge within {cap[0]} steps, which the larger cap would carry on: "
                         f"{', '.join(open_cells[:6])}; rerun those priors under the new profile too")


def _fingerprints_that_differ(kept: list, new_rows: list, grid_keys) -> list[dict]:
    """The cells (prior and grid coordinates) where a new row's observation fingerprint differs from
    the kept rows': an exact hash of float coordinates, which another build of the body's cache
    (another machine: Anny's differ by up to 4.5e-8 m) changes while the observation is the same to
    0.1 micrometre. Recorded, not refused: the metrics, and ``fit-check --robustness``'s 1e-6 m
    probe for the prior, say whether such a difference can move its numbers."""
    seen: dict[int, set] = {}
    for row in kept:
        for j, cell in enumerate(row["cells"]):
            if cell.get("fingerprint"):
                seen.setdefault(j, set()).add(cell["fingerprint"])
    return [{"prior": row["prior"], **{k: cell.get(k) for k in grid_keys}}
            for row in new_rows for j, cell in enumerate(row["cells"])
            if cell.get("fingerprint") and seen.get(j) and cell["fingerprint"] not in seen[j]]


def _units_done(cell: Mapping) -> int:
    """How many of a cell's units had results (its ``na_reason`` says so when some had none)."""
    match = re.match(r"incomplete: (\d+) of \d+ units", str(cell.get("na_reason") or ""))
    return int(match.group(1)) if match else int(cell.get("units", 0))


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."
