"""``python -m benchmark report RUN_DIR``: one self-contained folder (``index.html`` + images) that
shows a finished run: its tables, diagnostics, plots and animated fits. Offline: no server, no CDN,
no script; relative links only.

What it reads (:mod:`benchmark.report.run_folder`): the table JSONs at the top of the run folder,
the unit JSONs under ``units/`` (per-sequence metrics, fit logs) and, beside each unit JSON, the
fitted and ground-truth motion (``<unit_id>.npz``, :mod:`benchmark.data.unit_arrays`). Units run before
those arrays were stored get no animation and the page says so where the animation would be.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from benchmark.report.cells import CellReport, cell_text, diagnose, run_animation_jobs, safe_name
from benchmark.report.out_folder import check_report_folder, finish_report_folder, start_report_folder
from benchmark.report.run_folder import RunFolder, load_run, sequence_rows
from benchmark.report.sections import (about_html, animation_section, breakdown_section, diagnostics_table, esc,
                                       figure_html, metric_table)

log = logging.getLogger(__name__)

DEFAULT_SEQUENCES = 1  # sequences animated per prior x cell
ANIMATION_FPS = 15.0  # every second 30 fps output frame: about 250 kB per 4 s animation (WebP)


def build_report(run_dir, out_dir=None, sequences: int = DEFAULT_SEQUENCES, animation_format: str = "webp",
                 body_spec: str | None = None, animation_fps: float = ANIMATION_FPS, workers: int = 1) -> Path:
    """Write the report of ``run_dir`` into ``out_dir`` (default ``<run_dir>/report``); returns the
    path of ``index.html``. ``sequences``: how many sequences to animate per prior x cell (0: none);
    ``animation_fps``: frame rate of the animations (a divisor of the output rate; 30 shows every
    output frame, at about twice the file size); ``workers``: processes rendering animations."""
    t_start = time.perf_counter()
    run = load_run(run_dir)
    out = Path(out_dir) if out_dir is not None else run.root / "report"
    if sequences < 0:
        raise ValueError(f"--sequences must be >= 0, got {sequences}")
    if not animation_fps > 0:
        raise ValueError(f"--animation-fps must be > 0, got {animation_fps}")
    if animation_format not in ("webp", "gif"):
        raise ValueError(f"--format must be webp or gif, got {animation_format!r}")
    if animation_format == "webp":
        from PIL import features

        if not features.check("webp"):
            log.warning("report: this Pillow has no WebP support; writing GIF animations")
            animation_format = "gif"
    check_report_folder(out)  # nothing but an earlier report, as its marker records it
    img_dir = start_report_folder(out)

    from benchmark.report import plots

    jobs: list = []
    writers = [_table_section(run, table, img_dir, sequences, animation_format, body_spec, plots, animation_fps, jobs)
               for table in run.tables]
    run_animation_jobs(jobs, workers)
    sections = [write() for write in writers]
    page = _page(run, sections, out, time.perf_counter() - t_start)
    index = out / "index.html"
    index.write_text(page, encoding="utf-8")
    finish_report_folder(out)
    log.info("report: %s (%.1f s)", index, time.perf_counter() - t_start)
    return index


# ------------------------------------------------------------------------------------ per table
def _table_section(run: RunFolder, table: dict, img_dir: Path, sequences: int, fmt: str, body_spec, plots,
                   animation_fps: float, jobs: list):
    """Read a table's units and queue its animations on ``jobs``; returns the function that writes
    the table's HTML (and plots) once the jobs have run."""
    name = table["table"]
    stem = safe_name(Path(table.get("_file", name)).stem)
    priors = [r["prior"] for r in table["rows"]]
    colours = plots.prior_colours(priors)
    metric_names = [m["name"] for m in table["metrics"]]
    head = table.get("headline_metric", metric_names[0])
    metric_names.sort(key=lambda m: m != head)
    cells = table["rows"][0]["cells"] if table["rows"] else []
    grid_keys = list(table["grid"])

    reports: dict = {}
    for row in table["rows"]:
        for i, c in enumerate(row["cells"]):
            cell = {k: c[k] for k in grid_keys}
            same = c.get("same_as")  # a copied column: its source's units and fits, animated once, under the source
            units, mismatch = run.units_for(table, row["prior"], {**cell, **(same or {})}, c)
            cr = CellReport(table=name, prior=row["prior"], cell=cell, units=units,
                            anchor=f"seq-{stem}-{safe_name(row['prior'])}-{i}")
            cr.seq_rows = sequence_rows(units, metric_names)
            diagnose(run, cr, img_dir, sequences if not (c.get("na_reason") or same) else 0, fmt, body_spec,
                     animation_fps, jobs)
            if same and units:
                cr.no_animation = f"the fits of column {cell_text(same)}: animated there"
            if mismatch:
                cr.no_animation = mismatch
            reports[(row["prior"], i)] = cr
    return lambda: _table_html(table, reports, img_dir, plots, stem, priors, colours, metric_names, head, cells,
                               grid_keys)


