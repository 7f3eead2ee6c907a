"""Write a derived table (the JSON of :func:`benchmark.run.table_derive.derive_table`) as files people read.

- ``<stem>.json``: the table itself (atomic write).
- ``<stem>.md``: Markdown: a header (title, profile, protocol version, device, seed, revision), one
  table per metric (headline first), one row per prior and one column per grid cell, mean ± std;
  ``n/a`` cells carry a footnote with their reason; the paper's own numbers, where the spec has
  them, are added as separate, labelled rows.
- ``<stem>.csv``: long format, one line per prior x cell x metric.
- ``<stem>.tex``: a booktabs ``tabular`` of the headline metric.

Numbers arrive already in reported units (the derivation converted them); nothing here rescales.
"""

from __future__ import annotations

import csv
import io
import logging
import os
from pathlib import Path
from typing import Mapping, Sequence

from benchmark.core.fit_diagnostics import (BACKWARDS_DEG, CONVERGED_MAX_DECREASE, CONVERGENCE_WINDOW, FLAG, MISORIENTED_DEG,
                                      cell_flagged)
from benchmark.core.json_io import atomic_write_json, atomic_write_text

log = logging.getLogger(__name__)

FORMATS = ("json", "md", "csv", "tex")
ARROWS = {"lower": "↓", "higher": "↑"}
TEX_ARROWS = {"lower": r"$\downarrow$", "higher": r"$\uparrow$"}
# Readable names for known metrics; others are derived from the name (see metric_label).
METRIC_NAMES = {
    "chamfer": "Chamfer",
    "chamfer_surface": "Surface Chamfer",
    "mpjpe": "MPJPE",
    "pa_mpjpe": "PA-MPJPE",
    "v2v": "V2V",
    "accel": "Acceleration",
    "accer": "Acceleration error",
    "root": "Root error",
    "gt_travel": "Ground-truth root travel",
}
UNIT_SUFFIXES = ("mm", "cm", "m", "deg", "rad", "s")
# How a grid axis value is shown in a column label.
AXIS_LABELS = {"points": "{} pts", "fps": "{} fps", "sigma": "σ = {}", "gap": "gap {}", "frames": "{} frames", "sweep": "{}",
               "mode": "{}"}


# --------------------------------------------------------------------------------------------
# Labels and numbers
# --------------------------------------------------------------------------------------------

def metric_unit(name: str) -> str | None:
    """The unit a metric name ends with (``chamfer_mm`` -> ``mm``), or None."""
    for unit in UNIT_SUFFIXES:
        if name.endswith("_" + unit):
            return unit
    return None


def metric_label(name: str) -> str:
    """``chamfer_mm`` -> ``Chamfer (mm)``; unknown names: words capitalised, unit in brackets."""
    unit = metric_unit(name)
    base = name[: -len(unit) - 1] if unit else name
    text = METRIC_NAMES.get(base, base.replace("_", " ").capitalize())
    return f"{text} ({unit})" if unit else text


def cell_label(cell: Mapping, grid_keys: Sequence[str]) -> str:
    """Column label of a grid cell: ``100 pts / 5 fps``."""
    return " / ".join(AXIS_LABELS.get(k, f"{k} = {{}}").format(cell[k]) for k in grid_keys)


def format_number(value: float | None, name: str) -> str:
    """One decimal for lengths (mm, cm); three significant digits otherwise."""
    if value is None:
        return "n/a"
    if metric_unit(name) in ("mm", "cm"):
        return f"{value:.1f}"
    return f"{value:.3g}"


def _metrics_in_order(table: Mapping) -> list[dict]:
    metrics = list(table["metrics"])
    head = table.get("headline_metric", metrics[0]["name"])
    return sorted(metrics, key=lambda m: m["name"] != head)


def _cell_reason(cell: Mapping, metric: str) -> str | None:
    if cell.get("na_reason"):
        return cell["na_reason"]
    if cell.get(metric) is None:
        return cell.get("metric_na", {}).get(metric, "no value")
    return None


