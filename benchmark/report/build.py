"""``python -m benchmark report RUN_DIR``: one self-contained folder (``index.html`` + images) that
shows a finished run: its tables, diagnostics, plots and animated fits. Offline: no server, no CDN,
no script; relative links only.

What it reads (:mod:`benchmark.report.run_folder`): the table JSONs at the top of the run folder,
the unit JSONs under ``units/`` (per-sequence metrics, fit logs) and, beside each unit JSON, the
fitted and ground-truth motion (``<unit_id>.npz``, :mod:`benchmark.unit_arrays`). Units run before
those arrays were stored get no animation and the page says so where the animation would be.
"""

from __future__ import annotations

import html
import logging
import re
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmark.report.run_folder import RunFolder, load_run, sequence_rows

log = logging.getLogger(__name__)

DEFAULT_SEQUENCES = 1  # sequences animated per prior x cell
ANIMATION_SIZE = (140, 190)  # pixels of each of the two views
ANIMATION_FPS = 15.0  # every second 30 fps output frame: about 250 kB per 4 s animation (WebP)
BACKWARDS_FRACTION = 0.5  # a sequence is flagged backwards when its fit faces > 90° away on this share of frames


@dataclass
class SequenceDiag:
    """Diagnostics of one fitted sequence, computed from its stored arrays."""

    facing_err_mean: float  # degrees
    root_err_mean: float  # degrees
    backwards_fraction: float  # share of output frames facing > 90° away from the ground truth
    v2v_mm: float | None = None  # mean per-vertex distance to the ground-truth mesh (animated sequences only)

    @property
    def backwards(self) -> bool:
        return self.backwards_fraction > BACKWARDS_FRACTION


@dataclass
class CellReport:
    table: str
    prior: str
    cell: dict
    anchor: str
    units: list
    seq_rows: list = field(default_factory=list)
    diag: dict = field(default_factory=dict)  # sequence id -> SequenceDiag
    animations: list = field(default_factory=list)  # (sequence id, relative path)
    facing_curves: list = field(default_factory=list)  # (label, t, facing error)
    no_animation: str | None = None  # why there is none


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", str(text)).strip("-")


def _esc(x) -> str:
    return html.escape(str(x), quote=True)


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
    img_dir = out / "img"
    marker = img_dir / ".benchmark-report"
    if img_dir.exists():
        index = out / "index.html"
        ours = marker.exists() or (index.is_file() and "python -m benchmark report" in index.read_text(errors="replace"))
        if not ours:
            raise FileExistsError(f"report: {img_dir} exists and was not written by the report; choose another --out")
        shutil.rmtree(img_dir)  # a previous report's images: replaced
    img_dir.mkdir(parents=True)
    marker.write_text("written by python -m benchmark report; replaced on the next report into this folder\n")

    from benchmark.report import plots

    jobs: list = []
    writers = [_table_section(run, table, img_dir, sequences, animation_format, body_spec, plots, animation_fps, jobs)
               for table in run.tables]
    run_animation_jobs(jobs, workers)
    sections = [write() for write in writers]
    page = _page(run, sections, out, time.perf_counter() - t_start)
    index = out / "index.html"
    index.write_text(page, encoding="utf-8")
    log.info("report: %s (%.1f s)", index, time.perf_counter() - t_start)
    return index


# ------------------------------------------------------------------------------------ per table
def _table_section(run: RunFolder, table: dict, img_dir: Path, sequences: int, fmt: str, body_spec, plots,
                   animation_fps: float, jobs: list):
    """Read a table's units and queue its animations on ``jobs``; returns the function that writes
    the table's HTML (and plots) once the jobs have run."""
    name = table["table"]
    stem = _safe(Path(table.get("_file", name)).stem)
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
            units = run.units_of(name, row["prior"], cell)
            cr = CellReport(table=name, prior=row["prior"], cell=cell, units=units,
                            anchor=f"seq-{stem}-{_safe(row['prior'])}-{i}")
            cr.seq_rows = sequence_rows(units, metric_names)
            _diagnose(run, cr, img_dir, sequences if not c.get("na_reason") else 0, fmt, body_spec, animation_fps, jobs)
            reports[(row["prior"], i)] = cr
    return lambda: _table_html(table, reports, img_dir, plots, stem, priors, colours, metric_names, head, cells,
                               grid_keys)


