"""The ``report`` sub-command."""

from __future__ import annotations

import argparse
import os


def _cmd_report(args) -> int:
    from benchmark.report import build_report

    index = build_report(args.run_dir, args.out, sequences=args.sequences, animation_format=args.format,
                         body_spec=args.body, animation_fps=args.animation_fps, workers=args.workers)
    files = [p for p in index.parent.rglob("*") if p.is_file()]
    size = sum(p.stat().st_size for p in files)
    print(f"wrote {index} ({len(files)} files, {size / 1e6:.1f} MB); open it in a browser (works offline)")
    return 0


def add_report_command(sub) -> None:
    from benchmark.report.build import ANIMATION_FPS, DEFAULT_SEQUENCES

    p = sub.add_parser("report", help="HTML report of a finished run: tables, plots, animated fits",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run folder (the --out of 'run': <table>.json + units/)")
    p.add_argument("--out", default=None, help="report folder (default: RUN_DIR/report)")
    p.add_argument("--sequences", type=int, default=DEFAULT_SEQUENCES,
                   help="sequences to animate per prior x cell (0: no animations)")
    p.add_argument("--format", choices=["webp", "gif"], default="webp", help="animation format")
    p.add_argument("--animation-fps", type=float, default=ANIMATION_FPS,
                   help="animation frame rate (30: every output frame, about twice the size)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                   help="processes rendering the animations")
    p.add_argument("--body", default=None, help="body model to re-skin the stored fits (default: the run's)")
    p.set_defaults(func=_cmd_report)
