"""``check-prior``: the conformance kit (:func:`benchmark.tools.conformance.check_prior`): an adapter
through a tiny table."""

from __future__ import annotations

from benchmark.commands.common import HelpFormatter

from benchmark.run.registry import make_adapter, registry


def _cmd_check_prior(args) -> int:
    from benchmark.tools.conformance import check_prior

    # input errors (an unknown prior, a weights file torch cannot read) are errors, exit 2, not a
    # conformance FAIL: construct once up front
    named, _, path = (args.weights or "").partition("=")
    if path and named.strip() in registry():  # the NAME=PATH form of run's --weights (a file name may hold '=')
        if named.strip() != args.name:
            raise ValueError(f"--weights {args.weights}: names prior {named.strip()!r}, but the prior checked is "
                             f"{args.name!r}; give --weights PATH (or {args.name}=PATH)")
        args.weights = path
    make_adapter(args.name, size=args.size, weights=args.weights, device="cpu")
    ok = check_prior(args.name, size=args.size, weights=args.weights)
    return 0 if ok else 1


def add_command(sub) -> None:
    from benchmark.core import argtypes as at

    fmt = HelpFormatter
    p = sub.add_parser("check-prior", help="conformance kit: run an adapter through a tiny table", formatter_class=fmt)
    p.add_argument("name")
    p.add_argument("--size", choices=["embedded", "paper"], default="embedded")
    p.add_argument("--weights", action=at.Once, default=None)
    p.set_defaults(func=_cmd_check_prior)
