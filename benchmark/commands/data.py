"""``data``: ``convert`` (AMASS / BVH -> the harness's motion .npz), ``build`` (a synthetic split),
``make-scans`` (captured-like scan folders from the synthetic test split)."""

from __future__ import annotations

from benchmark.commands.common import HelpFormatter


def _cmd_data_convert(args) -> int:
    from benchmark.loaders.convert import convert

    body = None
    if args.body:
        from benchmark.body import get_body

        body = get_body(args.body)
    motion = convert(args.input, args.out, fps=args.fps, overwrite=args.force, body=body)
    shape = ""
    if body is not None:
        shape = (f", shape for body {body.name} ({body.shape_dim} parameters)" if motion.shape is not None else
                 f", no shape stored (the input's shape is not body {body.name}'s: its neutral shape will be used)")
    print(f"wrote {args.out}: {motion.num_frames} frames, {motion.duration:.2f} s, {motion.fps:.1f} fps"
          + (f" ({motion.source})" if motion.source else "") + shape)
    return 0


def _cmd_data_build(args) -> int:
    from benchmark.synthetic.splits import build_split

    motions = build_split(args.split, seed=args.seed, rebuild=args.rebuild)
    total = sum(m.duration for m in motions)
    print(f"split {args.split!r}: {len(motions)} sequences, {total / 60:.1f} min of motion")
    return 0


def _cmd_data_make_scans(args) -> int:
    from benchmark.synthetic.scan_set import make_scan_set

    table_spec = None
    if args.table_capture is not None:
        from benchmark.run.catalog import load_table_spec

        table_spec = load_table_spec("table1")
    written = make_scan_set(args.out, sequences=args.ids if args.ids is not None else args.sequences, fps=args.fps,
                            points=args.points, noise_mm=args.noise_mm, holes=args.holes, duration=args.duration,
                            seed=args.seed, up=args.up, units=args.units, overwrite=args.force,
                            table_capture=args.table_capture, table_spec=table_spec)
    print(f"wrote {len(written)} scan sequences to {args.out}: {', '.join(p.name for p in written)}")
    return 0


def add_command(sub) -> None:
    from benchmark.core import argtypes as at

    p = sub.add_parser("data", help="motion data: convert files, build the synthetic splits")
    dsub = p.add_subparsers(dest="data_command", metavar="DATA_COMMAND")

    def no_data_command(args) -> int:  # `python -m benchmark data` alone: say what it takes
        raise ValueError(f"data: give a DATA_COMMAND: {', '.join(dsub.choices)} "
                         "(e.g. python -m benchmark data convert motion.bvh --out motion.npz; --help on each)")

    p.set_defaults(func=no_data_command)
    c = dsub.add_parser("convert", help="AMASS .npz or BVH -> the harness's motion .npz",
                        formatter_class=HelpFormatter)
    c.add_argument("input")
    c.add_argument("--out", required=True, help="output .npz (never overwritten without --force)")
    c.add_argument("--fps", type=at.fps, default=None, help="resample to this rate (default: keep the source rate)")
    c.add_argument("--force", action="store_true", help="overwrite an existing output file")
    c.add_argument("--body", default=None, help="store the motion's shape for this body model (anny | smpl | smplh | "
                   "smplx[=PATH[:gender]]): SMPL betas cut or zero-padded to the model's, another body's shape dropped")
    c.set_defaults(func=_cmd_data_convert)
    b = dsub.add_parser("build", help="generate (or check the cache of) a synthetic split",
                        formatter_class=HelpFormatter)
    b.add_argument("split", choices=["test", "train", "val"])
    b.add_argument("--seed", type=at.seed, default=None, help="override the split's seed")
    b.add_argument("--rebuild", action="store_true")
    b.set_defaults(func=_cmd_data_build)
    m = dsub.add_parser("make-scans", help="write captured-like scan folders (PLY + timestamps) from the synthetic test split",
                        formatter_class=HelpFormatter)
    m.add_argument("--out", required=True, help="output folder, one sub-folder per sequence")
    m.add_argument("--sequences", type=at.positive_int, default=4, help="how many test sequences (the profiles' selection)")
    m.add_argument("--ids", nargs="+", default=None, help="explicit test sequence ids instead of --sequences")
    m.add_argument("--fps", type=at.fps, default=60.0, help="capture rate")
    m.add_argument("--points", type=at.Number(int, 3, at.MAX_POINTS), default=10000,
                   help="points per frame (after the holes); a scan frame needs at least 3")
    m.add_argument("--noise-mm", type=at.Number(float, 0.0, 1000.0, unit="mm"), default=3.0, help="Gaussian noise per axis, mm")
    m.add_argument("--holes", type=at.fraction, default=0.1, help="fraction of each frame's surface cut away")
    m.add_argument("--duration", type=at.positive_float, default=4.0,
                   help="seconds per sequence (at most the sequences' length, 4.4 s)")
    m.add_argument("--seed", type=at.seed, default=0)
    m.add_argument("--up", choices=["y", "z"], default="y", help="up axis to write")
    m.add_argument("--units", choices=["m", "cm", "mm"], default="m", help="units to write")
    m.add_argument("--table-capture", type=at.seed, default=None, metavar="SEED",
                   help="write the capture `run table1 --seed SEED` synthesises (its rate, points and seeds; "
                        "no noise, no holes): the scan path's check against the synthetic run")
    m.add_argument("--force", action="store_true",
                   help="replace the output of an earlier make-scans in --out (a folder holding anything else is refused)")
    m.set_defaults(func=_cmd_data_make_scans)