def _paper_rows(table: Mapping, metric: str) -> list[tuple[str, list]]:
    """The paper's rows for ``metric``, each value placed in the column of its grid cell (None
    where the paper has no number). Empty when the spec's paper block does not match the grid."""
    paper = table.get("paper") or {}
    values = paper.get(metric)
    if not values:
        return []
    grid_keys = list(table["grid"])
    cells = [tuple(str(c[k]) for k in grid_keys) for c in table["rows"][0]["cells"]] if table["rows"] else []
    columns = paper.get("columns", [])
    positions = []
    for col in columns:
        coords = tuple(part.strip() for part in str(col).split("/"))
        if coords not in cells:
            log.warning("table %s: paper column %r does not match the grid %s; paper rows left out",
                        table["table"], col, grid_keys)
            return []
        positions.append(cells.index(coords))
    out = []
    for prior, numbers in values.items():
        if len(numbers) != len(columns):
            log.warning("table %s: paper %s row %r has %d numbers for %d columns; left out",
                        table["table"], metric, prior, len(numbers), len(columns))
            continue
        row = [None] * len(cells)
        for pos, number in zip(positions, numbers):
            row[pos] = number
        out.append((prior, row))
    return out


def _header_facts(table: Mapping) -> list[str]:
    prov = table.get("provenance") or {}
    git = prov.get("git") or {}
    rev = git.get("revision")
    rev_text = "unknown" if not rev else rev[:10] + (" (uncommitted changes)" if git.get("dirty") else "")
    facts = [
        f"table `{table['table']}`, protocol version {table['protocol_version']}"
        + (f" ({table['protocol']})" if table.get("protocol") else ""),
        f"profile `{table['profile']}`"
        + "".join(f", {k} {v}" for k, v in (table.get("profile_sizes") or {}).items()),
        f"device `{table['device']}`" + (f" ({prov['gpu']['name']})" if (prov.get("gpu") or {}).get("name") else ""),
        f"seed {table['seed']}",
        f"git {rev_text}",
    ]
    if table.get("data"):
        facts.append(f"data `{table['data']}`")
    if prov.get("timestamp"):
        facts.append(f"made {prov['timestamp']}")
    seqs = sorted({c["sequences"] for r in table["rows"] for c in r["cells"] if "sequences" in c})
    frames = sorted({c["frames"] for r in table["rows"] for c in r["cells"] if "frames" in c})
    if seqs:
        facts.append("sequences per cell " + "–".join(map(str, dict.fromkeys([seqs[0], seqs[-1]])))
                     + ", frames per cell " + "–".join(map(str, dict.fromkeys([frames[0], frames[-1]]))))
    return facts


def profile_warning(table: Mapping) -> str | None:
    """The warning a non-``full`` profile carries, or None."""
    if table.get("profile") == "full":
        return None
    desc = table.get("profile_description")
    return (f"Profile `{table['profile']}`" + (f" ({desc})" if desc else "")
            + ": not the full protocol. These numbers are not comparable to the paper's or to `full` runs.")


# --------------------------------------------------------------------------------------------
# Markdown
# --------------------------------------------------------------------------------------------

