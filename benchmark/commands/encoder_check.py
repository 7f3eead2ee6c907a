"""``encoder-check``: encode-decode error of each prior's encoder on clean and joint-noised motion
(:mod:`benchmark.tools.encoder_check`)."""

from __future__ import annotations

from benchmark.commands.common import HelpFormatter


def add_command(sub) -> None:
    from benchmark.core import argtypes as at

    p = sub.add_parser("encoder-check", help="encode -> decode error (MPJPE mm) of each prior's encoder on the quick "
                                             "test windows, clean and with per-frame joint noise (the completion "
                                             "start's condition)",
                       formatter_class=HelpFormatter)
    p.add_argument("--prior", action="append", default=None,
                   help="prior name (repeatable); default: table1's default priors")
    p.add_argument("--noise-deg", type=at.non_negative_float, action="append", default=None,
                   help="per-axis standard deviation (degrees) of the random turn of every body joint, per frame "
                        "(repeatable; default 0, 2, 5)")
    p.add_argument("--window", type=at.positive_float, default=4.0, help="window length, seconds (table1's: 4)")
    p.add_argument("--sequences", type=at.positive_int, default=8, help="test sequences (the quick profile's selection)")
    p.add_argument("--seed", type=at.seed, default=0)
    p.add_argument("--size", choices=["embedded", "paper"], default="embedded", help="prior size; paper needs --weights")
    p.add_argument("--weights", action="append", metavar="PRIOR=PATH",
                   help="a checkpoint for a prior (repeatable): official weights, or embedded-size ones you trained")
    p.add_argument("--device", default=None, help="cpu | cuda (default: cuda when available)")

    def run(args) -> int:
        from benchmark.body import get_body
        from benchmark.commands.common import parse_pairs, resolve_device
        from benchmark.run.registry import check_weights_option
        from benchmark.run.catalog import load_table_spec
        from benchmark.tools.encoder_check import NOISE_DEG, check_encoders, check_options, format_rows

        check_options(args.sequences, args.window, tuple(args.noise_deg or NOISE_DEG))  # before any work
        priors = args.prior or list(load_table_spec("table1")["default_priors"])
        weights = parse_pairs(args.weights, "--weights")
        check_weights_option(weights, priors, "checked")
        device = resolve_device(args.device)
        rows = check_encoders(priors, get_body("anny", device=device), sequences=args.sequences, window_s=args.window,
                              noise_deg=tuple(args.noise_deg or NOISE_DEG), seed=args.seed, device=device,
                              size=args.size, weights=weights)
        used = max((len(r.get("per_sequence_mm") or []) for r in rows), default=0)
        asked = "" if used == args.sequences else f" (of {args.sequences} asked: the test data holds {used} long enough)"
        print(f"encode -> decode MPJPE (mm, 22 joints, no alignment) over {used} test windows of {args.window:g} s{asked}; "
              "noise: every body joint turned per frame (root and translation clean)")
        print(format_rows(rows))
        return 0

    p.set_defaults(func=run)