def _table_html(table, reports, img_dir, plots, stem, priors, colours, metric_names, head, cells, grid_keys) -> str:
    name = table["table"]

    parts = [f'<section id="{_esc(stem)}"><h2>{_esc(name)}: {_esc(table.get("title", ""))}</h2>'
             f'<p class="note">{_esc(table.get("_file", ""))}, profile {_esc(table.get("profile"))}</p>']
    parts.append(_about(table))
    if not cells:
        parts.append('<p class="note">This table has no rows (no prior was run).</p></section>')
        return "\n".join(parts)
    for m in metric_names:
        parts.append(_metric_table(table, m, reports, grid_keys))
    parts.append(_diagnostics_table(table, reports, grid_keys))

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
        parts.append(_figure(path, caption, img_dir))

    # animations
    parts.append(_animation_section(table, reports, img_dir, plots, priors, cells, grid_keys))
    parts.append(_breakdown_section(table, reports, metric_names, grid_keys))
    parts.append("</section>")
    return "\n".join(parts)


@dataclass
class AnimationJob:
    """One animation to render (picklable: it runs in a worker process when ``workers`` > 1)."""

    npz: str
    index: int
    out: str
    title: str
    body_spec: str
    size: tuple
    fps: float
    cell_report: object = field(default=None, repr=False)  # filled in this process only
    sequence_id: str = ""

    def payload(self) -> tuple:
        return (self.npz, self.index, self.out, self.title, self.body_spec, self.size, self.fps)


def _diagnose(run, cr: CellReport, img_dir: Path, sequences: int, fmt: str, body_spec, animation_fps: float,
              jobs: list) -> None:
    """Per-sequence diagnostics of a cell from its stored root rotations; queue its animations."""
    from benchmark.report.animate import check_arrays, root_diagnostics
    from benchmark.unit_arrays import read_arrays

    if not cr.units:
        cr.no_animation = "no unit file for this cell under units/"
        return
    missing = [u["unit_id"] for u in cr.units if not run.npz_path(u).exists()]
    if len(missing) == len(cr.units):
        cr.no_animation = ("animation unavailable: this run stored no fitted motion for this cell (no "
                           f"units/{missing[0]}.npz; units run before the harness kept it, or a protocol that does not "
                           "store it). Rerun the table with --resume never into a new --out folder to get it.")
        return
    done = 0
    for u in cr.units:
        path = run.npz_path(u)
        if not path.exists():
            continue
        try:
            arrays = read_arrays(path)
        except (OSError, ValueError) as exc:
            cr.no_animation = f"{path.name}: unreadable ({exc})"
            continue
        why = check_arrays(arrays, u, path.name)
        if why:
            cr.no_animation = f"animation unavailable: {why}"
            continue
        for b in range(len(arrays["sequence_ids"])):
            root_err, facing_err = root_diagnostics(arrays, b)
            sid = str(arrays["sequence_ids"][b])
            cr.diag[sid] = SequenceDiag(facing_err_mean=float(facing_err.mean()), root_err_mean=float(root_err.mean()),
                                        backwards_fraction=float((facing_err > 90.0).mean()))
            if done < sequences:
                name = f"anim__{_safe(u['unit_id'])}__{b}.{fmt}"
                cr.facing_curves.append((sid, arrays["t"][b].astype(np.float64), facing_err))
                cr.animations.append((sid, name))
                jobs.append(AnimationJob(str(path), b, str(img_dir / name), f"{cr.prior} {_cell_text(cr.cell)}",
                                         body_spec or run_body(run, cr.table), ANIMATION_SIZE, animation_fps,
                                         cell_report=cr, sequence_id=sid))
                done += 1


_WORKER_CACHE: dict = {}  # per process: body models and skinned ground truths


def render_animation(npz: str, index: int, out: str, title: str, body_spec: str, size, fps: float) -> float:
    """Skin, render and write one animation; returns the sequence's mean V2V error (mm)."""
    from benchmark.report.animate import animate, sequence_motion
    from benchmark.unit_arrays import read_arrays

    body = _body(body_spec, _WORKER_CACHE.setdefault("bodies", {}))
    motion = sequence_motion(read_arrays(npz), index, body, _WORKER_CACHE.setdefault("gt", {}))
    animate(motion, body, out, title=title, size=tuple(size), fps=fps)
    return float(motion.v2v_mm.mean())


