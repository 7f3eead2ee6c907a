"""The protocol commands: run, describe, check-prior, train, export-onnx, compare."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from benchmark.registry import make_adapter

log = logging.getLogger("benchmark")

DEFAULT_PRIORS = ("no-prior", "vposer-slerp")  # when a table spec has no ``default_priors``


def default_priors(spec: dict) -> list[str]:
    """The rows a table runs without --prior: the spec's ``default_priors``, else DEFAULT_PRIORS."""
    return list(spec.get("default_priors") or DEFAULT_PRIORS)


def resolve_device(name: str | None) -> str:
    """The device to run on: ``None`` picks cuda when available; otherwise ``cpu``, ``cuda`` or
    ``cuda:N``, checked here so that a wrong name fails before any work."""
    import torch

    if name is None:
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError, TypeError):
        raise ValueError(f"--device {name!r}: not a device name; use cpu, cuda or cuda:N") from None
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"--device {name!r}: the harness runs on cpu or cuda (cuda:N), not {dev.type!r}")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"--device {name}: no CUDA device is available on this machine "
                             "(torch.cuda.is_available() is False); use --device cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA device(s) "
                             f"(cuda:0..cuda:{torch.cuda.device_count() - 1})")
    return name


def _opset(text):
    """``--opset``: an opset :func:`benchmark.export_onnx.export_onnx` takes (its range comes from
    torch, imported only when the option is given)."""
    from benchmark.argtypes import Number
    from benchmark.export_onnx import supported_opsets

    lo, hi = supported_opsets()
    return Number(int, lo, hi)(text)


_opset.__name__ = "ONNX opset"


def _parse_pairs(items, what: str) -> dict:
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key or not value:
            raise ValueError(f"{what} must look like NAME=VALUE, got {item!r}")
        if key in out:
            raise ValueError(f"{what}: {key!r} is given twice ({key}={out[key]} and {item}); give each NAME once")
        out[key] = value
    return out


def _check_data_arg(data: str | None) -> None:
    if data is None:
        return
    root = Path(data.split("=", 1)[-1]).expanduser()
    if not root.exists():
        raise FileNotFoundError(f"--data {data}: no such file or folder; give a folder of harness/AMASS .npz files "
                                "(or one file), or leave --data out for the synthetic test split")


def _backend_options(args, device: str) -> dict:
    """--jobs / --ray-address / --cpus-per-unit / --gpus-per-unit as options of the chosen backend."""
    from benchmark.backends import default_jobs

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
    from benchmark.catalog import get_profile, load_table_spec
    from benchmark.outdir import OutDirLock, check_out_dir
    from benchmark.registry import get_prior_class

    # everything a user can get wrong is checked here, before the body, data or any prior loads
    spec = load_table_spec(args.table)
    device = resolve_device(args.device)
    profile_name = args.profile or ("full" if device.startswith("cuda") else "quick")
    profile = get_profile(profile_name, table=spec["name"])
    out = check_out_dir(args.out)  # cheap, and the costliest mistake to find late: first
    priors = args.prior or default_priors(spec)
    for name in priors:
        get_prior_class(name)
    weights = _parse_pairs(args.weights, "--weights")
    unknown = sorted(set(weights) - set(priors))
    if unknown:
        raise ValueError(f"--weights given for prior(s) {unknown} that are not being run ({', '.join(priors)}); "
                         "add them with --prior NAME or drop those --weights")
    for name, path in weights.items():
        if not Path(path.split(",")[0]).expanduser().exists():
            raise FileNotFoundError(f"--weights {name}={path}: no such file or folder")
    from benchmark.body import parse_body_spec

    parse_body_spec(args.body)
    _check_data_arg(args.data)
    with OutDirLock(out, command="python -m benchmark " + " ".join(sys.argv[1:])):
        return _run_locked(args, spec, device, profile_name, profile, priors, weights, out)


def _run_locked(args, spec, device, profile_name, profile, priors, weights, out) -> int:
    from benchmark.body import get_body
    from benchmark.loaders.scans import scan_data_spec
    from benchmark.protocols.table_run import run_table

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


def _count(module) -> tuple[int, int]:
    params = list(module.parameters())
    return sum(p.numel() for p in params), sum(p.numel() for p in params if p.requires_grad)


