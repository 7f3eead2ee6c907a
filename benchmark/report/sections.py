"""The HTML parts of a table's section of the report (:mod:`benchmark.report.build`): provenance,
metric and diagnostics tables, figures, the animations and the per-sequence breakdown."""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from benchmark.report.cells import BACKWARDS_FRACTION, safe_name


def esc(x) -> str:
    return html.escape(str(x), quote=True)


def about_html(table: dict) -> str:
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
        ("interval", table.get("interval_definition")),
        ("paired comparison", table.get("paired_definition")),
    ]
    rows = "".join(f"<tr><th>{esc(k)}</th><td>{esc(v)}</td></tr>" for k, v in items if v not in (None, ""))
    return f'<details class="about"><summary>Profile and provenance</summary><table class="kv">{rows}</table></details>'


def metric_table(table: dict, metric: str, reports: dict, grid_keys: list) -> str:
    from benchmark.report.plots import paper_rows
    from benchmark.run.writers import (SIGNIFICANT_MARK, direction_text, cell_label, cell_text, format_number, has_intervals,
                                       interval_note, metric_label, significant_win)

    spec = next((m for m in table["metrics"] if m["name"] == metric), {})
    cells = table["rows"][0]["cells"]
    head = "".join(f"<th>{esc(cell_label(c, grid_keys))}</th>" for c in cells)
    body = []
    for row in table["rows"]:
        tds = []
        for i, c in enumerate(row["cells"]):
            cr = reports[(row["prior"], i)]
            reason = c.get("na_reason") or (c.get("metric_na") or {}).get(metric)
            if c.get(metric) is None:
                tds.append(f'<td class="na" title="{esc(reason or "no value")}"><a href="#{cr.anchor}">n/a</a></td>')
                continue
            text = cell_text(c, metric, mark=False)
            win = ""
            if significant_win(c, metric):
                p = c["paired"][metric]["no_prior"]
                tip = (f"better than no-prior: difference {format_number(p['diff'], metric)}, paired interval "
                       f"{format_number(p['ci95'][0], metric)} to {format_number(p['ci95'][1], metric)} excludes 0")
                win = f' <span class="win" title="{esc(tip)}">{SIGNIFICANT_MARK}</span>'
            flag = ' <span class="bw" title="backwards fits in this cell">⟲</span>' if any(
                d.backwards for d in cr.diag.values()) else ""
            tds.append(f'<td><a href="#{cr.anchor}">{esc(text)}</a>{win}{flag}</td>')
        body.append(f"<tr><th>{esc(row['prior'])}</th>{''.join(tds)}</tr>")
    for prior, values in paper_rows(table, metric).items():
        tds = "".join(f"<td>{'' if v is None else esc(format_number(v, metric))}</td>" for v in values)
        body.append(f'<tr class="paper"><th>{esc(prior)} (paper)</th>{tds}</tr>')
    arrow = direction_text(spec) if spec else ""
    note = f'<p class="note">{esc(interval_note(table).replace("`", ""))}</p>' if has_intervals(table) else ""
    return (f'<h3>{esc(metric_label(metric))} {arrow}</h3><table class="results"><thead><tr><th>prior</th>{head}</tr>'
            f'</thead><tbody>{"".join(body)}</tbody></table>{note}')


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


def diagnostics_table(table: dict, reports: dict, grid_keys: list) -> str:
    from benchmark.run.writers import cell_label

    cells = table["rows"][0]["cells"]
    head = "".join(f"<th>{esc(cell_label(c, grid_keys))}</th>" for c in cells)
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
                lines.append(esc(conv))
            tds.append(f'<td><a href="#{cr.anchor}">{"<br>".join(lines) or "–"}</a></td>')
        body.append(f"<tr><th>{esc(row['prior'])}</th>{''.join(tds)}</tr>")
    return ('<h3>Diagnostics</h3><p class="note">Backwards: the fit faces more than 90° away from the ground truth on '
            f'more than {BACKWARDS_FRACTION:.0%} of the output frames (from the stored fitted motion). Convergence: the '
            'fit\'s data term at its first and last logged steps.</p>'
            f'<table class="results diag"><thead><tr><th>prior</th>{head}</tr></thead><tbody>{"".join(body)}</tbody></table>')


def figure_html(path: Path, caption: str, img_dir: Path) -> str:
    rel = f"img/{path.name}"
    return f'<figure><img src="{esc(rel)}" alt="{esc(caption)}"><figcaption>{esc(caption)}</figcaption></figure>'