def _table_html(table, reports, img_dir, plots, stem, priors, colours, metric_names, head, cells, grid_keys) -> str:
    name = table["table"]

    parts = [f'<section id="{esc(stem)}"><h2>{esc(name)}: {esc(table.get("title", ""))}</h2>'
             f'<p class="note">{esc(table.get("_file", ""))}, profile {esc(table.get("profile"))}</p>']
    parts.append(about_html(table))
    if not cells:
        parts.append('<p class="note">This table has no rows (no prior was run).</p></section>')
        return "\n".join(parts)
    for m in metric_names:
        parts.append(metric_table(table, m, reports, grid_keys))
    parts.append(diagnostics_table(table, reports, grid_keys))

    # plots
    parts.append("<h3>Plots</h3>")
    figs = []
    for m in [head] + (["mpjpe_mm"] if "mpjpe_mm" in metric_names and head != "mpjpe_mm" else []):
        figs += plots.sweep_plots(table, m, img_dir, colours, stem)
    for m in [head] + (["mpjpe_mm"] if "mpjpe_mm" in metric_names and head != "mpjpe_mm" else []):
        seq_values = {(p, i): [r[m] for r in reports[(p, i)].seq_rows] for p in priors for i in range(len(cells))}
        if any(seq_values.values()):
            figs.append(plots.spread_plot(table, m, seq_values, img_dir, colours, stem))
    if not any(reports[k].seq_rows for k in reports):
        parts.append('<p class="note">No unit files under units/: per-sequence plots need them.</p>')
    for caption, path in figs:
        parts.append(figure_html(path, caption, img_dir))

    # animations
    parts.append(animation_section(table, reports, img_dir, plots, priors, cells, grid_keys))
    parts.append(breakdown_section(table, reports, metric_names, grid_keys))
    parts.append("</section>")
    return "\n".join(parts)


CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:1.5em auto;max-width:1400px;padding:0 1em;color:#222}
h1{font-size:1.5em} h2{border-bottom:2px solid #ccc;padding-bottom:.2em;margin-top:2em} h3{margin-top:1.6em}
table.results{border-collapse:collapse;font-size:.85em;margin:.5em 0}
table.results th,table.results td{border:1px solid #ddd;padding:.25em .5em;text-align:right}
table.results th{background:#f4f4f4;text-align:left}
table.results tr.paper{font-style:italic;color:#666}
table.results a{color:inherit;text-decoration:none;border-bottom:1px dotted #999}
td.na{color:#999} .bad{color:#c0392b;font-weight:600} .ok{color:#27803b} .muted{color:#999}
.bw{color:#c0392b} .win{color:#1e7b34;font-weight:bold} .note{color:#555;font-size:.9em;max-width:70em}
table.kv{font-size:.85em;border-collapse:collapse} table.kv th{text-align:left;padding-right:1em;vertical-align:top}
figure{display:inline-block;margin:.5em 1em .5em 0;vertical-align:top} figcaption{font-size:.8em;color:#555;max-width:40em}
figure img{max-width:100%} .anims{display:flex;flex-wrap:wrap;gap:.3em}
figure.anim{margin:.2em} figure.anim figcaption{max-width:260px}
.unavail{border:1px dashed #bbb;color:#666;padding:.5em;font-size:.85em;max-width:260px;margin:.2em}
img.legend{display:block;margin:.3em 0}
.seq{margin-bottom:1em} nav a{margin-right:1em}
"""


def _page(run: RunFolder, sections: list, out: Path, seconds: float) -> str:
    nav = " ".join(f'<a href="#{esc(safe_name(Path(t.get("_file", t["table"])).stem))}">{esc(Path(t.get("_file", t["table"])).stem)}</a>'
                   for t in run.tables)
    skipped = ""
    if run.skipped:
        skipped = ("<p class='note'>Skipped files: " + "; ".join(f"{esc(p.name)} ({esc(w)})" for p, w in run.skipped)
                   + "</p>")
    stamp = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    return (f"<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
            f"<meta name='viewport' content='width=device-width, initial-scale=1'>"
            f"<title>Benchmark report: {esc(run.root.name)}</title><style>{CSS}</style></head><body>"
            f"<h1>Benchmark report: {esc(run.root)}</h1>"
            f"<p class='note'>Made by <code>python -m benchmark report</code> on {stamp} in {seconds:.0f} s. "
            f"Every number links to its sequence breakdown.</p><nav>{nav}</nav>{skipped}"
            + "\n".join(sections) + "</body></html>\n")


__all__ = ["build_report", "DEFAULT_SEQUENCES"]
