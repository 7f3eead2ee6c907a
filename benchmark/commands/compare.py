"""``compare``: per-cell differences between two table JSONs (:mod:`benchmark.tools.compare`)."""

from __future__ import annotations

from benchmark.commands.common import HelpFormatter


def _cmd_compare(args) -> int:
    from benchmark.tools.compare import main_compare

    return main_compare(args.a, args.b, args.tol or [], priors=args.prior)


def add_command(sub) -> None:
    fmt = HelpFormatter
    p = sub.add_parser("compare", help="per-cell differences between two table JSONs", formatter_class=fmt)
    p.add_argument("a")
    p.add_argument("b")
    p.add_argument("--tol", action="append", metavar="METRIC=VALUE", help="tolerance in the metric's unit")
    p.add_argument("--prior", action="append", metavar="NAME",
                   help="compare only this prior's row (repeatable), e.g. a one-prior run against a whole reference table")
    p.set_defaults(func=_cmd_compare)
