"""Compare two table JSONs cell by cell, metric by metric, with tolerances in the metric's unit.

``python -m benchmark compare A.json B.json --tol chamfer_mm=0.5`` calls :func:`main_compare`.
A difference is ``B - A``. The comparison fails (exit status 1) when any compared number is out of
tolerance, a cell or metric is present in one table and not the other, a cell is ``n/a`` in one and
a number in the other, or the tables differ in what they measure (table, protocol version,
profile). Differences in seed, device, profile sizes or test sequences, and cells whose input fingerprint changed
("the input changed", as opposed to "the model changed"), are reported but do not fail by themselves.

Default tolerances: the table's own for a metric (its spec's ``tolerance``), else by the unit
suffix of the metric name (:data:`DEFAULT_TOLERANCES`; ``*_mm``: 0.5 mm). A metric the table marks
``timing: true`` (a measured time) is reported, never failing, unless ``--tol`` names it.
``*_std`` companions are compared only when a tolerance names them. A metric with no default and
no ``--tol`` fails with a message saying how to give one.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Mapping, Sequence, TextIO

from benchmark.core.json_io import canonical_json
from benchmark.core.work_units import TABLE_FORMAT_VERSION, grid_axes
from benchmark.run.writers import cell_label

# unit suffix -> default tolerance, in that unit
DEFAULT_TOLERANCES = {"_mm": 0.5, "_cm": 0.05, "_m": 0.0005, "_deg": 0.5, "_rad": 0.01, "_mps2": 0.05}
# table fields that must agree for the numbers to be comparable
MUST_MATCH = ("table", "protocol_version", "profile")
# table fields whose difference is reported as a note
NOTE_IF_DIFFERENT = ("seed", "device", "profile_sizes", "data")
TABLE_FIELDS = ("table", "protocol_version", "profile", "grid", "metrics", "rows")
KNOWN_FORMAT_VERSIONS = frozenset({TABLE_FORMAT_VERSION})
FAILING = {"out of tolerance", "missing in A", "missing in B", "n/a mismatch", "no tolerance", "mismatch"}


def default_tolerance(metric: str) -> float | None:
    """The default tolerance of a metric (by its unit suffix); None for ``*_std`` and unknown units."""
    if metric.endswith("_std"):
        return None
    for suffix, tol in DEFAULT_TOLERANCES.items():
        if metric.endswith(suffix):
            return tol
    return None


def parse_tolerances(tol_args: Sequence[str] | None) -> dict[str, float]:
    """``["chamfer_mm=0.5", ...]`` -> ``{"chamfer_mm": 0.5}``. Raises ValueError on a malformed,
    negative, non-finite or repeated entry, naming it."""
    out: dict[str, float] = {}
    for arg in tol_args or []:
        name, sep, value = str(arg).partition("=")
        name, value = name.strip(), value.strip()
        hint = "expected METRIC=VALUE with VALUE in the metric's unit, e.g. --tol chamfer_mm=0.5"
        if not sep or not name or not value:
            raise ValueError(f"bad --tol {arg!r}: {hint}")
        try:
            tol = float(value)
        except ValueError:
            raise ValueError(f"bad --tol {arg!r}: {value!r} is not a number; {hint}") from None
        if not math.isfinite(tol) or tol < 0:
            raise ValueError(f"bad --tol {arg!r}: the tolerance must be a finite number >= 0")
        if name in out:
            raise ValueError(f"bad --tol {arg!r}: {name!r} is given twice")
        out[name] = tol
    return out


COMPARE_WITH_WRITER = "Compare it with the harness version that wrote it"


def check_table(table, label: str, with_writer: str = COMPARE_WITH_WRITER) -> None:
    """Refuse what is not a table JSON this version can read, naming the file and the field.
    ``with_writer``: the first fix for a format version this harness does not read, in the words of
    the command that reads the table (``report``: make the report with the harness that wrote it)."""
    if not isinstance(table, Mapping):
        raise ValueError(f"{label}: not a table JSON (expected an object)")
    missing = [k for k in TABLE_FIELDS if k not in table]
    if missing:
        raise ValueError(f"{label}: not a table JSON, field(s) {missing} missing (write it with `python -m benchmark run`)")
    version = table.get("format_version")
    if version is not None and (not isinstance(version, int) or isinstance(version, bool) or version not in KNOWN_FORMAT_VERSIONS):
        raise ValueError(f"{label}: field 'format_version' is {version!r}; this harness reads table format version(s) "
                         f"{sorted(KNOWN_FORMAT_VERSIONS)}. {with_writer}, or rerun the table with this one")
    if not isinstance(table["grid"], Mapping) or not all(isinstance(v, list) for v in table["grid"].values()):
        raise ValueError(f"{label}: field 'grid' must be an object (axis -> list of values), got {table['grid']!r:.80}")
    if not isinstance(table["metrics"], list) or not all(isinstance(m, Mapping) and isinstance(m.get("name"), str)
                                                         for m in table["metrics"]):
        raise ValueError(f"{label}: field 'metrics' must be a list of objects with a 'name'")
    if not isinstance(table["rows"], list):
        raise ValueError(f"{label}: field 'rows' must be a list of rows")
    seen = set()
    for i, row in enumerate(table["rows"]):
        if not isinstance(row, Mapping) or not isinstance(row.get("prior"), str) or not isinstance(row.get("cells"), list):
            raise ValueError(f"{label}: rows[{i}] must be an object with 'prior' (a string) and 'cells' (a list)")
        if row["prior"] in seen:
            raise ValueError(f"{label}: rows[{i}]: prior {row['prior']!r} has two rows; a table holds one row per prior "
                             "(the file was edited or written by another tool: rerun the table)")
        seen.add(row["prior"])
        cells = set()
        for j, cell in enumerate(row["cells"]):
            if not isinstance(cell, Mapping):
                raise ValueError(f"{label}: rows[{i}] ({row['prior']}) cells[{j}] must be an object")
            key = canonical_json({k: cell.get(k) for k in table["grid"]})
            if key in cells:
                raise ValueError(f"{label}: rows[{i}] ({row['prior']}) cells[{j}] repeats the cell {key}")
            cells.add(key)


def _index(table: Mapping) -> dict[tuple[str, str], tuple[dict, Mapping]]:
    keys = grid_axes(table)
    out = {}
    for row in table["rows"]:
        for cell in row["cells"]:
            coords = {k: cell.get(k) for k in keys}
            out[(row["prior"], canonical_json(coords))] = (coords, cell)
    return out


def cell_value(cell: Mapping, metric: str, where: str = "") -> tuple[float | None, str | None, bool]:
    """(value, n/a reason, metric present in the cell). A value that is not a finite number
    raises ValueError naming ``where`` (file, prior, cell) and the metric."""
    if cell.get("na_reason"):
        return None, cell["na_reason"], True
    if metric not in cell:
        return None, None, False
    if cell[metric] is None:
        base = metric[:-4] if metric.endswith("_std") else metric
        na = cell.get("metric_na")
        return None, (na.get(base, "no value") if isinstance(na, Mapping) else "no value"), True
    value = cell[metric]
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > 1e300:
        value = float("inf")  # an integer no float holds: not finite either
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{where}: metric {metric!r} is {value!r}, not a finite number (or null with its reason in "
                         "'metric_na'); the file was edited or written by another tool: rerun the table")
    return float(value), None, True


def compare_tables(a: Mapping, b: Mapping, tolerances: Mapping[str, float] | None = None,
                   labels: tuple[str, str] = ("A", "B")) -> tuple[bool, list[dict]]:
    """Compare table JSONs ``a`` (reference) and ``b`` (new).

    tolerances: metric name -> largest allowed ``|b - a|`` in the metric's unit; metrics not named
        use :func:`default_tolerance`; a ``<metric>_std`` is compared only when named here.

    Returns ``(ok, rows)``. Each row is a dict with ``kind`` (``"header"`` or ``"cell"``),
    ``status`` (``ok``, ``both n/a``, ``out of tolerance``, ``missing in A``, ``missing in B``,
    ``n/a mismatch``, ``no tolerance``, ``mismatch``, ``note``) and ``ok``; header rows carry
    ``field``, ``a``, ``b``; cell rows carry ``prior``, ``cell`` (grid coordinates), ``metric``, ``a``,
    ``b``, ``diff`` (b - a), ``tol``, ``input`` (``same`` / ``changed`` / None: the cells' input
    fingerprints) and ``note`` (n/a reasons).
    """
    check_table(a, labels[0])
    check_table(b, labels[1])
    tolerances = dict(tolerances or {})
    rows: list[dict] = []
    for field in MUST_MATCH:
        if a.get(field) != b.get(field):
            rows.append({"kind": "header", "field": field, "a": a.get(field), "b": b.get(field), "status": "mismatch", "ok": False})
    for field in NOTE_IF_DIFFERENT:
        if a.get(field) != b.get(field):
            rows.append({"kind": "header", "field": field, "a": a.get(field), "b": b.get(field), "status": "note", "ok": True})
    seq_a, seq_b = _sequence_ids(a), _sequence_ids(b)
    if seq_a is not None and seq_b is not None and seq_a != seq_b:  # another test set: its cells average other sequences
        rows.append({"kind": "header", "field": "sequences", "a": _sequences_text(seq_a, seq_b, "B"),
                     "b": _sequences_text(seq_b, seq_a, "A"), "status": "note", "ok": True})

    names = list(dict.fromkeys([m["name"] for m in a["metrics"]] + [m["name"] for m in b["metrics"]]))
    known = set(names) | {f"{n}_std" for n in names}
    unknown = sorted(set(tolerances) - known)
    if unknown:
        raise ValueError(f"--tol names unknown metric(s) {unknown}; the tables have: {', '.join(sorted(known))}")
    specs = {m["name"]: m for m in list(b["metrics"]) + list(a["metrics"])}  # A's entry wins
    timings = {n for n, m in specs.items() if m.get("timing")}
    compared = []
    for name in names:
        compared.append((name, tolerances.get(name, specs[name].get("tolerance", default_tolerance(name)))))
        if f"{name}_std" in tolerances:
            compared.append((f"{name}_std", tolerances[f"{name}_std"]))

    ia, ib = _index(a), _index(b)
    for key in list(dict.fromkeys(list(ia) + list(ib))):
        prior = key[0]
        coords = (ia.get(key) or ib.get(key))[0]
        ca = ia[key][1] if key in ia else None
        cb = ib[key][1] if key in ib else None
        fa, fb = (ca or {}).get("fingerprint"), (cb or {}).get("fingerprint")
        input_state = None if not (fa and fb) else ("same" if fa == fb else "changed")
        for metric, tol in compared:
            row = {"kind": "cell", "prior": prior, "cell": coords, "metric": metric, "a": None, "b": None,
                   "diff": None, "tol": tol, "input": input_state, "note": None}
            if ca is None or cb is None:
                row["status"] = "missing in B" if cb is None else "missing in A"
                rows.append(row)
                continue
            where = cell_label(coords, list(coords)) if coords else "(no grid)"
            va, ra, pa = cell_value(ca, metric, f"{labels[0]}: prior {prior!r}, cell {where}")
            vb, rb, pb = cell_value(cb, metric, f"{labels[1]}: prior {prior!r}, cell {where}")
            row["a"], row["b"] = va, vb
            if not pa or not pb:
                row["status"] = "missing in A" if not pa else "missing in B"
            elif va is None and vb is None:
                row["status"], row["note"] = "both n/a", ra if ra == rb else f"A: {ra}; B: {rb}"
            elif va is None or vb is None:
                row["status"], row["note"] = "n/a mismatch", f"A: {ra}" if va is None else f"B: {rb}"
            else:
                row["diff"] = vb - va
                if metric in timings and metric not in tolerances:  # a measured time: reported, never failing
                    row["status"], row["note"] = "note", "a measured time (timing: true); --tol NAME=VALUE compares it"
                elif tol is None:
                    row["status"] = "no tolerance"
                    row["note"] = f"no default tolerance for {metric!r}; pass --tol {metric}=VALUE (in its unit)"
                else:
                    # a hair of slack so that a difference equal to the tolerance passes despite rounding
                    row["status"] = "ok" if abs(row["diff"]) <= tol + 1e-9 * max(1.0, abs(va), abs(vb)) else "out of tolerance"
            rows.append(row)
    for row in rows:
        row.setdefault("ok", row["status"] not in FAILING)
    return all(r["ok"] for r in rows), rows


def _sequence_ids(table: Mapping) -> set[str] | None:
    """The test sequences a table ran: its ``sequences``, else those its cells' ``per_sequence`` name."""
    if isinstance(table.get("sequences"), list):
        return set(map(str, table["sequences"]))
    ids = {str(i) for row in table["rows"] for c in row["cells"] if isinstance(c, Mapping)
           for i in ((c.get("per_sequence") or {}).get("id") or [])}
    return ids or None


