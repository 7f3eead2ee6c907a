"""``python -m benchmark train-report``: the training and validation curves of the embedded priors.

Every embedded checkpoint ships with its training record (``priors/weights/NAME.json``, written by
:mod:`priors.training`). A record holds one or more loss histories: lists of ``{"step": ..., loss
parts...}`` entries, every ``log_every`` steps, at any depth (a recipe with two phases has two,
e.g. ``phase1/history``); entries may carry validation parts (``val_<part>``, logged every
``--val-every`` steps since ``train --val-every``) and the wall time so far (``wall_s``). The
record's ``final_val`` (or a phase's) is the validation loss at the end.

The report plots, per prior and per history, every loss part against the step (training solid,
validation dashed, the final validation value as a marker), and writes ``OUT/index.html`` (no
JavaScript, no CDN) with a summary table: steps, wall time, final training and validation loss,
checkpoint size. Records without any history are listed with the reason.
"""

from __future__ import annotations

import html
import json
from pathlib import Path

from priors.training import WEIGHTS_DIR


def histories(record, path: str = "") -> list[tuple[str, list[dict]]]:
    """(path, entries) of every loss history in a training record, depth first, in key order."""
    found = []
    if isinstance(record, dict):
        for key, value in record.items():
            found += histories(value, f"{path}/{key}" if path else key)
    elif isinstance(record, list) and record and all(isinstance(e, dict) and "step" in e for e in record):
        found.append((path, record))
    return found


def final_values(record, path: str) -> dict:
    """The validation values at the end of the history at ``path``: its phase's ``final_val`` (or the record's)."""
    keys = path.split("/")
    if len(keys) == 1:  # a top-level history: the record's final_val belongs to the record's own "history"
        val = record.get("final_val") if path == "history" else None
    else:
        parent = record
        for key in keys[:-1]:
            parent = parent.get(key, {}) if isinstance(parent, dict) else {}
        val = parent.get("final_val") if isinstance(parent, dict) else None
    return val if isinstance(val, dict) else {}


def _plot(name: str, record: dict, groups: list, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(groups), figsize=(5.2 * len(groups), 3.6), squeeze=False)
    for ax, (path, entries) in zip(axes[0], groups):
        steps = [e["step"] for e in entries]
        parts = [k for k in entries[0] if k not in ("step", "wall_s") and not k.startswith("val_")
                 and isinstance(entries[0][k], (int, float))]
        for i, part in enumerate(parts):
            color = f"C{i % 10}"
            ax.plot(steps, [e.get(part) for e in entries], color=color, label=part)
            val = [(e["step"], e[f"val_{part}"]) for e in entries if f"val_{part}" in e]
            if val:
                ax.plot(*zip(*val), color=color, linestyle="--", marker="o", markersize=3, label=f"val {part}")
            final = final_values(record, path).get(part)
            if isinstance(final, (int, float)):
                ax.plot([steps[-1]], [final], color=color, marker="*", markersize=10, linestyle="none")
        positive = all(isinstance(e.get(p), (int, float)) and e[p] > 0 for e in entries for p in parts)
        if positive:
            ax.set_yscale("log")
        ax.set_title(f"{name}: {path}", fontsize=9)
        ax.set_xlabel("step")
        ax.legend(fontsize=6, ncol=2)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(png, dpi=90)
    plt.close(fig)


def _loss(values) -> str:
    return f"{values['loss']:.4g}" if isinstance(values, dict) and isinstance(values.get("loss"), (int, float)) else "–"


TITLE = "<title>Training report</title>"
OUTPUT_ENTRIES = ("index.html", "img")  # what the report writes into --out


def check_train_report_out(out: str | Path, weights_dir: str | Path) -> Path:
    """Before any plot: --out is a writable folder, not the weights folder nor around it, holding
    nothing but an earlier training report (its index.html and img/, which are replaced)."""
    from benchmark.core.outdir import OutDirError, check_not_overlapping, check_out_dir

    out = Path(out)
    check_not_overlapping(out, [("--weights-dir", weights_dir)], allow_inside=True)
    if out.is_dir():
        entries = sorted(p.name for p in out.iterdir())
        index = out / "index.html"
        ours = index.is_file() and TITLE in index.read_text(encoding="utf-8", errors="replace")[:500]
        foreign = [n for n in entries if n not in OUTPUT_ENTRIES]
        if entries and (not ours or foreign):
            shown = f" ({', '.join(foreign[:3])})" if foreign else ""
            raise OutDirError(f"--out {out}: holds files train-report did not write{shown}; it replaces its folder's "
                              "index.html and img/, so nothing was written: choose an empty or new --out")
    return check_out_dir(out, min_free_bytes=1 << 20)


def build_train_report(weights_dir: str | Path = WEIGHTS_DIR, out: str | Path = "runs/train-report") -> Path:
    weights_dir, out = Path(weights_dir), Path(out)
    records = sorted(weights_dir.glob("*.json"))
    if not records:
        raise FileNotFoundError(f"{weights_dir}: no training record (NAME.json) found; train a prior with "
                                "`python -m benchmark train NAME` or point --weights-dir at the folder of its weights")
    out = check_train_report_out(out, weights_dir)
    (out / "img").mkdir(parents=True, exist_ok=True)
    rows, figures = [], []
    for path in records:
        name = path.stem
        try:
            record = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            rows.append((name, "unreadable record", f"{path}: {exc}", "", "", "", ""))
            continue
        groups = histories(record)
        wall = record.get("train_wall_s")
        ckpt = record.get("checkpoint_bytes")
        steps = record.get("steps")
        steps = steps.get("total", steps) if isinstance(steps, dict) else steps
        if not groups:
            rows.append((name, str(steps), "–" if wall is None else f"{wall:.0f}", "–", "–",
                         "–" if ckpt is None else f"{ckpt / 1e6:.1f}", "no loss history in the record (trained before "
                         "records kept one): retrain to get curves"))
            continue
        png = out / "img" / f"{name}.png"
        _plot(name, record, groups, png)
        figures.append((name, png.relative_to(out).as_posix()))
        main = next((g for g in groups if g[0] == "history"), groups[-1])  # the record's own, else the last phase
        rows.append((name, str(steps), "–" if wall is None else f"{wall:.0f}", _loss(main[1][-1]),
                     _loss(final_values(record, main[0])), "–" if ckpt is None else f"{ckpt / 1e6:.1f}",
                     ", ".join(p for p, _ in groups)))
    head = ("prior", "steps", "train wall (s)", "final train loss", "final val loss", "checkpoint (MB)", "histories")
    table = "<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>" + "".join(
        "<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows) + "</table>"
    imgs = "".join(f'<h2>{html.escape(n)}</h2><img src="{src}" alt="{html.escape(n)} training curves">' for n, src in figures)
    page = (f"<!doctype html><meta charset='utf-8'>{TITLE}<h1>Training report: {html.escape(str(weights_dir))}</h1>"
            "<p>Loss parts against the step: training (solid, mean over each logging interval), validation (dashed), "
            "the final validation value (star).</p>" + table + imgs)
    (out / "index.html").write_text(page)
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for row in rows:
        print("| " + " | ".join(str(c) for c in row) + " |")
    print(f"wrote {out / 'index.html'}")
    return out / "index.html"
