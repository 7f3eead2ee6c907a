"""Write a derived table (the JSON of :func:`benchmark.run.table_derive.derive_table`) as files people read.

- ``<stem>.json``: the table itself (atomic write).
- ``<stem>.md``: Markdown: a header (title, profile, protocol version, device, seed, revision), one
  table per metric (headline first), one row per prior and one column per grid cell, the mean and
  its 95 % interval ``25.0 [19.1, 31.2]``, :data:`SIGNIFICANT_MARK` on a significant win over
  ``no-prior`` (tables derived before the intervals: mean ± std); ``n/a`` cells carry a footnote
  with their reason; the paper's own numbers, where the spec has them, are added as separate,
  labelled rows.
- ``<stem>.csv``: long format, one line per prior x cell x metric, with the interval and the paired
  comparisons (against ``no-prior`` and the cell's best prior).
- ``<stem>.tex``: a booktabs ``tabular`` of the headline metric, with the intervals and the mark.

Numbers arrive already in reported units (the derivation converted them); nothing here rescales.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path
from typing import Mapping, Sequence

from benchmark.core.fit_diagnostics import (BACKWARDS_DEG, CONVERGED_MAX_DECREASE, CONVERGENCE_WINDOW, FLAG, MISORIENTED_DEG,
                                      cell_flagged)
from benchmark.core.intervals import MIN_SIGNIFICANCE_SEQUENCES
from benchmark.core.json_io import atomic_write_texts, json_text
from benchmark.core.work_units import grid_axes
from benchmark.run.csv_format import format_csv
from benchmark.run.table_derive import NO_PRIOR, cell_reason, metric_unit

log = logging.getLogger(__name__)

FORMATS = ("json", "md", "csv", "tex")
SIGNIFICANT_MARK = "†"  # a cell whose win over no-prior is significant (paired interval excludes 0)
ARROWS = {"lower": "↓", "higher": "↑"}
TEX_ARROWS = {"lower": r"$\downarrow$", "higher": r"$\uparrow$"}
# Readable names for known metrics; others are derived from the name (see metric_label).
METRIC_NAMES = {
    "chamfer": "Chamfer",
    "chamfer_surface": "Surface Chamfer",
    "mpjpe": "MPJPE",
    "mpjpe_local": "MPJPE, pelvis-centred",
    "pa_mpjpe": "PA-MPJPE",
    "v2v": "V2V",
    "accel": "Acceleration",
    "accer": "Acceleration error",
    "root": "Root error",
    "gt_travel": "Ground-truth root travel",
    "gt_accel": "Ground-truth acceleration",
    "obs_accel": "Observation's acceleration",
    "obs_v2v": "Observation's V2V",
    "time_per_frame": "Time per frame",
    "quat_loss": "Quaternion loss",
}
UNIT_TEXT = {"mps2": "m/s²"}  # how a unit suffix is written in a label (the CSV: ASCII, m/s^2)
# How a grid axis value is shown in a column label.
AXIS_LABELS = {"points": "{} pts", "fps": "{} fps", "sigma": "σ = {}", "gap": "gap {}", "frames": "{} frames", "sweep": "{}",
               "mode": "{}"}


# --------------------------------------------------------------------------------------------
# Labels and numbers
# --------------------------------------------------------------------------------------------

def metric_label(name: str) -> str:
    """``chamfer_mm`` -> ``Chamfer (mm)``; unknown names: words capitalised, unit in brackets."""
    unit = metric_unit(name)
    base = name[: -len(unit) - 1] if unit else name
    text = METRIC_NAMES.get(base, base.replace("_", " ").capitalize())
    return f"{text} ({UNIT_TEXT.get(unit, unit)})" if unit else text


def direction_text(metric: Mapping, tex: bool = False) -> str:
    """What follows a metric's heading: its arrow, or for ``better: closest`` the metric it is judged
    against, for ``better: none`` that it is a reference (:func:`benchmark.core.work_units.metric_specs`)."""
    better = metric.get("better", "lower")
    if better == "closest":
        return f"(closest to {metric_label(metric['reference'])} is best)"
    if better == "none":
        return "(reference, not ranked)"
    return (TEX_ARROWS if tex else ARROWS)[better]


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


def format_interval(interval, name: str) -> str:
    """``[lo, hi]`` in the metric's number format."""
    lo, hi = interval
    return f"[{format_number(lo, name)}, {format_number(hi, name)}]"


def printed_step(value: float, name: str) -> float:
    """The size of one unit in the last digit :func:`format_number` prints of ``value``."""
    if metric_unit(name) in ("mm", "cm"):
        return 0.1
    return 10.0 ** (math.floor(math.log10(abs(value))) - 2) if value else 0.0