def _init_worker() -> None:
    import torch

    torch.set_num_threads(1)


def run_animation_jobs(jobs: list, workers: int = 1) -> None:
    """Render ``jobs`` here (``workers`` <= 1) or in that many spawned processes; a job that fails
    leaves its cell without that animation and says why on the page."""
    if not jobs:
        return
    results = {}
    if workers <= 1 or len(jobs) == 1:
        for k, job in enumerate(jobs):
            try:
                results[k] = (render_animation(*job.payload()), None)
            except Exception as exc:  # one bad unit must not take the report down
                results[k] = (None, f"{type(exc).__name__}: {exc}")
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_init_worker) as pool:
            futures = {k: pool.submit(render_animation, *job.payload()) for k, job in enumerate(jobs)}
            for k, fut in futures.items():
                try:
                    results[k] = (fut.result(), None)
                except Exception as exc:
                    results[k] = (None, f"{type(exc).__name__}: {exc}")
    for k, job in enumerate(jobs):
        v2v, error = results[k]
        cr = job.cell_report
        if error is None:
            cr.diag[job.sequence_id].v2v_mm = v2v
            continue
        log.error("report: animation of %s (%s) failed: %s", job.sequence_id, Path(job.npz).name, error)
        cr.animations = [(sid, name) for sid, name in cr.animations if name != Path(job.out).name]
        cr.facing_curves = [c for c in cr.facing_curves if c[0] != job.sequence_id]
        cr.no_animation = f"animation of {job.sequence_id} failed: {error}"


def run_body(run: RunFolder, table_name: str) -> str:
    for t in run.tables:
        if t["table"] == table_name:
            return t.get("body") or "anny"
    return "anny"


def _body(spec: str, cache: dict):
    if spec not in cache:
        from benchmark.body import get_body

        try:
            cache[spec] = get_body(spec, device="cpu")
        except (FileNotFoundError, ValueError) as exc:
            raise FileNotFoundError(f"report: the run used body model {spec!r}, which cannot be loaded here ({exc}); "
                                    "pass --body with its files, or --sequences 0 for a report without animations") from exc
    return cache[spec]


def _cell_text(cell: dict) -> str:
    from benchmark.writers import cell_label

    return cell_label(cell, list(cell))


# ------------------------------------------------------------------------------------ HTML parts
def _about(table: dict) -> str:
    prov = table.get("provenance") or {}
    git = prov.get("git") or {}
    versions = prov.get("versions") or {}
    items = [
        ("profile", f"{table.get('profile')}: {table.get('profile_description', '')}"),
        ("profile sizes", ", ".join(f"{k} {v}" for k, v in (table.get("profile_sizes") or {}).items())),
        ("comparable to full", table.get("comparable_to_full")),
        ("protocol", f"{table.get('protocol')} v{table.get('protocol_version')}"),
        ("data / body / seed", f"{table.get('data')} / {table.get('body')} / {table.get('seed')}"),
        ("sequences", ", ".join(table.get("sequences") or [])),
        ("units", ", ".join(f"{k} {v}" for k, v in (table.get("counts") or {}).items())),
        ("device", f"{prov.get('device', table.get('device'))} ({prov.get('cpu') or ''}{', ' + prov['gpu'] if prov.get('gpu') else ''})"),
        ("git", f"{git.get('revision')}{' (dirty)' if git.get('dirty') else ''}"),
        ("made", f"{prov.get('timestamp')}: {prov.get('command', '')}"),
        ("versions", ", ".join(f"{k} {v}" for k, v in versions.items())),
        ("std", table.get("std_definition")),
    ]
    rows = "".join(f"<tr><th>{_esc(k)}</th><td>{_esc(v)}</td></tr>" for k, v in items if v not in (None, ""))
    return f'<details class="about"><summary>Profile and provenance</summary><table class="kv">{rows}</table></details>'