def parameter_rows(module) -> list[tuple[str, int, int]]:
    """(name, parameters, trainable) per top-level child of ``module``. An adapter whose parameters
    all sit in one child (``VPoserSlerp.vposer``) is looked through, so the rows name the
    network's own parts (``vposer.encoder_net``, ``vposer.decoder_net``) for every size."""
    children = [(n, c) for n, c in module.named_children() if _count(c)[0] > 0]
    prefix = ""
    while len(children) == 1 and _count(children[0][1])[0] == _count(module)[0] and list(children[0][1].children()):
        name, module = children[0]
        prefix += name + "."
        children = [(n, c) for n, c in module.named_children() if _count(c)[0] > 0]
    rows = [(prefix + n, *_count(c)) for n, c in children]
    direct = sum(p.numel() for p in module.parameters(recurse=False))
    if direct:
        rows.append((prefix + "(own parameters)", direct, sum(p.numel() for p in module.parameters(recurse=False) if p.requires_grad)))
    return rows


def _print_counts(module, note: str = "") -> None:
    total, trainable = _count(module)
    print(f"parameters: {total:,} (trainable {trainable:,}{note})")
    rows = parameter_rows(module)
    width = max((len(r[0]) for r in rows), default=0)
    for name, n, t in rows:
        print(f"  {name.ljust(width)}  {n:>12,}  (trainable {t:,})")


def describe_body(spec: str) -> str:
    """A body model in a few lines: kind, file, vertices, faces, joints, shape parameters."""
    from benchmark.body import get_body

    body = get_body(spec)
    source = getattr(body, "source_path", None)
    file_joints = getattr(body, "num_file_joints", None)
    lines = [f"body {body.name}" + (f" from {source}" if source else " (embedded)"),
             f"  vertices {body.num_vertices:,}, faces {int(body.faces.shape[0]):,}, joints driven 22"
             + (f" (file: {file_joints})" if file_joints else "") + f", shape parameters {body.shape_dim}"]
    return "\n".join(lines)


def _cmd_describe(args) -> int:
    from benchmark.registry import get_prior_class

    if args.body:
        print(describe_body(args.body))
        if args.name is None:
            return 0
    elif args.name is None:
        raise ValueError("describe needs a prior NAME (python -m benchmark list priors) or --body KIND")
    cls = get_prior_class(args.name)
    from priors.base import PaperNetwork

    if args.size == "paper" and args.weights is None and isinstance(cls, type) and issubclass(cls, PaperNetwork):
        net = cls.paper_network()
        print(f"{args.name} (paper size, random weights: architecture only, no checkpoint loaded)")
        print(net)
        _print_counts(net)
        return 0
    adapter = make_adapter(args.name, size=args.size, weights=args.weights, device="cpu")
    print(adapter.describe())
    frozen = "; the adapter freezes its network" if _count(adapter)[0] and not _count(adapter)[1] else ""
    _print_counts(adapter, frozen)
    return 0


def _cmd_check_prior(args) -> int:
    from benchmark.conformance import check_prior

    # input errors (an unknown prior, a weights file torch cannot read) are errors, exit 2, not a
    # conformance FAIL: construct once up front
    make_adapter(args.name, size=args.size, weights=args.weights, device="cpu")
    ok = check_prior(args.name, size=args.size, weights=args.weights)
    return 0 if ok else 1


def _cmd_train(args) -> int:
    from benchmark.registry import get_prior_class

    from benchmark.outdir import check_out_dir

    cls = get_prior_class(args.name)
    from priors.base import Trainable

    if not (isinstance(cls, type) and issubclass(cls, Trainable)):
        raise ValueError(f"prior {args.name!r} has no training recipe (it is not a priors.base.Trainable: "
                         "no train_embedded classmethod)")
    out = Path(args.out) if args.out is not None else None
    from benchmark.synthetic.train_data import SyntheticTrainingData
    from priors.training import WEIGHTS_DIR, training_session

    # the weights folder first: a wrong --out fails in a second, not after hours of training
    check_out_dir(out if out is not None else WEIGHTS_DIR, min_free_bytes=1 << 20,
                  what="--out" if out is not None else "the weights folder")

    # every loop of the recipe checkpoints here; --resume continues from it (priors/training.py)
    state_dir = (out or WEIGHTS_DIR) / ".train_state" / args.name
    if args.resume and not state_dir.exists():
        raise FileNotFoundError(f"train {args.name} --resume: no training state in {state_dir}; start the training "
                                f"without --resume (it checkpoints every {args.checkpoint_every} steps)")
    with training_session(state_dir, resume=args.resume, checkpoint_every=args.checkpoint_every,
                          val_every=args.val_every):
        # the training data: the synthetic splits, handed to the recipe (priors never build data)
        record = cls.train_embedded(out_dir=out, steps=args.steps, seed=args.seed, overwrite=args.force,
                                    dataset=SyntheticTrainingData())
    print(record)
    return 0


