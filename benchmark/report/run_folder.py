"""Reading a finished run folder: its table JSONs, its unit JSONs and their stored arrays."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

from benchmark.core.json_io import canonical_json
from benchmark.core.work_units import si_metric
from benchmark.data.unit_arrays import arrays_path

log = logging.getLogger(__name__)


@dataclass
class RunFolder:
    root: Path
    tables: list  # table JSONs (benchmark.run.table_derive.derive_table), sorted by name
    units: dict = field(default_factory=dict)  # table name -> (prior, cell key) -> [unit JSON, ...] (plan order)
    skipped: list = field(default_factory=list)  # (path, why) of files that could not be read

    def units_of(self, table: str, prior: str, cell: dict) -> list:
        return self.units.get(table, {}).get((prior, cell_key(cell)), [])

    def units_for(self, table: dict, prior: str, cell: dict, table_cell: dict) -> tuple[list, str | None]:
        """The stored units of a table's cell, or ([], why) where they are not the ones the table was
        derived from (a later run into the folder under other settings, stopped before it wrote its
        table): their observation fingerprints and per-sequence values must be the cell's."""
        from benchmark.run.table_derive import cell_fingerprint, sequence_values

        units = self.units_of(table["table"], prior, cell)
        if not units or table_cell.get("na_reason"):
            return units, None
        per_seq = table_cell.get("per_sequence") or {}
        stored = [row for u in units for row in (u.get("per_sequence") or [])]
        same = (cell_fingerprint(units) == table_cell.get("fingerprint")
                and [r.get("id") for r in stored] == list(per_seq.get("id") or []))
        for m in table.get("metrics") or []:
            values = per_seq.get(m["name"])
            if same and values is not None:
                same = all(a is not None and abs(a - b) <= 1e-9 * max(1.0, abs(b))
                           for a, b in zip(sequence_values(stored, m["name"]), values))
        if same:
            return units, None
        why = (f"the stored units of this cell ({', '.join(u['unit_id'] for u in units)}) are not the ones "
               f"{table.get('_file', 'the table')} was made from (another run into this folder since?); not shown")
        log.warning("report: %s, %s %s: %s", table["table"], prior, cell, why)
        return [], why

    def npz_path(self, unit: dict) -> Path:
        return arrays_path(self.root, unit["unit_id"])


def cell_key(cell: dict) -> str:
    return canonical_json({k: v for k, v in cell.items()})


def is_table(obj) -> bool:
    return isinstance(obj, dict) and {"table", "rows", "grid", "metrics"} <= set(obj)


def is_table_file(path: Path) -> bool:
    """Whether ``path`` is a readable JSON file holding a table."""
    try:
        return is_table(json.loads(path.read_text(encoding="utf-8")))
    except (OSError, ValueError):
        return False


def check_table_file(table: dict, path: Path) -> None:
    """Refuse a table JSON the report cannot show, naming the file, the field and the fix: the checks
    of ``compare`` (fields, format version, rows and cells), at least one metric, and every metric
    value (and its ``_std``) a finite number or null, its ``_ci95`` null or two numbers."""
    from benchmark.run.writers import cell_label
    from benchmark.tools.compare import cell_value, check_table

    check_table(table, str(path), with_writer="Make its report with the harness version that wrote it")
    if not table["metrics"]:
        raise ValueError(f"{path}: field 'metrics' is empty: a table names the metrics its cells hold; the file "
                         "was edited or written by another tool: rerun the table")
    for row in table["rows"]:
        for cell in row["cells"]:
            coords = {k: cell.get(k) for k in table["grid"]}
            where = f"{path}: prior {row['prior']!r}, cell {cell_label(coords, list(coords)) if coords else '(no grid)'}"
            for m in table["metrics"]:
                for name in (m["name"], f"{m['name']}_std"):
                    cell_value(cell, name, where)
                ci = cell.get(f"{m['name']}_ci95")
                if ci is not None and not (isinstance(ci, list) and len(ci) == 2 and all(
                        cell_value({"v": v}, "v", where)[2] for v in ci)):
                    raise ValueError(f"{where}: {m['name']}_ci95 is {ci!r:.60}, not [low, high] or null; the file "
                                     "was edited or written by another tool: rerun the table")


