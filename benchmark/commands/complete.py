"""``complete``: fit a prior to one capture and write the completed motion
(:func:`benchmark.tools.complete.run_complete`)."""

from __future__ import annotations

from benchmark.commands.common import HelpFormatter


def _cmd_complete(args) -> int:
    from benchmark.commands.common import resolve_device
    from benchmark.tools.complete import run_complete

    args.device = resolve_device(args.device)  # a wrong --device fails before anything loads, not in torch
    return 0 if run_complete(args) else 1


def add_command(sub) -> None:
    from benchmark.core import argtypes as at

    p = sub.add_parser("complete", help="fit a prior to one capture (scan folder, .npz motion or BVH) and write the "
                       "completed motion", formatter_class=HelpFormatter)
    p.add_argument("input", help="scan folder, harness/AMASS .npz, or .bvh")
    p.add_argument("--prior", required=True, help="prior name (python -m benchmark list priors)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--points", type=at.points, default=None, help="points per observed frame (default: all)")
    p.add_argument("--fps", type=at.fps, default=10.0, help="observed frames per second")
    p.add_argument("--window", type=at.positive_float, default=None,
                   help="seconds to complete (default: table1's 4 s; shorter if the input is)")
    p.add_argument("--start", type=at.non_negative_float, default=0.0, help="window start, seconds after the first frame")
    p.add_argument("--meshes", action="store_true", help="write one PLY mesh per output frame")
    p.add_argument("--no-preview", action="store_true", help="skip the animated preview")
    p.add_argument("--profile", default=None, help="steps and loss vertices from this profile (default: quick on CPU)")
    p.add_argument("--steps", type=at.positive_int, default=None, help="override the profile's step cap (table1 v6: each fit stops at its plateau)")
    p.add_argument("--device", default=None, help="cpu | cuda | cuda:N (default: cuda when available)")
    p.add_argument("--seed", type=at.seed, default=0)
    p.add_argument("--facing", choices=["observation", "search", "heading8"], default="observation",
                   help="how the fit finds the facing direction: 'observation' (table1 protocol v2) finds it on the "
                        "observation with the prior-free coarse search and turns the prior's start to it; 'search' runs "
                        "that search with the prior itself; 'heading8' is table1 protocol v1's T-pose yaw score")
    p.add_argument("--size", choices=["embedded", "paper"], default="embedded")
    p.add_argument("--weights", action=at.Once, default=None, help="checkpoint for --size paper")
    p.add_argument("--body", default="anny")
    p.add_argument("--up", choices=["y", "z"], default="y", help="scan folders: up axis")
    p.add_argument("--units", choices=["m", "cm", "mm"], default="m", help="scan folders: units")
    p.add_argument("--capture-fps", type=at.fps, default=None, help="scan folders without timestamps: their rate")
    p.add_argument("--force", action="store_true",
                   help="replace the output of an earlier complete in --out (a folder holding anything else is refused)")
    p.set_defaults(func=_cmd_complete)
