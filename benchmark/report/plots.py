"""The report's plots (matplotlib, headless Agg, PNG).

- :func:`sweep_plots`: a metric against each numeric grid axis, one line per prior (error bars: the
  cell's 95 % bootstrap interval where the table has one, else the std over sequences), one panel
  per value of the other axes; the paper's numbers, where the spec has them, as dashed lines of
  the prior's colour. Table1: against points per frame (a panel per fps)
  and against fps (a panel per point count); denoise: against σ (a panel per mode); inbetween:
  against the gap; sls: against p and against f (its sweep codes ``p100``, ``f20`` split into a
  letter and a number). A grid without a numeric axis gets a bar chart.
- :func:`spread_plot`: per-sequence values of a metric per cell and prior (strip plot, mean marked).
- :func:`facing_plot`: facing-direction error per output frame of the animated sequences.
- :func:`error_legend`: the colour scale of the animations.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

_CODE = re.compile(r"^([A-Za-z]+)(\d+(?:\.\d+)?)$")


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def prior_colours(priors: list) -> dict:
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    return {p: cmap(i % 10) for i, p in enumerate(priors)}


def _number(v):
    if isinstance(v, bool):
        return None
    if isinstance(v, (int, float)):
        return float(v)
    return None


def _coords(table: dict) -> list[dict]:
    """Per cell (in the rows' order): {axis: value}, sweep codes split into (letter axis -> number)."""
    out = []
    for c in table["rows"][0]["cells"] if table["rows"] else []:
        coords = {}
        for k in table["grid"]:
            v = c[k]
            m = _CODE.match(str(v)) if _number(v) is None else None
            if m:
                coords[f"{k}:{m.group(1)}"] = float(m.group(2))
            else:
                coords[k] = v
        out.append(coords)
    return out


def paper_rows(table: dict, metric: str) -> dict:
    """The paper's numbers of ``metric``, prior -> list aligned with the table's cells (None where
    the paper has none). A paper column names a cell by its grid values joined by '/', in the
    order of the spec's grid; the table JSON may list its grid axes in another order, so every
    order of the axes is tried. Empty when no order places every column on a cell."""
    from itertools import permutations

    paper = table.get("paper") or {}
    values, columns = paper.get(metric), paper.get("columns") or []
    if not values or not table["rows"]:
        return {}
    cells = table["rows"][0]["cells"]
    cols = [tuple(part.strip() for part in str(c).split("/")) for c in columns]
    for keys in permutations(table["grid"]):
        labels = [tuple(str(c[k]) for k in keys) for c in cells]
        if all(col in labels for col in cols):
            out = {}
            for prior, numbers in values.items():
                if isinstance(numbers, list) and len(numbers) == len(cols):
                    row = [None] * len(cells)
                    for col, v in zip(cols, numbers):
                        row[labels.index(col)] = v
                    out[prior] = row
            return out
    return {}


def error_bars(cells: list, metric: str) -> np.ndarray:
    """``yerr`` (2 x cells: below, above the mean) of the cells' ``metric``: the distance to the ends
    of its interval (``<metric>_ci95``) where the cell has one, else ± its std; 0 without either."""
    out = np.zeros((2, len(cells)))
    for i, c in enumerate(cells):
        mean, ci = _val(c.get(metric)), c.get(f"{metric}_ci95")
        if not np.isfinite(mean):
            continue
        if ci is not None:
            out[:, i] = max(0.0, mean - float(ci[0])), max(0.0, float(ci[1]) - mean)
        elif f"{metric}_ci95" not in c:
            std = _val(c.get(f"{metric}_std"))
            out[:, i] = 0.0 if not np.isfinite(std) else std
    return out


def _save(fig, path: Path) -> Path:
    fig.savefig(path, dpi=100, bbox_inches="tight")
    _plt().close(fig)
    return path


def sweep_plots(table: dict, metric: str, out_dir: Path, colours: dict, stem: str) -> list[tuple[str, Path]]:
    """(caption, path) of the plots of ``metric`` against each numeric axis of the table's grid."""
    from benchmark.run.writers import has_intervals, metric_label

    plt = _plt()
    coords = _coords(table)
    if not coords:
        return []
    paper = paper_rows(table, metric)
    axes_all = list(dict.fromkeys(k for c in coords for k in c))
    numeric = [a for a in axes_all
               if len({c.get(a) for c in coords if a in c}) > 1 and all(_number(c[a]) is not None for c in coords if a in c)]
    out = []
    for x_axis in numeric:
        others = [a for a in axes_all if a != x_axis and all(a in c for c in coords if x_axis in c)]
        panel_keys = sorted({tuple(c[a] for a in others) for c in coords if x_axis in c},
                            key=lambda t: [(0, _number(v), "") if _number(v) is not None else (1, 0.0, str(v)) for v in t])
        n = len(panel_keys)
        fig, axs = plt.subplots(1, n, figsize=(3.6 * n + 0.6, 3.2), squeeze=False, sharey=True)
        for ax, pk in zip(axs[0], panel_keys):
            idx = [i for i, c in enumerate(coords) if x_axis in c and tuple(c[a] for a in others) == pk]
            idx.sort(key=lambda i: coords[i][x_axis])
            xs = np.array([coords[i][x_axis] for i in idx], dtype=float)
            for row in table["rows"]:
                p = row["prior"]
                ys = np.array([_val(row["cells"][i].get(metric)) for i in idx], dtype=float)
                es = error_bars([row["cells"][i] for i in idx], metric)
                if np.isfinite(ys).any():
                    ax.errorbar(xs, ys, yerr=np.nan_to_num(es), color=colours[p], marker="o", ms=4, lw=1.5, capsize=2,
                                label=p)
                if p in paper:
                    py = np.array([_val(paper[p][i]) for i in idx], dtype=float)
                    if np.isfinite(py).any():
                        ax.plot(xs, py, color=colours[p], ls="--", lw=1.2, marker="x", ms=4, label=f"{p} (paper)")
            if xs.min() > 0 and xs.max() / xs.min() >= 10:
                ax.set_xscale("log")
            elif xs.min() == 0 and xs.max() >= 100:
                ax.set_xscale("symlog", linthresh=max(1.0, float(np.sort(xs)[1]) if len(xs) > 1 else 1.0))
            ax.set_xticks(xs)
            ax.set_xticklabels([f"{v:g}" for v in xs])
            ax.set_xlabel(_axis_label(x_axis))
            ax.set_title(", ".join(f"{_axis_label(a)} = {v}" for a, v in zip(others, pk)) or table["table"], fontsize=10)
            ax.grid(alpha=0.3)
        lows = [v for ax in axs[0] for line in ax.get_lines() for v in np.asarray(line.get_ydata(), float) if v > 0]
        if lows and max(lows) / min(lows) > 20:  # a few failed fits would flatten every other line
            for ax in axs[0]:
                ax.set_yscale("log")
        axs[0][0].set_ylabel(metric_label(metric))
        handles, labels = axs[0][-1].get_legend_handles_labels()
        if handles:
            fig.legend(handles, labels, loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=8, frameon=False)
        fig.tight_layout()
        path = _save(fig, out_dir / f"{stem}__{metric}__vs_{_safe(x_axis)}.png")
        out.append((f"{metric_label(metric)} against {_axis_label(x_axis)}"
                    + (f", one panel per {', '.join(_axis_label(a) for a in others)}" if others else "")
                    + ("; dashed: the paper's numbers" if paper else "")
                    + ("; error bars: the 95 % bootstrap interval over sequences" if has_intervals(table)
                       else "; error bars: ± std over sequences"), path))
    if not numeric:
        out.append(_bars(table, metric, out_dir, colours, stem))
    return out


def _bars(table, metric, out_dir, colours, stem):
    from benchmark.run.writers import cell_label, metric_label

    plt = _plt()
    keys = list(table["grid"])
    cells = table["rows"][0]["cells"]
    fig, ax = plt.subplots(figsize=(max(4.0, 1.2 * len(cells) * max(1, len(table["rows"])) / 3), 3.2))
    width = 0.8 / max(1, len(table["rows"]))
    for j, row in enumerate(table["rows"]):
        ys = [_val(c.get(metric)) for c in row["cells"]]
        es = error_bars(row["cells"], metric)
        ax.bar(np.arange(len(cells)) + j * width, np.nan_to_num(ys), width, yerr=np.nan_to_num(es),
               color=colours[row["prior"]], label=row["prior"])
    ax.set_xticks(np.arange(len(cells)) + width * (len(table["rows"]) - 1) / 2)
    ax.set_xticklabels([cell_label(c, keys) for c in cells])
    ax.set_ylabel(metric_label(metric))
    ax.legend(fontsize=8, frameon=False, loc="center left", bbox_to_anchor=(1.0, 0.5))
    fig.tight_layout()
    return (f"{metric_label(metric)} per cell (n/a cells left empty)", _save(fig, out_dir / f"{stem}__{metric}__bars.png"))


def spread_plot(table: dict, metric: str, seq_values: dict, out_dir: Path, colours: dict, stem: str):
    """Strip plot: ``seq_values[(prior, cell index)]`` = per-sequence values; mean as a bar."""
    from benchmark.run.writers import cell_label, metric_label

    plt = _plt()
    keys = list(table["grid"])
    cells = table["rows"][0]["cells"]
    priors = [r["prior"] for r in table["rows"]]
    fig, ax = plt.subplots(figsize=(max(5.0, 0.5 * len(cells) * len(priors) / 2 + 2), 3.4))
    width = 0.8 / max(1, len(priors))
    rng = np.random.default_rng(0)
    for j, p in enumerate(priors):
        for i in range(len(cells)):
            vals = np.array([v for v in seq_values.get((p, i), []) if v is not None], dtype=float)
            if not len(vals):
                continue
            x0 = i + (j - (len(priors) - 1) / 2) * width
            ax.scatter(x0 + rng.uniform(-width / 4, width / 4, len(vals)), vals, s=10, color=colours[p], alpha=0.8,
                       label=p if i == 0 or not ax.get_legend_handles_labels()[1].count(p) else None, zorder=3)
            ax.plot([x0 - width / 2.5, x0 + width / 2.5], [vals.mean()] * 2, color=colours[p], lw=2, zorder=4)
    ax.set_xticks(range(len(cells)))
    ax.set_xticklabels([cell_label(c, keys) for c in cells], rotation=20, ha="right", fontsize=8)
    ax.set_ylabel(metric_label(metric))
    if all(v is None or v > 0 for vals in seq_values.values() for v in vals) and seq_values:
        flat = [v for vals in seq_values.values() for v in vals if v is not None]
        if flat and max(flat) / max(min(flat), 1e-12) > 30:
            ax.set_yscale("log")
    ax.grid(alpha=0.3, axis="y")
    handles, labels = ax.get_legend_handles_labels()
    uniq = dict(zip(labels, handles))
    ax.legend(uniq.values(), uniq.keys(), fontsize=8, frameon=False, loc="center left", bbox_to_anchor=(1.0, 0.5))
    fig.tight_layout()
    return (f"{metric_label(metric)} per sequence (dots) and its mean (bar), per cell and prior",
            _save(fig, out_dir / f"{stem}__{metric}__spread.png"))


def facing_plot(curves: list, path: Path, title: str):
    """``curves``: [(label, t (T,), facing error (T,) degrees)], with the 90° line dashed."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.2, 2.4))
    for label, t, err in curves:
        ax.plot(t, err, lw=1.2, label=label)
    ax.axhline(90.0, color="#d7191c", ls="--", lw=1)
    ax.set_ylim(0, 180)
    ax.set_yticks([0, 45, 90, 135, 180])
    ax.set_xlabel("time (s)", fontsize=8)
    ax.set_ylabel("facing error (°)", fontsize=8)
    ax.set_title(title, fontsize=9)
    ax.tick_params(labelsize=7)
    if len(curves) > 1:
        ax.legend(fontsize=6, frameon=False, loc="center left", bbox_to_anchor=(1.0, 0.5))
    ax.grid(alpha=0.3)
    return _save(fig, path)


def error_legend(path: Path, max_mm: float) -> Path:
    plt = _plt()
    import matplotlib as mpl

    fig, ax = plt.subplots(figsize=(3.2, 0.55))
    fig.colorbar(mpl.cm.ScalarMappable(norm=mpl.colors.Normalize(0, max_mm), cmap="turbo"), cax=ax,
                 orientation="horizontal")
    ax.set_xlabel(f"per-vertex error (mm; ≥ {max_mm:g} shown as {max_mm:g})", fontsize=8)
    ax.tick_params(labelsize=7)
    return _save(fig, path)


def _val(v):
    return np.nan if v is None else float(v)


def _axis_label(axis: str) -> str:
    name, _, code = axis.partition(":")
    return {"points": "points per frame", "fps": "fps", "sigma": "σ (rad)", "gap": "gap (frames)",
            "mode": "mode"}.get(name, f"{name} {code}".strip() if code else name)


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", text)


__all__ = ["error_legend", "facing_plot", "prior_colours", "spread_plot", "sweep_plots"]