def _cmd_export_onnx(args) -> int:
    from benchmark.export_onnx import ParityError, check_export_target, export_onnx, require_onnx_packages, sidecar_path

    out = Path(args.out) if args.out is not None else Path("exports") / f"{args.name}.{args.size}.onnx"
    check_export_target(out, overwrite=args.force, weights=args.weights)  # before anything loads
    require_onnx_packages()
    adapter = make_adapter(args.name, size=args.size, weights=args.weights, device="cpu")
    try:
        record = export_onnx(adapter, out, opset=args.opset, overwrite=args.force, check=not args.no_check)
    except ParityError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1

    def shapes(rows):
        return ", ".join(f"{r['name']} {tuple(r['shape'])} {r['dtype']}" for r in rows)

    print(f"wrote {record['file']} ({record['onnx_bytes']:,} bytes, opset {record['opset']}, sha256 {record['onnx_sha256'][:16]}...)")
    print(f"  prior {record['prior']} ({record['size']}), weights {record['weights'] or '(none)'}")
    print(f"  inputs:  {shapes(record['inputs'])}")
    print(f"  outputs: {shapes(record['outputs'])}")
    parity = record["parity"]
    if parity.get("ok") is None:
        print("  parity: not checked (--no-check)")
    else:
        print(
            f"  parity (onnxruntime {parity['onnxruntime']} CPU vs PyTorch, batch {parity['batch']}, traced at batch "
            f"{parity['example_batch']}): max abs error {parity['max_abs_error']:.3g}, max rel error "
            f"{parity['max_rel_error']:.3g}; {100 * parity['tolerance_used']:.2g}% of the tolerance (rtol {parity['rtol']:g}, "
            f"atol {parity['atol']:g}): PASS"
        )
    print(f"  record: {sidecar_path(out)}")
    return 0


def _cmd_compare(args) -> int:
    from benchmark.compare import main_compare

    return main_compare(args.a, args.b, args.tol or [])


def add_run_commands(sub) -> None:
    from benchmark.complete import add_complete_command

    from benchmark import argtypes as at

    fmt = argparse.ArgumentDefaultsHelpFormatter
    add_complete_command(sub)
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

    p = sub.add_parser("describe", help="architecture summary and parameter counts of a prior (--size paper without --weights: "
                       "the paper-size network with random weights)", formatter_class=fmt)
    p.add_argument("name", nargs="?", default=None, help="a prior (python -m benchmark list priors)")
    p.add_argument("--size", choices=["embedded", "paper"], default="embedded")
    p.add_argument("--weights", action=at.Once, default=None)
    p.add_argument("--body", default=None, help="also describe a body model: anny | smpl | smplh | smplx[=PATH[:gender]]")
    p.set_defaults(func=_cmd_describe)

    p = sub.add_parser("check-prior", help="conformance kit: run an adapter through a tiny table", formatter_class=fmt)
    p.add_argument("name")
    p.add_argument("--size", choices=["embedded", "paper"], default="embedded")
    p.add_argument("--weights", action=at.Once, default=None)
    p.set_defaults(func=_cmd_check_prior)

    p = sub.add_parser("train", help="train a prior's embedded weights on the synthetic training split", formatter_class=fmt)
    p.add_argument("name")
    p.add_argument("--steps", type=at.positive_int, default=None, help="training steps (default: the recipe's)")
    p.add_argument("--seed", type=at.seed, default=0)
    p.add_argument("--out", default=None, help="output folder (default: priors/weights)")
    p.add_argument("--force", action="store_true", help="overwrite existing weights")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted training from its last checkpoint (OUT/.train_state/NAME; add --force when "
                        "the weights file exists)")
    p.add_argument("--checkpoint-every", type=at.positive_int, default=200,
                   help="save the resumable training state every N steps")
    p.add_argument("--val-every", type=at.non_negative_int, default=500,
                   help="log the validation loss every N steps (0: at the end only)")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("export-onnx", help="export a prior's decoder to ONNX (dynamic batch) and check it with onnxruntime",
                       formatter_class=fmt)
    p.add_argument("name")
    p.add_argument("--size", choices=["embedded", "paper"], default="embedded", help="prior size; paper needs --weights")
    p.add_argument("--weights", action=at.Once, default=None, help="checkpoint (embedded: default priors/weights; paper: the official one)")
    p.add_argument("--out", default=None, help="output .onnx, record written beside it as .json (default: exports/NAME.SIZE.onnx)")
    p.add_argument("--opset", type=_opset, default=17,
                   help="ONNX opset version (11 up to the newest this torch exports; some priors need 13)")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file and its record")
    p.add_argument("--no-check", action="store_true", help="skip the onnxruntime parity check")
    p.set_defaults(func=_cmd_export_onnx)

    p = sub.add_parser("compare", help="per-cell differences between two table JSONs", formatter_class=fmt)
    p.add_argument("a")
    p.add_argument("b")
    p.add_argument("--tol", action="append", metavar="METRIC=VALUE", help="tolerance in the metric's unit")
    p.set_defaults(func=_cmd_compare)

