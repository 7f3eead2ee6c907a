"""``run``: run a table for some priors (:func:`benchmark.run.table_run.run_table`), after checking
everything a user can get wrong before anything heavy loads."""

from __future__ import annotations

import sys
from pathlib import Path

from benchmark.commands.common import HelpFormatter, parse_pairs, resolve_device
from benchmark.run.catalog import default_priors


def _check_data_arg(data: str | None) -> None:
    if data is None:
        return
    root = Path(data.split("=", 1)[-1]).expanduser()
    if not root.exists():
        raise FileNotFoundError(f"--data {data}: no such file or folder; give a folder of harness/AMASS .npz files "
                                "(or one file), or leave --data out for the synthetic test split")


def _check_table_files(out: Path, table: str) -> None:
    """The run writes ``<out>/<table>.{json,md,csv,tex}``: it replaces them only where they are an
    earlier run's (the JSON beside them is a table JSON of this table), never a user's own files."""
    import json

    from benchmark.core.outdir import OutDirError
    from benchmark.run.writers import FORMATS

    existing = [out / f"{table}.{fmt}" for fmt in FORMATS if (out / f"{table}.{fmt}").exists()]
    if not existing:
        return
    try:
        ours = json.loads((out / f"{table}.json").read_text()).get("table") == table
    except (OSError, ValueError, AttributeError):
        ours = False
    if not ours:
        one = len(existing) == 1
        raise OutDirError(f"--out {out}: {', '.join(p.name for p in existing)} {'exists and is' if one else 'exist and are'} "
                          f"not an earlier run's table {table!r} (no table JSON of it beside {'it' if one else 'them'}); "
                          f"the run would replace {'it' if one else 'them'}: choose another --out, or move "
                          f"{'it' if one else 'them'} away")


def _backend_options(args, device: str) -> dict:
    """--jobs / --ray-address / --cpus-per-unit / --gpus-per-unit as options of the chosen backend."""
    from benchmark.run.backends.local import default_jobs

    if args.backend == "local":
        for flag, value in (("--ray-address", args.ray_address), ("--cpus-per-unit", args.cpus_per_unit),
                            ("--gpus-per-unit", args.gpus_per_unit)):
            if value is not None:
                raise ValueError(f"{flag} applies to --backend ray; the local backend takes --jobs")
        jobs = default_jobs(device) if args.jobs is None else args.jobs
        print(f"backend local, {jobs} job(s)" + (" (worker processes, one torch thread each)" if jobs > 1 else ""))
        return {"jobs": jobs}
    if args.jobs is not None:
        raise ValueError("--jobs applies to --backend local; on Ray every unit is a task, sized by --cpus-per-unit "
                         "and --gpus-per-unit")
    print(f"backend ray, cluster {args.ray_address or '(a local runtime on this machine)'}")
    return {"address": args.ray_address, "cpus_per_unit": args.cpus_per_unit, "gpus_per_unit": args.gpus_per_unit}


def _cmd_run(args) -> int:
    from benchmark.run.catalog import get_profile, load_table_spec
    from benchmark.core.outdir import OutDirLock, check_out_dir, check_units_folder, remove_partial_files
    from benchmark.run.registry import check_weights_option, get_prior_class

    # everything a user can get wrong is checked here, before the body, data or any prior loads
    spec = load_table_spec(args.table)
    device = resolve_device(args.device)
    profile_name = args.profile if args.profile is not None else ("full" if device.startswith("cuda") else "quick")
    profile = get_profile(profile_name, table=spec["name"])
    out = check_out_dir(args.out)  # cheap, and the costliest mistake to find late: first
    _check_table_files(out, spec["name"])
    check_units_folder(out)
    priors = args.prior or default_priors(spec)
    twice = sorted({p for p in priors if priors.count(p) > 1})
    if twice:
        raise ValueError(f"--prior {', '.join(twice)} given twice; name each prior once")
    for name in priors:
        get_prior_class(name)
    weights = parse_pairs(args.weights, "--weights")
    check_weights_option(weights, priors)
    from benchmark.body import parse_body_spec

    parse_body_spec(args.body)
    _check_data_arg(args.data)
    with OutDirLock(out, command="python -m benchmark " + " ".join(sys.argv[1:])):
        remove_partial_files(out)  # a killed run's half-written files: only ours, and no other run writes here
        return _run_locked(args, spec, device, profile_name, profile, priors, weights, out)