def no_table_error(root: Path) -> FileNotFoundError:
    return FileNotFoundError(
        f"report: {root} holds no table JSON (a <table>.json with fields table, rows, grid, metrics, written by "
        f"'python -m benchmark run TABLE --out {root}'); is this the run folder?")


def check_run_folder(path) -> Path:
    """``path`` as a run folder: an existing folder holding at least one table JSON. Raises
    FileNotFoundError naming the path and the fix (a file such as RUN/table1.json is named as such)."""
    root = Path(path)
    if root.is_file():
        raise FileNotFoundError(f"report: {root} is a file, not a run folder; pass the folder that holds it "
                                f"(python -m benchmark report {root.parent}), the --out of 'python -m benchmark run'")
    if not root.is_dir():
        raise FileNotFoundError(f"report: run folder {root} does not exist (give the --out folder of "
                                "'python -m benchmark run TABLE', default runs/latest)")
    files = [f for f in root.glob("*.json") if not f.name.startswith(".")]
    if not any(is_table_file(f) for f in files):
        damaged = []
        for f in files:
            try:
                json.loads(f.read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                damaged.append(f"{f.name} ({exc})")
        if damaged:
            raise ValueError(f"report: {root}: its JSON file(s) {', '.join(damaged)} cannot be read (truncated or "
                             "edited?); rerun the table into the folder (its units are reused) to write them again")
        raise no_table_error(root)
    return root


def load_run(path) -> RunFolder:
    """Read ``path``: every ``<table>.json`` at its top level and every ``units/*.json``.

    Raises FileNotFoundError naming the folder and the fix when there is no table JSON.
    """
    root = check_run_folder(path)
    tables, skipped = [], []
    for f in sorted(root.glob("*.json")):
        try:
            obj = json.loads(f.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            skipped.append((f, f"unreadable JSON ({exc})"))
            continue
        if is_table(obj):
            check_table_file(obj, f)
            obj["_file"] = f.name  # several tables (or profiles of one) may share a folder
            tables.append(obj)
    if not tables:
        raise no_table_error(root)
    units: dict = {}
    for f in sorted((root / "units").glob("*.json")):
        try:
            u = json.loads(f.read_text(encoding="utf-8"))
            table = (u.get("spec") or {}).get("table") or u["unit_id"].split("__")[0]
            key = (u["prior"], cell_key(u["cell"]))
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            skipped.append((f, f"not a unit result ({type(exc).__name__}: {exc})"))
            continue
        units.setdefault(table, {}).setdefault(key, []).append(u)
    for by_cell in units.values():
        for lst in by_cell.values():
            lst.sort(key=lambda u: u["unit_id"])
    for f, why in skipped:
        log.warning("report: skipping %s: %s", f, why)
    return RunFolder(root=root, tables=sorted(tables, key=lambda t: (t["table"], t["_file"])), units=units, skipped=skipped)


def sequence_rows(units: list, metrics: list) -> list[dict]:
    """Per-sequence means in reported units of ``metrics`` (names such as ``chamfer_mm``), with the
    unit id and any extra per-sequence fields the protocol stored (e.g. diagnostics)."""
    rows = []
    for u in units:
        for s in u.get("per_sequence") or []:
            frames = s.get("frames") or 0
            row = {"id": s.get("id"), "unit_id": u["unit_id"], "frames": frames}
            sums = s.get("sums") or {}
            for m in metrics:
                si, factor = si_metric(m)
                row[m] = sums[si] / frames * factor if si in sums and frames else (s.get(m) if m in s else None)
            row["extra"] = {k: v for k, v in s.items() if k not in ("id", "frames", "sums")}
            rows.append(row)
    return rows
