"""``error-breakdown``: where a completion fit's joint error comes from
(:mod:`benchmark.tools.error_breakdown`)."""

from __future__ import annotations

from benchmark.commands.common import HelpFormatter


def add_command(sub) -> None:
    p = sub.add_parser("error-breakdown", help="split each completion cell's MPJPE: observed vs in-between frames, "
                                              "pelvis position vs pose, torso / legs / arms (mm)",
                       formatter_class=HelpFormatter)
    p.add_argument("run_dir", help="the --out folder of a table1 or sls run (its units/ are read)")
    p.add_argument("--prior", action="append", default=None, help="only this prior (repeatable)")
    p.add_argument("--body", default="anny", help="the body model the run used (anny | smpl | smplh | smplx[=PATH[:gender]])")

    def run(args) -> int:
        from benchmark.body import get_body
        from benchmark.tools.error_breakdown import format_rows, run_breakdown, units_folder

        units_folder(args.run_dir)  # a folder with no units/ is named before the body model loads
        rows = run_breakdown(args.run_dir, get_body(args.body), args.prior)
        print("MPJPE split (mm), means over every output frame of the cell; observed/between: output frames at / "
              "between observed instants; pelvis: root position error; aligned and the parts: pelvis-aligned")
        print(format_rows(rows))
        return 0

    p.set_defaults(func=run)
