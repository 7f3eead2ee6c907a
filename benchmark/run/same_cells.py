"""Columns that are another cell's observation, shown under their own name but fitted once (``same_cells``).

A paper's table can list one setting twice. sls (paper 001, Table 1) has two sweeps that meet at
one end: ``p10000`` (10,000 points per scan at all 100 anchors) and ``f100`` (all points at all 100
anchors), and a scan holds 10,000 points. Both are the same observation, point for point in the
same order, and the fit draws nothing from its seed, so fitting both computes one result twice
(the version 3 quick table: all 7 rows equal to the last bit).

A spec lists such a column under ``same_cells`` (a presentation key: it enters no unit's hash)::

    same_cells:
      - {cell: {sweep: f100}, as: {sweep: p10000}, why: "..."}

and leaves it out of ``grid``. No unit is planned for it. The derived table puts a copy of the
``as`` cell in every row under the column's own coordinates, after the other cells, with
``same_as`` naming the cell it copies, no units and no fit time, and the tables say so. The protocol checks that the two are the same
observation (sls: :func:`benchmark.protocols.sls_data.check_same_cells`). Only a grid of one axis
can hold such a column.
"""

from __future__ import annotations

import copy
from typing import Mapping


def same_cells(spec: Mapping) -> list[dict]:
    """The spec's ``same_cells``, checked: ``[{"cell": {...}, "as": {...}, "why": str}]``."""
    entries = spec.get("same_cells") or []
    src = spec.get("_source") or f"benchmark/tables/{spec.get('name', '?')}.yaml"
    grid = dict(spec.get("grid") or {})
    if entries and len(grid) != 1:
        raise ValueError(f"{src}: field 'same_cells' needs a grid of one axis (this grid has {sorted(grid)})")
    out = []
    for i, e in enumerate(entries):
        if not isinstance(e, Mapping) or not isinstance(e.get("cell"), Mapping) or not isinstance(e.get("as"), Mapping):
            raise ValueError(f"{src}: same_cells[{i}] must be {{cell: {{AXIS: VALUE}}, as: {{AXIS: VALUE}}, why: TEXT}}")
        axis = next(iter(grid))
        if set(e["cell"]) != {axis} or set(e["as"]) != {axis}:
            raise ValueError(f"{src}: same_cells[{i}] must name the grid's axis {axis!r} in 'cell' and 'as'")
        if e["cell"][axis] in grid[axis]:
            raise ValueError(f"{src}: same_cells[{i}]: {e['cell'][axis]!r} is also in grid.{axis}: it would be fitted "
                             "as well; remove it from the grid")
        out.append({"cell": dict(e["cell"]), "as": dict(e["as"]), "why": str(e.get("why", ""))})
    return out


def copy_same_cells(table: dict, entries: list[dict]) -> None:
    """Put (or refresh) each entry's column in ``table``: its grid axis lists it, and every row holds
    a copy of its ``as`` cell under its coordinates (``same_as``, no units, no fit time). An entry
    whose ``as`` cell the table lacks (a grid restricted by a test or a profile) is left out."""
    kept = []
    for e in entries:
        (axis, value), = e["cell"].items()
        target = e["as"][axis]
        if not any(c.get(axis) == target for row in table["rows"] for c in row["cells"]):
            continue
        kept.append(e)
        if value not in table["grid"][axis]:
            table["grid"][axis].append(value)
        for row in table["rows"]:
            row["cells"] = [c for c in row["cells"] if c.get(axis) != value]
            source = next((c for c in row["cells"] if c.get(axis) == target), None)
            if source is None:
                continue
            cell = copy.deepcopy(source)
            cell[axis] = value
            cell["same_as"] = dict(e["as"])
            cell["units"] = 0
            cell.pop("fit_s", None)
            cell.pop("eval_s", None)
            row["cells"].append(cell)
    if kept:
        table["same_cells"] = kept
    else:
        table.pop("same_cells", None)