def _metric_table(table: dict, metric: str, reports: dict, grid_keys: list) -> str:
    from benchmark.report.plots import paper_rows
    from benchmark.writers import ARROWS, cell_label, format_number, metric_label

    better = next((m.get("better") for m in table["metrics"] if m["name"] == metric), None)
    cells = table["rows"][0]["cells"]
    head = "".join(f"<th>{_esc(cell_label(c, grid_keys))}</th>" for c in cells)
    body = []
    for row in table["rows"]:
        tds = []
        for i, c in enumerate(row["cells"]):
            cr = reports[(row["prior"], i)]
            reason = c.get("na_reason") or (c.get("metric_na") or {}).get(metric)
            if c.get(metric) is None:
                tds.append(f'<td class="na" title="{_esc(reason or "no value")}"><a href="#{cr.anchor}">n/a</a></td>')
                continue
            std = c.get(f"{metric}_std")
            text = format_number(c[metric], metric) + (f" ± {format_number(std, metric)}" if std is not None else "")
            flag = ' <span class="bw" title="backwards fits in this cell">⟲</span>' if any(
                d.backwards for d in cr.diag.values()) else ""
            tds.append(f'<td><a href="#{cr.anchor}">{_esc(text)}</a>{flag}</td>')
        body.append(f"<tr><th>{_esc(row['prior'])}</th>{''.join(tds)}</tr>")
    for prior, values in paper_rows(table, metric).items():
        tds = "".join(f"<td>{'' if v is None else _esc(format_number(v, metric))}</td>" for v in values)
        body.append(f'<tr class="paper"><th>{_esc(prior)} (paper)</th>{tds}</tr>')
    arrow = ARROWS.get(better, "")
    return (f'<h3>{_esc(metric_label(metric))} {arrow}</h3><table class="results"><thead><tr><th>prior</th>{head}</tr>'
            f'</thead><tbody>{"".join(body)}</tbody></table>')


def _convergence(units: list) -> str:
    """The data term at the first and last logged steps (mean over the cell's units)."""
    first, last, prev = [], [], []
    for u in units:
        log_ = [e for e in (u.get("fit_log") or []) if "data_mm" in e]
        if len(log_) >= 2:
            first.append(log_[0]["data_mm"])
            last.append(log_[-1]["data_mm"])
            prev.append(log_[-2]["data_mm"])
    if not first:
        return ""
    f, lst, p = np.mean(first), np.mean(last), np.mean(prev)
    drop = (p - lst) / p * 100 if p else 0.0
    note = " still falling" if drop > 5 else ""
    return f"data {f:.0f}→{lst:.0f} mm ({drop:.0f}% in the last logged interval{note})"


def _diagnostics_table(table: dict, reports: dict, grid_keys: list) -> str:
    from benchmark.writers import cell_label

    cells = table["rows"][0]["cells"]
    head = "".join(f"<th>{_esc(cell_label(c, grid_keys))}</th>" for c in cells)
    body = []
    for row in table["rows"]:
        tds = []
        for i in range(len(cells)):
            cr = reports[(row["prior"], i)]
            lines = []
            if cr.diag:
                n_bw = sum(d.backwards for d in cr.diag.values())
                cls = "bad" if n_bw else "ok"
                lines.append(f'<span class="{cls}">{n_bw}/{len(cr.diag)} backwards</span>')
                lines.append(f"facing err {np.mean([d.facing_err_mean for d in cr.diag.values()]):.0f}°")
            elif cr.units:
                lines.append('<span class="muted">no stored fit</span>')
            conv = _convergence(cr.units)
            if conv:
                lines.append(_esc(conv))
            tds.append(f'<td><a href="#{cr.anchor}">{"<br>".join(lines) or "–"}</a></td>')
        body.append(f"<tr><th>{_esc(row['prior'])}</th>{''.join(tds)}</tr>")
    return ('<h3>Diagnostics</h3><p class="note">Backwards: the fit faces more than 90° away from the ground truth on '
            f'more than {BACKWARDS_FRACTION:.0%} of the output frames (from the stored fitted motion). Convergence: the '
            'fit\'s data term at its first and last logged steps.</p>'
            f'<table class="results diag"><thead><tr><th>prior</th>{head}</tr></thead><tbody>{"".join(body)}</tbody></table>')