def animation_section(table, reports, img_dir, plots, priors, cells, grid_keys) -> str:
    from benchmark.report.render import ERROR_MAX_MM
    from benchmark.run.writers import cell_label

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
        parts.append(f'<h4>{esc(p)}</h4><div class="anims">')
        curves_by_cell = []
        for i, c in enumerate(cells):
            cr = reports[(p, i)]
            label = cell_label(c, grid_keys)
            if cr.animations:
                for sid, rel in cr.animations:
                    d = cr.diag.get(sid)
                    cap = f"{label}: {sid}" + (f", facing err {d.facing_err_mean:.0f}°, {'BACKWARDS' if d.backwards else 'forwards'}" if d else "")
                    parts.append(f'<figure class="anim"><a href="#{cr.anchor}"><img src="img/{esc(rel)}" alt="{esc(cap)}">'
                                 f'</a><figcaption>{esc(cap)}</figcaption></figure>')
            elif c.get("na_reason"):
                parts.append(f'<div class="unavail"><b>{esc(label)}</b>: n/a ({esc(c["na_reason"])})</div>')
            else:
                parts.append(f'<div class="unavail"><b>{esc(label)}</b>: {esc(cr.no_animation or "not animated")}</div>')
            if cr.facing_curves:
                curves_by_cell.append((label, cr.facing_curves))
        parts.append("</div>")
        if curves_by_cell:
            path = img_dir / f"{safe_name(Path(table.get('_file', table['table'])).stem)}__{safe_name(p)}__facing.png"
            _facing_grid(curves_by_cell, path, p)
            parts.append(figure_html(path, f"{p}: facing-direction error per output frame of the animated sequences "
                                       "(above the dashed 90° line: backwards)", img_dir))
    return "\n".join(parts)


def _facing_grid(curves_by_cell, path, prior):
    """One plot per prior: facing error per frame of every animated sequence, one line per cell."""
    from benchmark.report.plots import facing_plot

    curves = [(f"{label}: {sid}" if len(cc) > 1 else label, t, err) for label, cc in curves_by_cell for sid, t, err in cc]
    facing_plot(curves, path, prior)


def breakdown_section(table, reports, metric_names, grid_keys) -> str:
    from benchmark.run.writers import cell_label, format_number, metric_label

    parts = ["<h3>Sequence breakdown</h3>"]
    for (prior, i), cr in reports.items():
        c = table["rows"][[r["prior"] for r in table["rows"]].index(prior)]["cells"][i]
        title = f"{prior}, {cell_label(c, grid_keys)}"
        parts.append(f'<div class="seq" id="{cr.anchor}"><h4>{esc(title)}</h4>')
        if c.get("na_reason"):
            parts.append(f'<p class="note">n/a: {esc(c["na_reason"])}</p>')
        if not cr.seq_rows:
            parts.append('<p class="note">No per-sequence rows (no unit file for this cell under units/).</p></div>')
            continue
        extra_keys = sorted({k for r in cr.seq_rows for k in r["extra"]})
        head = ("<th>sequence</th>" + "".join(f"<th>{esc(metric_label(m))}</th>" for m in metric_names)
                + "<th>facing err (°)</th><th>backwards frames</th><th>V2V (mm, animated only)</th>"
                + "".join(f"<th>{esc(k)}</th>" for k in extra_keys) + "<th>unit</th>")
        rows = []
        for r in cr.seq_rows:
            d = cr.diag.get(r["id"])
            tds = "".join(f"<td>{'n/a' if r[m] is None else esc(format_number(r[m], m))}</td>" for m in metric_names)
            if d:
                cls = ' class="bad"' if d.backwards else ""
                tds += (f"<td{cls}>{d.facing_err_mean:.0f}</td><td{cls}>{d.backwards_fraction:.0%}</td>"
                        f"<td>{'–' if d.v2v_mm is None else f'{d.v2v_mm:.0f}'}</td>")
            else:
                tds += '<td class="muted" colspan="3">no stored fit</td>'
            tds += "".join(f"<td>{esc(_short(r['extra'].get(k)))}</td>" for k in extra_keys)
            rows.append(f"<tr><th>{esc(r['id'])}</th>{tds}<td class='muted'>{esc(r['unit_id'])}</td></tr>")
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
