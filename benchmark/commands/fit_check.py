"""``fit-check``: fit a prior on one table1 cell and check the fit against its targets
(:mod:`benchmark.tools.fit_check`)."""

from __future__ import annotations

from benchmark.commands.common import HelpFormatter


def add_command(sub) -> None:
    from benchmark.core import argtypes as at

    p = sub.add_parser("fit-check", help="fit a prior (default no-prior) on one table1 cell and check the fit against "
                                         "its targets (MPJPE, Chamfer, root error, backwards, convergence); exit 1 on a miss",
                       formatter_class=HelpFormatter)
    p.add_argument("--prior", default="no-prior")
    p.add_argument("--points", type=at.points, default=10000, help="a table1 cell's points per frame")
    p.add_argument("--fps", type=at.fps, default=10, help="a table1 cell's observed frames per second")
    p.add_argument("--profile", default=None, help="default: quick on CPU, full on CUDA")
    p.add_argument("--device", default=None, help="cpu | cuda (default: cuda when available)")
    p.add_argument("--out", default="runs/fit-check", help="unit files and the one-cell table (a rerun resumes)")
    p.add_argument("--jobs", type=at.jobs, default=None, help="worker processes (default: the cores)")
    p.add_argument("--start-search", default=None, choices=("none", "limbs", "observation"),
                   help="override the table spec's objective.start_search (how per-frame priors search their start); "
                        "default: the spec's rule")
    p.add_argument("--multi-start", type=int, default=None, metavar="K",
                   help="fit the encoded priors from K starts each, keeping each sequence's lowest objective: the "
                        "candidate rule objective.multi_start (docs/protocol.md), not table1's protocol as committed")
    p.add_argument("--choose", default="end", choices=("end", "plateau"),
                   help="with --multi-start: keep each sequence's copy with the lowest objective at the end of every "
                        "copy's fit (end), or race the copies to their first plateau and go on with the lowest alone "
                        "(plateau): objective.multi_start.choose (docs/protocol.md)")
    p.add_argument("--around", default="encoded", choices=("encoded", "own"),
                   help="with --multi-start: the copies about the encoded prior-free start and the fit's own start "
                        "(encoded), or about the fit's own start alone, with seeded noise (own): "
                        "objective.multi_start.around (docs/protocol.md)")
    p.add_argument("--rate-scaled", action="store_true",
                   help="judge each plateau at a reduced rate against the tolerance scaled by that rate: the candidate "
                        "rule objective.plateau.rate_scaled (docs/protocol.md), not table1's protocol as committed")
    p.add_argument("--optimiser", default=None, choices=("adam", "lbfgs"),
                   help="lbfgs: the batched L-BFGS on the same objective, each sequence held at its plateau: the "
                        "candidate rule objective.optimiser (docs/protocol.md), not table1's protocol as committed")
    p.add_argument("--start-fit", default=None, choices=("exact", "smooth", "smooth-encoded"),
                   help="smooth: the start search's brief fits and choices on the soft-min Chamfer (smooth where the "
                        "nearest neighbours change), by L-BFGS; smooth-encoded: so only for the prior-free start the "
                        "encoders encode (no-prior's and the per-frame priors' own searches exact): the candidate "
                        "rule objective.start_fit (docs/protocol.md), not table1's protocol as committed; with "
                        "--start-probe, the search it probes (the encoders' start)")

    p.add_argument("--start-probe", action="store_true",
                   help="instead of a fit: the prior-free start's stages (facing, limb search) on the cell's "
                        "observation of the quick sequences and on it moved by 1e-6 m; print how far the joints move "
                        "after each stage (the start every encoded prior encodes)")
    p.add_argument("--robustness", action="store_true",
                   help="instead of the targets: fit the prior at table1's sparsest and densest cell, again with the "
                        "observation moved by 1e-6 m and with 3x the steps, print how far MPJPE moves; exit 1 above 1 mm")
    p.add_argument("--base-run", default=None, metavar="RUN_DIR",
                   help="with --robustness: a table1 run folder whose units of the prior at the two cells serve as the "
                        "base fits (copied into --out, the run folder untouched; reused only when their spec hash "
                        "matches, otherwise fitted again)")

    def run(args) -> int:
        from benchmark.commands.common import resolve_device
        from benchmark.tools.fit_check import run_fit_check, run_robustness

        fps = int(args.fps) if float(args.fps).is_integer() else args.fps
        if args.start_probe:
            from benchmark.tools.start_probe import format_probe, start_probe

            if args.robustness or args.multi_start is not None or args.base_run is not None:
                raise ValueError("fit-check: --start-probe runs the start search alone; drop --robustness, "
                                 "--multi-start and --base-run")
            print("\n".join(format_probe(start_probe(args.points, fps, profile_name=args.profile or "quick",
                                                     start_fit=args.start_fit or "exact"))))
            return 0
        if args.robustness:
            if args.start_search is not None:
                raise ValueError("fit-check: --robustness checks table1's own rules; drop --start-search")
            return run_robustness(prior=args.prior, profile_name=args.profile, device=resolve_device(args.device),
                                  out=args.out, jobs=args.jobs, base_run=args.base_run, multi_start=args.multi_start,
                                  rate_scaled=args.rate_scaled, optimiser=args.optimiser, choose=args.choose,
                                  around=args.around, start_fit=args.start_fit)
        if args.base_run is not None:
            raise ValueError("fit-check: --base-run gives the base fits of --robustness; add --robustness or drop it")
        return run_fit_check(prior=args.prior, points=args.points, fps=fps, profile_name=args.profile,
                             device=resolve_device(args.device), out=args.out, jobs=args.jobs,
                             start_search=args.start_search, multi_start=args.multi_start,
                             rate_scaled=args.rate_scaled, optimiser=args.optimiser, choose=args.choose,
                             around=args.around, start_fit=args.start_fit)

    p.set_defaults(func=run)
