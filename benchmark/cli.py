"""Command line: ``python -m benchmark <command>`` (see ``--help``)."""

from __future__ import annotations

import argparse
import errno
import logging
import sys
import traceback


def _cmd_list(args) -> int:
    from benchmark.body import BODY_KINDS
    from benchmark.catalog import dataset_rows, prior_rows, profile_rows, protocol_rows, table_rows

    sections = [  # each built only when listed: `list tables` imports no prior
        ("tables", table_rows),
        ("priors", prior_rows),
        ("protocols", protocol_rows),
        ("datasets", dataset_rows),
        ("body models", lambda: list(BODY_KINDS.items())),
        ("profiles", profile_rows),
    ]
    for title, make_rows in sections:
        if args.what and args.what != title.split()[0]:
            continue
        rows = make_rows()
        print(f"{title}:")
        if not rows:
            print("  (none)")
        width = max((len(r[0]) for r in rows), default=0)
        for name, desc in rows:
            print(f"  {name.ljust(width)}  {desc}")
        print()
    return 0


def _cmd_data_convert(args) -> int:
    from benchmark.loaders.convert import convert

    body = None
    if args.body:
        from benchmark.body import get_body

        body = get_body(args.body)
    motion = convert(args.input, args.out, fps=args.fps, overwrite=args.force, body=body)
    print(f"wrote {args.out}: {motion.num_frames} frames, {motion.duration:.2f} s, {motion.fps:.1f} fps ({motion.source})"
          + (f", shape for body {body.name} ({body.shape_dim} parameters)" if body is not None else ""))
    return 0


def _cmd_data_build(args) -> int:
    from benchmark.synthetic.splits import build_split

    motions = build_split(args.split, seed=args.seed, rebuild=args.rebuild)
    total = sum(m.duration for m in motions)
    print(f"split {args.split!r}: {len(motions)} sequences, {total / 60:.1f} min of motion")
    return 0


def _cmd_data_make_scans(args) -> int:
    from benchmark.synthetic.scan_set import make_scan_set

    table_spec = None
    if args.table_capture is not None:
        from benchmark.catalog import load_table_spec

        table_spec = load_table_spec("table1")
    written = make_scan_set(args.out, sequences=args.ids if args.ids is not None else args.sequences, fps=args.fps,
                            points=args.points, noise_mm=args.noise_mm, holes=args.holes, duration=args.duration,
                            seed=args.seed, up=args.up, units=args.units, overwrite=args.force,
                            table_capture=args.table_capture, table_spec=table_spec)
    print(f"wrote {len(written)} scan sequences to {args.out}: {', '.join(p.name for p in written)}")
    return 0


def _cmd_perf(args) -> int:
    from benchmark.cli_run import resolve_device
    from benchmark.perf import run_perf

    run_perf(device=resolve_device(args.device), quick=not args.full, out=args.out, parts=args.only)
    return 0