def _figure(path: Path, caption: str, img_dir: Path) -> str:
    rel = f"img/{path.name}"
    return f'<figure><img src="{_esc(rel)}" alt="{_esc(caption)}"><figcaption>{_esc(caption)}</figcaption></figure>'


def _animation_section(table, reports, img_dir, plots, priors, cells, grid_keys) -> str:
    from benchmark.report.render import ERROR_MAX_MM
    from benchmark.writers import cell_label

    legend = img_dir / "error_scale.png"
    if not legend.exists():
        plots.error_legend(legend, ERROR_MAX_MM)
    parts = ['<h3>Animated fits</h3><p class="note">Each animation: front view (the camera faces the ground truth\'s '
             'mean facing direction, so a fit facing away shows its back) and side view, following the ground truth\'s '
             'root. Mesh: the fit on the output timeline (every k-th output frame, at the animation\'s rate), coloured by per-vertex distance to the ground-truth mesh; dark '
             'skeleton: the ground truth; black dots: the observed points, on their timestamps. A red header and border '
             'mark frames where the fit faces more than 90° away from the ground truth (BACKWARDS).</p>',
             f'<img class="legend" src="img/{legend.name}" alt="per-vertex error colour scale">']
    for p in priors:
        parts.append(f'<h4>{_esc(p)}</h4><div class="anims">')
        curves_by_cell = []
        for i, c in enumerate(cells):
            cr = reports[(p, i)]
            label = cell_label(c, grid_keys)
            if cr.animations:
                for sid, rel in cr.animations:
                    d = cr.diag.get(sid)
                    cap = f"{label}: {sid}" + (f", facing err {d.facing_err_mean:.0f}°, {'BACKWARDS' if d.backwards else 'forwards'}" if d else "")
                    parts.append(f'<figure class="anim"><a href="#{cr.anchor}"><img src="img/{_esc(rel)}" alt="{_esc(cap)}">'
                                 f'</a><figcaption>{_esc(cap)}</figcaption></figure>')
            elif c.get("na_reason"):
                parts.append(f'<div class="unavail"><b>{_esc(label)}</b>: n/a ({_esc(c["na_reason"])})</div>')
            else:
                parts.append(f'<div class="unavail"><b>{_esc(label)}</b>: {_esc(cr.no_animation or "not animated")}</div>')
            if cr.facing_curves:
                curves_by_cell.append((label, cr.facing_curves))
        parts.append("</div>")
        if curves_by_cell:
            path = img_dir / f"{_safe(Path(table.get('_file', table['table'])).stem)}__{_safe(p)}__facing.png"
            _facing_grid(curves_by_cell, path, p)
            parts.append(_figure(path, f"{p}: facing-direction error per output frame of the animated sequences "
                                       "(above the dashed 90° line: backwards)", img_dir))
    return "\n".join(parts)


def _facing_grid(curves_by_cell, path, prior):
    """One plot per prior: facing error per frame of every animated sequence, one line per cell."""
    from benchmark.report.plots import facing_plot

    curves = [(f"{label}: {sid}" if len(cc) > 1 else label, t, err) for label, cc in curves_by_cell for sid, t, err in cc]
    facing_plot(curves, path, prior)