def significant_win(cell: Mapping, metric: str) -> bool:
    """Whether the cell beats ``no-prior`` on ``metric`` with a paired interval that excludes 0, by
    a mean difference of at least half a unit of the cell's last printed digit: a difference the
    table cannot show (two runs of one fit that differ by float rounding, 57.9003 against 57.9 mm)
    is a tie on the page, however consistent its sign, and is not marked. The table JSON keeps
    the comparison itself (``paired``: ``diff``, ``ci95``, ``significant``)."""
    comparison = ((cell.get("paired") or {}).get(metric) or {}).get("no_prior") or {}
    if not (comparison.get("significant") is True and comparison.get("better") is True):
        return False
    diff, value = comparison.get("diff"), cell.get(metric)
    if diff is None or value is None:
        return True
    return abs(float(diff)) >= 0.5 * printed_step(float(value), metric)


def cell_text(cell: Mapping, metric: str, mark: bool = True) -> str:
    """A served cell's number as the tables show it: ``25.0 [19.1, 31.2]`` (no interval below 2
    sequences), then :data:`SIGNIFICANT_MARK` on a significant win over no-prior (``mark``); a cell
    derived before the intervals: ``25.0 ± 9.3``."""
    text = format_number(cell[metric], metric)
    if f"{metric}_ci95" in cell:
        interval = cell[f"{metric}_ci95"]
        text += f" {format_interval(interval, metric)}" if interval is not None else ""
    elif cell.get(f"{metric}_std") is not None:
        text += f" ± {format_number(cell[f'{metric}_std'], metric)}"
    if mark and significant_win(cell, metric):
        text += f" {SIGNIFICANT_MARK}"
    return text


def has_intervals(table: Mapping) -> bool:
    """Whether the table was derived with intervals (cells with ``<metric>_ci95``)."""
    names = [m["name"] for m in table["metrics"]]
    return any(f"{n}_ci95" in c for r in table["rows"] for c in r["cells"] for n in names)


def same_label(same: Mapping) -> str:
    """``f100`` fitted once as ``p10000``: a ``same_cells`` entry in words (:mod:`benchmark.run.same_cells`)."""
    (_, value), = same["cell"].items()
    (_, source), = same["as"].items()
    return f"`{value}` is column `{source}`, fitted once and shown twice"


def interval_note(table: Mapping) -> str:
    """The sentence under each Markdown table: what the brackets and the mark mean."""
    level = (table.get("bootstrap") or {}).get("level", 0.95)
    text = (f"In brackets: the {level:.0%} bootstrap interval of that frame-weighted mean, its sequences resampled "
            "(none for a cell of one sequence or for a measured time).")
    if any(r["prior"] == NO_PRIOR for r in table["rows"]):
        text += (f" {SIGNIFICANT_MARK}: better than `{NO_PRIOR}` in this cell, the paired {level:.0%} bootstrap "
                 f"interval of the per-sequence difference excluding 0 (claimed from {MIN_SIGNIFICANCE_SEQUENCES} "
                 "sequences in common) and the mean difference at least half a unit of the last printed digit.")
    else:
        text += f" No `{NO_PRIOR}` row: no cell is marked as a significant win over it."
    return text


def _metrics_in_order(table: Mapping) -> list[dict]:
    metrics = list(table["metrics"])
    head = table.get("headline_metric", metrics[0]["name"])
    return sorted(metrics, key=lambda m: m["name"] != head)


def untrained_reason(table: Mapping, prior: str) -> str | None:
    """Why a row measures no trained prior (its network read no weights file: ``prior_info``'s
    ``untrained``, :func:`benchmark.run.table_run.prior_identity`), or None."""
    if ((table.get("prior_info") or {}).get(prior) or {}).get("untrained"):
        return (f"{prior} read no weights file: its network kept its initial, untrained parameters, so this row "
                "measures no trained prior (give its weights with --weights, or train them)")
    return None