def build_parser() -> argparse.ArgumentParser:
    from benchmark import argtypes as at

    parser = argparse.ArgumentParser(
        prog="python -m benchmark",
        description="Reference benchmark harness for human motion priors.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging (and tracebacks on errors)")
    parser.add_argument("--debug", action="store_true", help="print the traceback of an error")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("list", help="tables, priors, protocols, datasets, body models, profiles")
    p.add_argument("what", nargs="?", choices=["tables", "priors", "protocols", "datasets", "body", "profiles"], default=None)
    p.set_defaults(func=_cmd_list)

    p = sub.add_parser("data", help="motion data: convert files, build the synthetic splits")
    dsub = p.add_subparsers(dest="data_command", metavar="DATA_COMMAND")
    c = dsub.add_parser("convert", help="AMASS .npz or BVH -> the harness's motion .npz",
                        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    c.add_argument("input")
    c.add_argument("--out", required=True, help="output .npz (never overwritten without --force)")
    c.add_argument("--fps", type=at.fps, default=None, help="resample to this rate (default: keep the source rate)")
    c.add_argument("--force", action="store_true", help="overwrite an existing output file")
    c.add_argument("--body", default=None, help="store the motion's shape for this body model (anny | smpl | smplh | "
                   "smplx[=PATH[:gender]]): SMPL betas cut or zero-padded to the model's, another body's shape dropped")
    c.set_defaults(func=_cmd_data_convert)
    b = dsub.add_parser("build", help="generate (or check the cache of) a synthetic split",
                        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    b.add_argument("split", choices=["test", "train", "val"])
    b.add_argument("--seed", type=at.seed, default=None, help="override the split's seed")
    b.add_argument("--rebuild", action="store_true")
    b.set_defaults(func=_cmd_data_build)
    m = dsub.add_parser("make-scans", help="write captured-like scan folders (PLY + timestamps) from the synthetic test split",
                        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    m.add_argument("--out", required=True, help="output folder, one sub-folder per sequence")
    m.add_argument("--sequences", type=at.positive_int, default=4, help="how many test sequences (the profiles' selection)")
    m.add_argument("--ids", nargs="+", default=None, help="explicit test sequence ids instead of --sequences")
    m.add_argument("--fps", type=at.fps, default=60.0, help="capture rate")
    m.add_argument("--points", type=at.points, default=10000, help="points per frame (after the holes)")
    m.add_argument("--noise-mm", type=at.Number(float, 0.0, 1000.0, unit="mm"), default=3.0, help="Gaussian noise per axis, mm")
    m.add_argument("--holes", type=at.fraction, default=0.1, help="fraction of each frame's surface cut away")
    m.add_argument("--duration", type=at.positive_float, default=4.0,
                   help="seconds per sequence (at most the sequences' length, 4.4 s)")
    m.add_argument("--seed", type=at.seed, default=0)
    m.add_argument("--up", choices=["y", "z"], default="y", help="up axis to write")
    m.add_argument("--units", choices=["m", "cm", "mm"], default="m", help="units to write")
    m.add_argument("--table-capture", type=at.seed, default=None, metavar="SEED",
                   help="write the capture `run table1 --seed SEED` synthesises (its rate, points and seeds; "
                        "no noise, no holes): the scan path's check against the synthetic run")
    m.add_argument("--force", action="store_true",
                   help="replace the output of an earlier make-scans in --out (a folder holding anything else is refused)")
    m.set_defaults(func=_cmd_data_make_scans)

    p = sub.add_parser("perf", help="speed of the hot paths (Chamfer, point-to-surface, evaluation, skinning, fit "
                                    "steps) against the baselines a user would pick, measured side by side",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--device", default="cpu", help="cpu, or cuda (adds the tiled-vs-torch.cdist comparison)")
    p.add_argument("--full", action="store_true", help="more frames per measurement (slower)")
    p.add_argument("--out", default="perf", help="folder for perf.md and perf.json")
    p.add_argument("--only", nargs="+", default=None,
                   choices=["chamfer", "surface", "evaluation", "skinning", "adam", "cuda"], help="run only these parts")
    p.set_defaults(func=_cmd_perf)

    from benchmark.cli_run import add_run_commands

    add_run_commands(sub)
    from benchmark.fit_check import add_fit_check_command

    add_fit_check_command(sub)
    from benchmark.error_breakdown import add_error_breakdown_command

    add_error_breakdown_command(sub)
    from benchmark.train_report import add_train_report_command

    add_train_report_command(sub)
    from benchmark.report.cli import add_report_command

    add_report_command(sub)
    return parser


# exception types whose message the harness writes itself (file, field, fix): printed as they are
_OWN_ERRORS = (ValueError, FileNotFoundError, FileExistsError, KeyError, ImportError)


def error_message(exc: BaseException) -> str:
    """The text after ``error:`` for an exception: its message (a KeyError's without the quotes
    ``str()`` adds); an exception type the harness does not raise itself is named, and an OSError
    keeps the file it is about."""
    if isinstance(exc, KeyError) and len(exc.args) == 1 and isinstance(exc.args[0], str) and " " in exc.args[0]:
        text = exc.args[0]
    elif isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        text = f"{exc.filename}: {exc.strerror}"
        if isinstance(exc, PermissionError):
            text += "; fix the permissions or choose another path"
        elif exc.errno == errno.ENOSPC:
            text += "; free some space or choose another folder"
    else:
        text = str(exc).strip()
    if not (_is_own(exc) and text):
        text = f"{type(exc).__name__}: {text or 'no message'}"
    return text


def _is_own(exc: BaseException) -> bool:
    """An error whose message already names the file / field / fix: printed without its type."""
    return isinstance(exc, _OWN_ERRORS) or (isinstance(exc, OSError) and exc.filename is not None and bool(exc.strerror))


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    debug = bool(args.verbose or args.debug)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 0 if args.command is None else 2
    from benchmark.interrupts import exit_code, sigterm_raises, stop_message

    try:
        with sigterm_raises():  # SIGTERM unwinds like Ctrl-C: workers stopped, temp files removed, --out unlocked
            return int(args.func(args) or 0)
    except KeyboardInterrupt as exc:  # Ctrl-C (exit 130), or SIGTERM (Terminated, exit 143)
        print(stop_message(exc), file=sys.stderr)
        return exit_code(exc)
    except Exception as exc:  # every error is one line naming the file / field / fix; --debug shows where
        if debug:
            traceback.print_exc()
        text = error_message(exc)
        if not debug and not _is_own(exc):
            text += " (run with --debug for the traceback)"
        print(f"error: {text}", file=sys.stderr)
        return 2