def _breakdown_section(table, reports, metric_names, grid_keys) -> str:
    from benchmark.writers import cell_label, format_number, metric_label

    parts = ["<h3>Sequence breakdown</h3>"]
    for (prior, i), cr in reports.items():
        c = table["rows"][[r["prior"] for r in table["rows"]].index(prior)]["cells"][i]
        title = f"{prior}, {cell_label(c, grid_keys)}"
        parts.append(f'<div class="seq" id="{cr.anchor}"><h4>{_esc(title)}</h4>')
        if c.get("na_reason"):
            parts.append(f'<p class="note">n/a: {_esc(c["na_reason"])}</p>')
        if not cr.seq_rows:
            parts.append('<p class="note">No per-sequence rows (no unit file for this cell under units/).</p></div>')
            continue
        extra_keys = sorted({k for r in cr.seq_rows for k in r["extra"]})
        head = ("<th>sequence</th>" + "".join(f"<th>{_esc(metric_label(m))}</th>" for m in metric_names)
                + "<th>facing err (°)</th><th>backwards frames</th><th>V2V (mm, animated only)</th>"
                + "".join(f"<th>{_esc(k)}</th>" for k in extra_keys) + "<th>unit</th>")
        rows = []
        for r in cr.seq_rows:
            d = cr.diag.get(r["id"])
            tds = "".join(f"<td>{'n/a' if r[m] is None else _esc(format_number(r[m], m))}</td>" for m in metric_names)
            if d:
                cls = ' class="bad"' if d.backwards else ""
                tds += (f"<td{cls}>{d.facing_err_mean:.0f}</td><td{cls}>{d.backwards_fraction:.0%}</td>"
                        f"<td>{'–' if d.v2v_mm is None else f'{d.v2v_mm:.0f}'}</td>")
            else:
                tds += '<td class="muted" colspan="3">no stored fit</td>'
            tds += "".join(f"<td>{_esc(_short(r['extra'].get(k)))}</td>" for k in extra_keys)
            rows.append(f"<tr><th>{_esc(r['id'])}</th>{tds}<td class='muted'>{_esc(r['unit_id'])}</td></tr>")
        parts.append(f'<table class="results seqs"><thead><tr>{head}</tr></thead><tbody>{"".join(rows)}</tbody></table></div>')
    return "\n".join(parts)


def _short(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict):
        return ", ".join(f"{k} {_short(x)}" for k, x in v.items())
    return str(v)


CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:1.5em auto;max-width:1400px;padding:0 1em;color:#222}
h1{font-size:1.5em} h2{border-bottom:2px solid #ccc;padding-bottom:.2em;margin-top:2em} h3{margin-top:1.6em}
table.results{border-collapse:collapse;font-size:.85em;margin:.5em 0}
table.results th,table.results td{border:1px solid #ddd;padding:.25em .5em;text-align:right}
table.results th{background:#f4f4f4;text-align:left}
table.results tr.paper{font-style:italic;color:#666}
table.results a{color:inherit;text-decoration:none;border-bottom:1px dotted #999}
td.na{color:#999} .bad{color:#c0392b;font-weight:600} .ok{color:#27803b} .muted{color:#999}
.bw{color:#c0392b} .note{color:#555;font-size:.9em;max-width:70em}
table.kv{font-size:.85em;border-collapse:collapse} table.kv th{text-align:left;padding-right:1em;vertical-align:top}
figure{display:inline-block;margin:.5em 1em .5em 0;vertical-align:top} figcaption{font-size:.8em;color:#555;max-width:40em}
figure img{max-width:100%} .anims{display:flex;flex-wrap:wrap;gap:.3em}
figure.anim{margin:.2em} figure.anim figcaption{max-width:260px}
.unavail{border:1px dashed #bbb;color:#666;padding:.5em;font-size:.85em;max-width:260px;margin:.2em}
img.legend{display:block;margin:.3em 0}
.seq{margin-bottom:1em} nav a{margin-right:1em}
"""


def _page(run: RunFolder, sections: list, out: Path, seconds: float) -> str:
    nav = " ".join(f'<a href="#{_esc(_safe(Path(t.get("_file", t["table"])).stem))}">{_esc(Path(t.get("_file", t["table"])).stem)}</a>'
                   for t in run.tables)
    skipped = ""
    if run.skipped:
        skipped = ("<p class='note'>Skipped files: " + "; ".join(f"{_esc(p.name)} ({_esc(w)})" for p, w in run.skipped)
                   + "</p>")
    stamp = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    return (f"<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
            f"<meta name='viewport' content='width=device-width, initial-scale=1'>"
            f"<title>Benchmark report: {_esc(run.root.name)}</title><style>{CSS}</style></head><body>"
            f"<h1>Benchmark report: {_esc(run.root)}</h1>"
            f"<p class='note'>Made by <code>python -m benchmark report</code> on {stamp} in {seconds:.0f} s. "
            f"Every number links to its sequence breakdown.</p><nav>{nav}</nav>{skipped}"
            + "\n".join(sections) + "</body></html>\n")


__all__ = ["build_report", "DEFAULT_SEQUENCES"]
