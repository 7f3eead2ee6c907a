"""``perf``: the speed of the hot paths against the baselines a user would pick
(:mod:`benchmark.tools.perf`)."""

from __future__ import annotations

from benchmark.commands.common import HelpFormatter


def _cmd_perf(args) -> int:
    from benchmark.commands.common import resolve_device
    from benchmark.tools.perf import run_perf

    run_perf(device=resolve_device(args.device), quick=not args.full, out=args.out, parts=args.only)
    return 0


def add_command(sub) -> None:
    p = sub.add_parser("perf", help="speed of the hot paths (Chamfer, point-to-surface, evaluation, skinning, fit "
                                    "steps) against the baselines a user would pick, measured side by side",
                       formatter_class=HelpFormatter)
    p.add_argument("--device", default="cpu", help="cpu, or cuda (adds the tiled-vs-torch.cdist comparison)")
    p.add_argument("--full", action="store_true", help="more frames per measurement (slower)")
    p.add_argument("--out", default="perf", help="folder for perf.md and perf.json")
    p.add_argument("--only", nargs="+", default=None,
                   choices=["chamfer", "surface", "evaluation", "skinning", "adam", "soft-chamfer", "cuda", "plateau",
                            "lists"],
                   help="run only these parts (plateau, a quick table1 descent with and without the held sequences "
                        "kept, and lists, one quick table1 unit's nearest-neighbour searches with and without "
                        "neighbour lists: minutes each, run only when named)")
    p.set_defaults(func=_cmd_perf)