def format_markdown(table: Mapping) -> str:
    """The table as Markdown (see the module docstring)."""
    grid_keys = list(table["grid"])
    rows = table["rows"]
    cells = rows[0]["cells"] if rows else []
    labels = [cell_label(c, grid_keys) for c in cells]
    footnotes: dict[str, int] = {}

    def note(reason: str) -> str:
        footnotes.setdefault(reason, len(footnotes) + 1)
        return f"[^{footnotes[reason]}]"

    lines = [f"# {table.get('title', table['table'])}", ""]
    lines += [f"- {fact}" for fact in _header_facts(table)]
    warning = profile_warning(table)
    if warning:
        lines += ["", f"> **Warning.** {warning}"]
    lines += ["", f"Each number: mean over all output frames of all sequences ± {table.get('std_definition', 'standard deviation over sequences')}."]

    for metric in _metrics_in_order(table):
        name = metric["name"]
        lines += ["", f"## {metric_label(name)} {ARROWS[metric['better']]}", ""]
        if metric.get("description"):
            lines += [metric["description"][0].upper() + metric["description"][1:] + ".", ""]
        lines.append("| Prior | " + " | ".join(labels) + " |")
        lines.append("|:--|" + "--:|" * len(labels))
        for row in rows:
            out = []
            for cell in row["cells"]:
                reason = _cell_reason(cell, name)
                if reason is not None:
                    out.append(f"n/a {note(reason)}")
                else:
                    std = cell.get(f"{name}_std")
                    flag = f" {FLAG}" if cell_flagged(cell.get("diagnostics")) else ""
                    out.append(format_number(cell[name], name) + (f" ± {format_number(std, name)}" if std is not None else "")
                               + flag)
            lines.append(f"| {row['prior']} | " + " | ".join(out) + " |")
        paper = _paper_rows(table, name)
        for prior, numbers in paper:
            shown = ["–" if v is None else f"{v:g}" for v in numbers]
            lines.append(f"| *{prior} (paper, own data)* | " + " | ".join(f"*{s}*" for s in shown) + " |")
        if paper:
            lines += ["", "Rows in *italics* are the numbers printed in the paper, measured on the paper's own "
                          "data: for reference only, not produced by this run."]

    lines += _diagnostics_section(rows, labels)
    if footnotes:
        lines.append("")
        lines += [f"[^{n}]: {reason}" for reason, n in footnotes.items()]
    return "\n".join(lines) + "\n"


def _diagnostics_section(rows: list, labels: list[str]) -> list[str]:
    """The "Fit diagnostics" Markdown section (:mod:`benchmark.core.fit_diagnostics`): per prior and
    cell, backwards fits, unconverged fits and the mean root-orientation error; empty when no cell has them."""
    if not any(c.get("diagnostics") for row in rows for c in row["cells"]):
        return []
    lines = ["", "## Fit diagnostics", "",
             f"Per cell: backwards fits (mean facing error > {BACKWARDS_DEG:g}°) / unconverged fits (data term still "
             f"falling by more than {CONVERGED_MAX_DECREASE:.0%} over the last {CONVERGENCE_WINDOW:.0%} of the steps) / "
             "sequences, then the mean root-orientation error over the output frames, and the count of misoriented fits "
             f"(mean root-orientation error > {MISORIENTED_DEG:g}°: backwards, or facing the right way upside down) where "
             f"there is one. {FLAG} in the tables above marks a cell with a backwards, misoriented or unconverged fit: its "
             "number measures a fit failure as much as the prior.", "",
             "| Prior | " + " | ".join(labels) + " |", "|:--|" + "--:|" * len(labels)]
    for row in rows:
        out = []
        for cell in row["cells"]:
            d = cell.get("diagnostics")
            if not d:
                out.append("–")
                continue
            text = f"{d['backwards']}/{d['not_converged']}/{d['sequences']}"
            if d.get("root_err_deg") is not None:
                text += f", {d['root_err_deg']:.0f}°"
            if d.get("misoriented"):
                text += f", {d['misoriented']} misoriented"
            out.append(f"**{text}** {FLAG}" if cell_flagged(d) else text)
        lines.append(f"| {row['prior']} | " + " | ".join(out) + " |")
    return lines


# --------------------------------------------------------------------------------------------
# CSV and LaTeX
# --------------------------------------------------------------------------------------------