def _sequences_text(mine: set, other: set, other_label: str) -> str:
    only = sorted(mine - other)
    return (f"{len(mine)} sequences, {len(only)} not in {other_label}"
            + (f" ({', '.join(only[:3])}{', ...' if len(only) > 3 else ''})" if only else ""))


def _fmt(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.3f}"
    return str(v)


def format_report(ok: bool, rows: Sequence[Mapping], label_a: str = "A", label_b: str = "B", only_problems: bool = False) -> str:
    """The comparison as plain text: table-level differences, then one line per cell x metric
    (``only_problems``: only failing lines), then a summary line."""
    lines = [f"A = {label_a}", f"B = {label_b}", ""]
    header = [r for r in rows if r["kind"] == "header"]
    for r in header:
        tag = "FAIL" if not r["ok"] else "note"
        lines.append(f"{tag}  {r['field']} differs: A {r['a']!r}, B {r['b']!r}")
    if header:
        lines.append("")
    cells = [r for r in rows if r["kind"] == "cell" and (r["ok"] is False or not only_problems)]
    if cells:
        table = [("", "prior", "cell", "metric", "A", "B", "B-A", "tol", "input", "status")]
        for r in cells:
            label = cell_label(r["cell"], list(r["cell"])) if r["cell"] else ""
            status = r["status"] + (f" ({r['note']})" if r["note"] else "")
            table.append(("ok" if r["ok"] else "FAIL", r["prior"], label, r["metric"], _fmt(r["a"]), _fmt(r["b"]),
                          "n/a" if r["diff"] is None else f"{r['diff']:+.3f}", _fmt(r["tol"]), r["input"] or "?", status))
        widths = [max(len(str(t[i])) for t in table) for i in range(len(table[0]) - 1)]
        for t in table:
            lines.append("  ".join(str(x).ljust(w) for x, w in zip(t, widths)) + "  " + t[-1])
        lines.append("")
    cell_rows = [r for r in rows if r["kind"] == "cell"]
    failing = [r for r in rows if not r["ok"]]
    changed = len({(r["prior"], canonical_json(r["cell"])) for r in cell_rows if r["input"] == "changed"})
    lines.append(f"{'OK' if ok else 'FAIL'}: {len(cell_rows)} cell x metric comparisons, {len(failing)} failing"
                 + (f"; {changed} cell(s) saw a different input (fingerprint changed)" if changed else ""))
    return "\n".join(lines) + "\n"


