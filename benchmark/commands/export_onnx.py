"""``export-onnx``: export a prior's decoder to ONNX and check it with onnxruntime
(:mod:`benchmark.tools.export_onnx`)."""

from __future__ import annotations

import sys
from pathlib import Path

from benchmark.commands.common import HelpFormatter

from benchmark.run.registry import make_adapter


def _opset(text):
    """``--opset``: an opset :func:`benchmark.tools.export_onnx.export_onnx` takes (its range comes from
    torch, imported only when the option is given)."""
    from benchmark.core.argtypes import Number
    from benchmark.tools.export_onnx import supported_opsets

    lo, hi = supported_opsets()
    return Number(int, lo, hi)(text)


_opset.__name__ = "ONNX opset"


def _cmd_export_onnx(args) -> int:
    from benchmark.tools.export_onnx import ParityError, check_export_target, export_onnx, require_onnx_packages, sidecar_path

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


def add_command(sub) -> None:
    from benchmark.core import argtypes as at

    fmt = HelpFormatter
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
