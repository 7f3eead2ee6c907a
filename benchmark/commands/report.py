"""``report``: the HTML report of a finished run (:func:`benchmark.report.build_report`)."""

from __future__ import annotations

import os
from pathlib import Path

from benchmark.commands.common import HelpFormatter

def check_report_args(run_dir, out) -> Path:
    """Before anything loads or renders: RUN_DIR is a run folder (a file, such as RUN/table1.json, is
    named as such, with the fix); --out (default RUN_DIR/report) is a writable folder, neither the
    run folder nor around it (a folder inside it is fine: the default), and holds nothing but an
    earlier report (recognised by its marker: :mod:`benchmark.report.out_folder`), which the
    report replaces. Returns the output folder."""
    from benchmark.core.outdir import check_not_overlapping, check_out_dir
    from benchmark.report.out_folder import check_report_folder
    from benchmark.report.run_folder import check_run_folder

    root = check_run_folder(run_dir)
    folder = Path(out) if out is not None else root / "report"
    check_not_overlapping(folder, [("run folder", root)], allow_inside=True)
    check_report_folder(folder)  # nothing but an earlier report, as its marker records it
    return check_out_dir(folder, min_free_bytes=1 << 20)


def _cmd_report(args) -> int:
    from benchmark.report import build_report

    out = check_report_args(args.run_dir, args.out)
    index = build_report(args.run_dir, out, sequences=args.sequences, animation_format=args.format,
                         body_spec=args.body, animation_fps=args.animation_fps, workers=args.workers)
    files = [p for p in index.parent.rglob("*") if p.is_file()]
    size = sum(p.stat().st_size for p in files)
    print(f"wrote {index} ({len(files)} files, {size / 1e6:.1f} MB); open it in a browser (works offline)")
    return 0


def add_command(sub) -> None:
    from benchmark.core import argtypes as at
    from benchmark.report.build import ANIMATION_FPS, DEFAULT_SEQUENCES

    p = sub.add_parser("report", help="HTML report of a finished run: tables, plots, animated fits",
                       formatter_class=HelpFormatter)
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run folder (the --out of 'run': <table>.json + units/)")
    p.add_argument("--out", default=None, help="report folder (default: RUN_DIR/report)")
    p.add_argument("--sequences", type=at.non_negative_int, default=DEFAULT_SEQUENCES,
                   help="sequences to animate per prior x cell (0: no animations)")
    p.add_argument("--format", choices=["webp", "gif"], default="webp", help="animation format")
    p.add_argument("--animation-fps", type=at.Number(float, 1.0, 30.0, unit="frames per second"),
                   default=ANIMATION_FPS, help="animation frame rate (30: every output frame, about twice the size)")
    p.add_argument("--workers", type=at.jobs, default=min(2, os.cpu_count() or 1),
                   help="processes rendering the animations")
    p.add_argument("--body", default=None, help="body model to re-skin the stored fits (default: the run's)")
    p.set_defaults(func=_cmd_report)