def _paper_rows(table: Mapping, metric: str) -> list[tuple[str, list]]:
    """The paper's rows for ``metric``, each value placed in the column of its grid cell (None
    where the paper has no number). Empty when the spec's paper block does not match the grid."""
    paper = table.get("paper") or {}
    values = paper.get(metric)
    if not values:
        return []
    grid_keys = grid_axes(table)
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
    order = [r["prior"] for r in table["rows"]]  # the table's row order (a table read back from JSON lists the paper's sorted)
    for prior, numbers in sorted(values.items(), key=lambda kv: order.index(kv[0]) if kv[0] in order else len(order)):
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
        # sequences and steps first (a table read back from JSON lists its sizes sorted)
        + "".join(f", {k} {v}" for k, v in sorted((table.get("profile_sizes") or {}).items(),
                                                   key=lambda kv: kv[0] not in ("sequences", "steps"))),
        f"device `{table['device']}`" + (f" ({prov['gpu']['name']})" if (prov.get("gpu") or {}).get("name") else ""),
        f"seed {table['seed']}",
        f"git {rev_text}",
    ]
    if table.get("data"):
        facts.append(f"data `{table['data']}`")
    if prov.get("timestamp"):
        facts.append(f"made {prov['timestamp']}")
    for replaced in prov.get("rows_replaced") or []:  # benchmark.run.table_merge
        p = replaced.get("provenance") or {}
        r = (p.get("git") or {}).get("revision")
        facts.append(f"rows of {', '.join(f'`{n}`' for n in replaced['priors'])} replaced by a later run"
                     + (f" (git {r[:10]}" + (" (uncommitted changes)" if (p.get("git") or {}).get("dirty") else "") + ")" if r else "")
                     + (f" on {p['cpu']}" if p.get("cpu") else "") + (f", {p['timestamp']}" if p.get("timestamp") else "")
                     + (f"; its observation fingerprints differ in {len(replaced['observation_fingerprints_differ'])} cell(s) "
                        "(another build of the body's cache)" if replaced.get("observation_fingerprints_differ") else "")
                     + (f"; the step cap raised from {cap['from']} to {cap['to']}: the other rows' fits all converged "
                        "before the smaller cap, so they are the same under the larger" if (cap := replaced.get("step_cap_raised")) else ""))
    for same in table.get("same_cells") or []:  # benchmark.run.same_cells
        facts.append(f"column {same_label(same)}: {same['why'] or 'the same observation'}")
    seqs = sorted({c["sequences"] for r in table["rows"] for c in r["cells"] if "sequences" in c})
    frames = sorted({c["frames"] for r in table["rows"] for c in r["cells"] if "frames" in c})
    if seqs:
        facts.append("sequences per cell " + "–".join(map(str, dict.fromkeys([seqs[0], seqs[-1]])))
                     + ", frames per cell " + "–".join(map(str, dict.fromkeys([frames[0], frames[-1]]))))
    return facts


