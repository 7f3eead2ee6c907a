"""``device-check``: every table's smoke profile on one device, each (table, prior) on its own, every
failure collected (:mod:`benchmark.tools.device_check`)."""

from __future__ import annotations

import sys
from pathlib import Path

from benchmark.commands.common import HelpFormatter


def add_command(sub) -> None:
    from benchmark.core import argtypes as at
    from benchmark.tools.device_check import TABLE_ORDER

    p = sub.add_parser("device-check", help="run every table's smoke profile on a device (default cuda), one prior at "
                                            "a time, and report every failure with where it happened; exit 1 on any",
                       formatter_class=HelpFormatter)
    p.add_argument("--device", default="cuda", help="cpu | cuda | cuda:N")
    p.add_argument("--table", action="append", default=None, choices=TABLE_ORDER,
                   help="a table to check (repeatable); default: all, table1 first")
    p.add_argument("--prior", action="append", default=None,
                   help="a prior to check (repeatable); default: each table's default priors")
    p.add_argument("--budget", type=at.positive_float, default=480.0,
                   help="seconds after which no new (table, prior) pair starts; the rest are reported as not run")
    p.add_argument("--out", default="runs/device-check", help="unit files, device-check.json and device-check.md")
    p.add_argument("--results", default=None,
                   help="folder of the committed smoke tables to compare with (default: the repository's results/)")

    def run(args) -> int:
        from benchmark.commands.common import resolve_device
        from benchmark.core.outdir import check_out_dir
        from benchmark.run.registry import get_prior_class
        from benchmark.tools.device_check import TABLE_ORDER, check_device, failed

        device = resolve_device(args.device)
        for name in args.prior or []:
            get_prior_class(name)
        out = check_out_dir(args.out)
        results = Path(args.results) if args.results else Path(__file__).resolve().parents[2] / "results"
        tables = [t for t in TABLE_ORDER if t in (args.table or TABLE_ORDER)]
        report = check_device(device, tables, args.prior, out, results, budget_s=args.budget)
        pairs = report["pairs"]
        ran = [p for p in pairs if p["status"] in ("ok", "failed")]
        bad = [p for p in ran if p["status"] == "failed"]
        print(f"{len(ran) - len(bad)} of {len(pairs)} pairs ran without error" + (f", {len(bad)} failed" if bad else "")
              + (f", {len(pairs) - len(ran)} not run (--budget {args.budget:g} s spent)" if len(ran) < len(pairs) else "")
              + f"; report: {out / 'device-check.md'}")
        if not ran and pairs:
            print("nothing was checked: give a larger --budget", file=sys.stderr)
            return 1
        return 1 if failed(report) else 0

    p.set_defaults(func=run)
