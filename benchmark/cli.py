"""Command line: ``python -m benchmark <command>`` (see ``--help``).

:func:`main` builds the parser from :mod:`benchmark.commands` (one module per command), runs the
command and turns every error into one line (:func:`error_message`)."""

from __future__ import annotations

import argparse
import errno
import logging
import sys
import traceback

from benchmark.commands.common import HelpFormatter


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``python -m benchmark``: one sub-command per module of :mod:`benchmark.commands`
    (each adds its parser with ``add_command``), in the order of ``--help``."""
    from benchmark.commands import (check_prior, compare, complete, data, describe, device_check, encoder_check,
                                    error_breakdown, export_onnx, fit_check, list as list_command, merge_rows, perf,
                                    report, run, train, train_report)

    parser = argparse.ArgumentParser(
        prog="python -m benchmark",
        description="Reference benchmark harness for human motion priors.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging (and tracebacks on errors)")
    parser.add_argument("--debug", action="store_true", help="print the traceback of an error")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for command in (list_command, data, perf, complete, run, describe, check_prior, train, export_onnx, compare,
                    merge_rows, fit_check, error_breakdown, encoder_check, train_report, report, device_check):
        command.add_command(sub)
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
    if args.debug:  # a failed work unit's traceback (benchmark.run.runner logs it at DEBUG level only)
        logging.getLogger("benchmark.run.runner").setLevel(logging.DEBUG)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0 if args.command is None else 2
    from benchmark.core.interrupts import exit_code, sigint_once, sigterm_raises, stop_message

    empty = [opt for opt in ("out", "out_dir") if isinstance(getattr(args, opt, None), str) and not getattr(args, opt).strip()]
    if empty:  # `--out "$DIR"` with DIR unset: never the current folder
        print(f"error: --{empty[0].replace('_', '-')} '': empty; give a folder path (or the file the command writes), "
              "e.g. --out runs/mytable", file=sys.stderr)
        return 2

    try:
        # SIGTERM unwinds like Ctrl-C: workers stopped, temp files removed, --out unlocked; a second
        # Ctrl-C or SIGTERM while it unwinds is ignored
        with sigterm_raises(), sigint_once():
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


def console_main() -> None:
    """``python -m benchmark`` and the ``motion-benchmark`` script: :func:`main`, then exit with its
    code. Once a run has stopped on Ctrl-C or SIGTERM and printed its line, more of them are ignored,
    so that the interpreter's exit (its atexit hooks) is not cut short with a traceback."""
    import signal

    from benchmark.core.interrupts import EXIT_SIGINT, EXIT_SIGTERM

    code = main()
    if code in (EXIT_SIGINT, EXIT_SIGTERM):
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise SystemExit(code)