def averaged_over(table: Mapping) -> str:
    """What a cell's number averages: every output frame of every sequence, unless the table scores
    only some frames (its spec's ``scored_frames``, e.g. inbetween's missing frames)."""
    return (f"mean over {table.get('scored_frames') or 'all output frames'} of all sequences (a frame-weighted "
            "mean: each sequence weighs by its scored frames)")


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
    grid_keys = grid_axes(table)
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
    intervals = has_intervals(table)
    if intervals:
        lines += ["", f"Each number: {averaged_over(table)}, then in brackets its "
                      f"{table.get('interval_definition', 'bootstrap interval over sequences')}."]
    else:
        lines += ["", f"Each number: {averaged_over(table)} ± {table.get('std_definition', 'standard deviation over sequences')}."]

    for metric in _metrics_in_order(table):
        name = metric["name"]
        lines += ["", f"## {metric_label(name)} {direction_text(metric)}", ""]
        if metric.get("description"):
            lines += [metric["description"][0].upper() + metric["description"][1:] + ".", ""]
        lines.append("| Prior | " + " | ".join(labels) + " |")
        lines.append("|:--|" + "--:|" * len(labels))
        for row in rows:
            out = []
            for cell in row["cells"]:
                reason = cell_reason(cell, name)
                if reason is not None:
                    out.append(f"n/a {note(reason)}")
                else:
                    flag = f" {FLAG}" if cell_flagged(cell.get("diagnostics")) else ""
                    out.append(cell_text(cell, name) + flag)
            untrained = untrained_reason(table, row["prior"])
            label = row["prior"] + (f" {note(untrained)}" if untrained else "")
            lines.append(f"| {label} | " + " | ".join(out) + " |")
        paper = _paper_rows(table, name)
        for prior, numbers in paper:
            shown = ["–" if v is None else f"{v:g}" for v in numbers]
            lines.append(f"| *{prior} (paper, own data)* | " + " | ".join(f"*{s}*" for s in shown) + " |")
        if intervals:
            lines += ["", interval_note(table)]
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
    plateau = any("steps_max" in (c.get("diagnostics") or {}) for row in rows for c in row["cells"])
    unconverged = ("objective still changing by more than the plateau rule's tolerance over its window at the fit's "
                   "last learning rate when it stopped descending, or at the step cap" if plateau else
                   f"data term still falling by more than {CONVERGED_MAX_DECREASE:.0%} over the last "
                   f"{CONVERGENCE_WINDOW:.0%} of the steps")
    lines = ["", "## Fit diagnostics", "",
             f"Per cell: backwards fits (mean facing error > {BACKWARDS_DEG:g}°) / unconverged fits ({unconverged}) / "
             "sequences, then the mean root-orientation error over the output frames"
             + (", the most steps a fit of the cell took" if plateau else "") + ", and the count of misoriented fits "
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
            if d.get("steps_max") is not None:
                text += f", {d['steps_max']} steps"
            if d.get("misoriented"):
                text += f", {d['misoriented']} misoriented"
            out.append(f"**{text}** {FLAG}" if cell_flagged(d) else text)
        lines.append(f"| {row['prior']} | " + " | ".join(out) + " |")
    return lines


# --------------------------------------------------------------------------------------------
# CSV and LaTeX
# --------------------------------------------------------------------------------------------

_TEX_ESCAPES = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
                "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}


def tex_escape(text: str) -> str:
    return "".join(_TEX_ESCAPES.get(ch, ch) for ch in str(text))


def format_latex(table: Mapping) -> str:
    """A booktabs ``tabular`` of the headline metric (needs ``\\usepackage{booktabs}``): each mean with its
    interval in small type and ``$^\\dagger$`` on a significant win over no-prior, explained in a
    note under the table (tables derived before the intervals: the mean alone)."""
    grid_keys = grid_axes(table)
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
           f"% {metric_label(name)}: {averaged_over(table)}"]
    intervals = has_intervals(table)
    level = (table.get("bootstrap") or {}).get("level", 0.95)
    if intervals:
        out.append(f"% in brackets: {table.get('interval_definition', 'bootstrap interval over sequences')}")
    if warning:
        out.append(f"% WARNING: {warning}")
    out += [rf"\begin{{tabular}}{{l{'r' * n}}}", r"\toprule",
            rf" & \multicolumn{{{n}}}{{c}}{{{tex_escape(metric_label(name))} {direction_text(metric, tex=True)}}} \\",
            rf"\cmidrule(lr){{2-{n + 1}}}",
            "Prior & " + " & ".join(tex_escape(cell_label(c, grid_keys)) for c in cells) + r" \\",
            r"\midrule"]
    for row in rows:
        values = []
        for cell in row["cells"]:
            reason = cell_reason(cell, name)
            if reason is not None:
                marks.setdefault(reason, len(marks) + 1)
                values.append(rf"n/a$^{{{marks[reason]}}}$")
            else:
                text = format_number(cell[name], name)
                if cell.get(f"{name}_ci95") is not None:
                    text += rf"{{\scriptsize\,{format_interval(cell[f'{name}_ci95'], name)}}}"
                if significant_win(cell, name):
                    text += r"$^\dagger$"
                values.append(text)
        untrained = untrained_reason(table, row["prior"])
        if untrained:
            marks.setdefault(untrained, len(marks) + 1)
        out.append(tex_escape(row["prior"]) + (rf"$^{{{marks[untrained]}}}$" if untrained else "") + " & "
                   + " & ".join(values) + r" \\")
    paper = _paper_rows(table, name)
    if paper:
        out += [r"\midrule", rf"\multicolumn{{{n + 1}}}{{l}}{{\emph{{Paper's numbers, on the paper's own data (reference only)}}}} \\"]
        for prior, numbers in paper:
            out.append(tex_escape(prior) + " & " + " & ".join("--" if v is None else f"{v:g}" for v in numbers) + r" \\")
    out.append(r"\bottomrule")
    if intervals:
        note = (rf"In brackets: {level * 100:.0f}\% bootstrap interval over sequences. "
                + (rf"$^\dagger$ better than {tex_escape(NO_PRIOR)}, paired {level * 100:.0f}\% interval of the "
                   rf"difference excluding 0 (from {MIN_SIGNIFICANCE_SEQUENCES} sequences), by at least half the last printed digit." if any(r["prior"] == NO_PRIOR for r in rows) else ""))
        out.append(rf"\multicolumn{{{n + 1}}}{{l}}{{\footnotesize {note.strip()}}} \\")
    for reason, k in marks.items():
        out.append(rf"\multicolumn{{{n + 1}}}{{l}}{{\footnotesize $^{{{k}}}$ {tex_escape(reason)}}} \\")
    for same in table.get("same_cells") or []:
        out.append(rf"\multicolumn{{{n + 1}}}{{l}}{{\footnotesize {tex_escape(same_label(same).replace('`', ''))}}} \\")
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
    makers = {"md": format_markdown, "csv": format_csv, "tex": format_latex, "json": json_text}
    paths = {fmt: out_dir / f"{stem}.{fmt}" for fmt in formats}
    # every format made and written before any replaces its old file: a full disk or an interrupt
    # part way never leaves this run's JSON beside an earlier run's Markdown
    atomic_write_texts({paths[fmt]: makers[fmt](table) for fmt in formats})
    return paths