def format_csv(table: Mapping) -> str:
    """Long format: one line per prior x cell x metric (``value`` and ``std`` in ``unit``)."""
    grid_keys = list(table["grid"])
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["table", "protocol_version", "profile", "prior", *grid_keys, "metric", "unit", "value", "std",
                     "sequences", "frames", "na_reason"])
    for row in table["rows"]:
        for cell in row["cells"]:
            for metric in table["metrics"]:
                name = metric["name"]
                reason = _cell_reason(cell, name)
                value = "" if reason is not None else repr(float(cell[name]))
                std = cell.get(f"{name}_std")
                writer.writerow([table["table"], table["protocol_version"], table["profile"], row["prior"],
                                 *(cell[k] for k in grid_keys), name, metric_unit(name) or "", value,
                                 "" if reason is not None or std is None else repr(float(std)),
                                 cell.get("sequences", ""), cell.get("frames", ""), reason or ""])
    return buf.getvalue()


_TEX_ESCAPES = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
                "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}


def tex_escape(text: str) -> str:
    return "".join(_TEX_ESCAPES.get(ch, ch) for ch in str(text))


def format_latex(table: Mapping) -> str:
    """A booktabs ``tabular`` of the headline metric (needs ``\\usepackage{booktabs}``)."""
    grid_keys = list(table["grid"])
    rows = table["rows"]
    cells = rows[0]["cells"] if rows else []
    metric = _metrics_in_order(table)[0]
    name = metric["name"]
    n = len(cells)
    marks: dict[str, int] = {}
    warning = profile_warning(table)
    out = [f"% {table.get('title', table['table'])}",
           f"% table {table['table']}, protocol version {table['protocol_version']}, profile {table['profile']}, "
           f"device {table['device']}, seed {table['seed']}",
           f"% {metric_label(name)}: mean over all output frames of all sequences"]
    if warning:
        out.append(f"% WARNING: {warning}")
    out += [rf"\begin{{tabular}}{{l{'r' * n}}}", r"\toprule",
            rf" & \multicolumn{{{n}}}{{c}}{{{tex_escape(metric_label(name))} {TEX_ARROWS[metric['better']]}}} \\",
            rf"\cmidrule(lr){{2-{n + 1}}}",
            "Prior & " + " & ".join(tex_escape(cell_label(c, grid_keys)) for c in cells) + r" \\",
            r"\midrule"]
    for row in rows:
        values = []
        for cell in row["cells"]:
            reason = _cell_reason(cell, name)
            if reason is not None:
                marks.setdefault(reason, len(marks) + 1)
                values.append(rf"n/a$^{{{marks[reason]}}}$")
            else:
                values.append(format_number(cell[name], name))
        out.append(tex_escape(row["prior"]) + " & " + " & ".join(values) + r" \\")
    paper = _paper_rows(table, name)
    if paper:
        out += [r"\midrule", rf"\multicolumn{{{n + 1}}}{{l}}{{\emph{{Paper's numbers, on the paper's own data (reference only)}}}} \\"]
        for prior, numbers in paper:
            out.append(tex_escape(prior) + " & " + " & ".join("--" if v is None else f"{v:g}" for v in numbers) + r" \\")
    out.append(r"\bottomrule")
    for reason, k in marks.items():
        out.append(rf"\multicolumn{{{n + 1}}}{{l}}{{\footnotesize $^{{{k}}}$ {tex_escape(reason)}}} \\")
    out.append(r"\end{tabular}")
    return "\n".join(out) + "\n"


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------

def write_table(table: Mapping, out_dir: str | os.PathLike, stem: str | None = None,
                formats: Sequence[str] = FORMATS) -> dict[str, Path]:
    """Write ``<out_dir>/<stem>.{json,md,csv,tex}`` (``stem`` defaults to the table name), each
    atomically. Returns format -> path."""
    unknown = [f for f in formats if f not in FORMATS]
    if unknown:
        raise ValueError(f"unknown output format(s) {unknown}; known: {', '.join(FORMATS)}")
    out_dir = Path(out_dir)
    stem = stem or table["table"]
    makers = {"md": format_markdown, "csv": format_csv, "tex": format_latex}
    paths = {}
    for fmt in formats:
        path = out_dir / f"{stem}.{fmt}"
        if fmt == "json":
            atomic_write_json(path, table)
        else:
            atomic_write_text(path, makers[fmt](table))
        paths[fmt] = path
    return paths