def _run_locked(args, spec, device, profile_name, profile, priors, weights, out) -> int:
    from benchmark.body import get_body
    from benchmark.loaders.scans import scan_data_spec
    from benchmark.run.table_run import run_table

    print(f"table {args.table} (protocol v{spec['protocol_version']}), profile {profile_name!r}: {profile['description']}")
    print(f"device {device}, seed {args.seed}, output {out}")
    backend_options = _backend_options(args, device)
    body = get_body(args.body, device=device)
    result = run_table(
        spec, profile, priors=priors, body=body, device=device, seed=args.seed,
        out_dir=out, resume=args.resume, size=args.size, weights=weights,
        data=scan_data_spec(args.data, args.up, args.units), backend=args.backend, backend_options=backend_options,
    )
    print()
    print(result["markdown"])
    print(f"written: {', '.join(str(p) for p in result['files'].values())}")
    return 1 if result["failures"] else 0


def add_command(sub) -> None:
    from benchmark.core import argtypes as at

    fmt = HelpFormatter
    p = sub.add_parser("run", help="run a table (e.g. table1) for some priors", formatter_class=fmt)
    p.add_argument("table")
    p.add_argument("--prior", action="append", help="prior name (repeatable); default: the table spec's default_priors (python -m benchmark list)")
    p.add_argument("--profile", default=None, help="smoke | quick | full (default: full on CUDA, quick on CPU)")
    p.add_argument("--device", default=None, help="cpu | cuda (default: cuda when available)")
    p.add_argument("--seed", type=at.seed, default=0)
    p.add_argument("--out", default="runs/latest", help="output directory (unit files, table JSON/MD/CSV/TeX)")
    p.add_argument("--resume", choices=["only-missing", "never"], default="only-missing")
    p.add_argument("--size", choices=["embedded", "paper"], default="embedded", help="prior size; paper needs --weights")
    p.add_argument("--weights", action="append", metavar="PRIOR=PATH", help="official checkpoint for a prior")
    p.add_argument("--body", default="anny", help="body model: anny | smpl | smplh | smplx[=PATH[:gender]]")
    p.add_argument("--data", default=None, help="motion data: default synthetic test split; or a folder of harness/AMASS .npz files; "
                   "or scans=DIR, captured scans (one folder per sequence, table1 only)")
    p.add_argument("--up", choices=["y", "z"], default=None, help="--data scans=DIR: the captures' up axis (default y)")
    p.add_argument("--units", choices=["m", "cm", "mm"], default=None, help="--data scans=DIR: the captures' units (default m)")
    p.add_argument("--backend", choices=["local", "ray"], default="local",
                   help="execution backend: local (this machine, --jobs processes) or ray (a Ray runtime or cluster); "
                        "the backend never changes a number")
    p.add_argument("--jobs", type=at.jobs, default=None,
                   help="local backend: units run in parallel in this many worker processes, one torch thread each "
                        "(default: the CPU cores, 1 on CUDA; 1 runs them in this process)")
    p.add_argument("--ray-address", default=None, metavar="auto|HOST:PORT",
                   help="ray backend: join a running cluster ('auto': the one started on this machine by 'ray start'); "
                        "default: start a local Ray runtime with this machine's cores")
    p.add_argument("--cpus-per-unit", type=at.positive_float, default=None,
                   help="ray backend: CPUs each unit reserves, also its torch threads (default 1)")
    p.add_argument("--gpus-per-unit", type=at.non_negative_float, default=None,
                   help="ray backend: GPUs each unit reserves, a fraction shares one (default 1 with --device cuda, else 0)")
    p.set_defaults(func=_cmd_run)