def load_table_json(path: str | Path) -> dict:
    """Read a table JSON, with errors that name the file."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; give the table JSON in it (e.g. {path / 'table1.json'})")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such table JSON")
    try:
        table = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    except OSError as exc:
        raise ValueError(f"{path}: cannot read it ({exc.strerror or exc})") from None
    check_table(table, str(path))
    return table


def only_priors(table: Mapping, priors: Sequence[str], label: str) -> dict:
    """``table`` with only the rows of ``priors`` (``compare --prior``); a prior the table has no row
    of raises ValueError naming the file and the rows it has."""
    have = [r["prior"] for r in table["rows"]]
    missing = [p for p in priors if p not in have]
    if missing:
        raise ValueError(f"{label}: no row for --prior {', '.join(missing)}; its rows: {', '.join(have)}")
    return {**table, "rows": [r for r in table["rows"] if r["prior"] in priors]}


def main_compare(path_a: str | Path, path_b: str | Path, tol_args: Sequence[str] | None = None,
                 out: TextIO | None = None, only_problems: bool = False, priors: Sequence[str] | None = None) -> int:
    """``compare`` command: print the report; return 0 when everything is within tolerance, 1
    otherwise. Bad ``--tol`` strings or unreadable files raise ValueError / FileNotFoundError with
    a message that names them. ``priors``: compare only those rows (each must be in both tables),
    e.g. a run of one prior against a whole reference table."""
    tolerances = parse_tolerances(tol_args)
    a, b = load_table_json(path_a), load_table_json(path_b)
    if priors:
        a, b = only_priors(a, priors, str(path_a)), only_priors(b, priors, str(path_b))
    ok, rows = compare_tables(a, b, tolerances, labels=(str(path_a), str(path_b)))
    print(format_report(ok, rows, str(path_a), str(path_b), only_problems=only_problems), end="", file=out or sys.stdout)
    return 0 if ok else 1
