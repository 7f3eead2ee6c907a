"""ONNX export of a prior's decoder, with an onnxruntime parity check and a JSON record beside it.

``python -m benchmark export-onnx NAME`` calls :func:`export_onnx`. The adapter gives its
deterministic decode path as a :class:`priors.base.ExportSpec` (``PriorAdapter.export_decoder``);
it is traced by the TorchScript-based exporter (``torch.onnx.export(..., dynamo=False)``: the
torch.export-based one needs ``onnxscript``, which is not a dependency) with dim 0 of every input
and output dynamic (named ``batch``). :func:`check_parity` then runs the file with onnxruntime
(CPUExecutionProvider) on random inputs at a batch size *different* from the traced example, so a
batch size frozen into the graph by the trace fails the check instead of passing silently.

Files: ``OUT.onnx`` and the record ``OUT.json`` beside it (prior, size, weights file and its
sha256, input/output names and shapes, opset, exporter, library versions, git revision, the ONNX
file's sha256, the parity numbers). Neither is ever overwritten without ``overwrite=True``
(``--force``). The export goes to a temporary file first: a failed export or parity check leaves
nothing behind.
"""

from __future__ import annotations

import hashlib
import json
import contextlib
import logging
import os
import re
import sys
import tempfile
import warnings
from pathlib import Path

import torch

log = logging.getLogger(__name__)

DEFAULT_OPSET = 17
EXPORTER = "torch.onnx.export (TorchScript-based, dynamo=False)"
# The lowest opset a decoder exports at with its dynamic batch dimension: below 11 the traced
# reshapes lose a dimension (vposer-slerp at 9 and 10: "'rotations' has rank 3 in the graph") or
# the exporter stops on an AssertionError after dumping the graph (7). Priors that need more (those
# using aten::unflatten: 13) get torch's own UnsupportedOperatorError, which names the opset to use.
MIN_DYNAMIC_BATCH_OPSET = 11
_FALLBACK_MAX_OPSET = 20  # when torch does not say (torch 2.x: 20 to 23)


@contextlib.contextmanager
def _output_quiet():
    """File descriptors 1 and 2 into a temporary file while the block runs, then back."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with tempfile.TemporaryFile() as sink:
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            try:
                yield
            finally:
                sys.stdout.flush()
                sys.stderr.flush()
                os.dup2(saved[0], 1)
                os.dup2(saved[1], 2)
    finally:
        for fd in saved:
            os.close(fd)


def _opset_problem(prior: str, opset: int, message: str) -> str:
    """The one-line error for an operator the asked opset lacks (from torch's UnsupportedOperatorError)."""
    op = re.search(r"operator '([^']+)'", message)
    since = re.search(r"added in version (\d+)", message)
    what = f"the operator {op.group(1)}" if op else "an operator"
    if since:
        return (f"--opset {opset}: {prior}'s decoder uses {what}, which ONNX has from opset {since.group(1)}; "
                f"export with --opset {since.group(1)} or later (default 17)")
    return f"--opset {opset}: {prior}'s decoder uses {what} this opset cannot express; export with a later --opset (default 17)"


def supported_opsets() -> tuple[int, int]:
    """(lowest, highest) ``opset_version`` :func:`export_onnx` takes: from the exporter's own range
    (``torch.onnx._constants``: 7..23 for torch 2.13; 24 is refused by torch), raised to
    :data:`MIN_DYNAMIC_BATCH_OPSET`. ``--opset`` is checked against it when the command line is parsed."""
    try:
        from torch.onnx import _constants as c

        lo, hi = int(c.ONNX_MIN_OPSET), int(c.ONNX_MAX_OPSET)
    except (ImportError, AttributeError, TypeError, ValueError):
        lo, hi = MIN_DYNAMIC_BATCH_OPSET, _FALLBACK_MAX_OPSET
    return max(lo, MIN_DYNAMIC_BATCH_OPSET), hi


class NotExportableError(ValueError):
    """The prior has no exportable decoder (its ``export_decoder`` raised NotImplementedError)."""


class ParityError(AssertionError):
    """onnxruntime's outputs differ from PyTorch's beyond the tolerance (message names the output)."""

    def __init__(self, message: str, result: dict):
        super().__init__(message)
        self.result = result


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


def sidecar_path(path: str | Path) -> Path:
    """The JSON record written beside ``path`` (``x.onnx`` -> ``x.json``)."""
    return Path(path).with_suffix(".json")


def get_spec(adapter_or_spec):
    """The ExportSpec of an adapter (an :class:`~priors.base.ExportableDecoder`: ``export_decoder()``),
    or the spec itself; checked."""
    from priors.base import ExportableDecoder, ExportSpec, PriorAdapter

    if isinstance(adapter_or_spec, ExportSpec):
        spec = adapter_or_spec
    else:
        name = adapter_or_spec.name if isinstance(adapter_or_spec, PriorAdapter) else type(adapter_or_spec).__name__
        if not isinstance(adapter_or_spec, ExportableDecoder):
            raise NotExportableError(f"prior {name!r} has no decoder to export to ONNX (it is not an ExportableDecoder: "
                                     "no export_decoder())")
        try:
            spec = adapter_or_spec.export_decoder()
        except NotImplementedError as exc:
            raise NotExportableError(str(exc) or f"prior {name!r} does not export its decoder") from exc
        if not isinstance(spec, ExportSpec):
            raise TypeError(f"prior {name!r}: export_decoder() must return priors.base.ExportSpec, got {type(spec).__name__}")
    inputs = tuple(spec.example_inputs)
    if not inputs or not all(torch.is_tensor(t) for t in inputs):
        raise ValueError("ExportSpec.example_inputs must be a non-empty tuple of tensors")
    if len(spec.input_names) != len(inputs):
        raise ValueError(f"ExportSpec: {len(spec.input_names)} input_names {spec.input_names} for {len(inputs)} example inputs")
    if len(set(spec.input_names) | set(spec.output_names)) != len(spec.input_names) + len(spec.output_names):
        raise ValueError(f"ExportSpec: input and output names must be distinct, got {spec.input_names} and {spec.output_names}")
    batch = {t.shape[0] if t.dim() else None for t in inputs}
    if len(batch) != 1 or None in batch or next(iter(batch)) < 2:
        raise ValueError(
            f"ExportSpec.example_inputs must share one batch size >= 2 on dim 0 (a batch of 1 can be specialised by "
            f"the trace), got shapes {[tuple(t.shape) for t in inputs]}"
        )
    return spec


def _outputs_tuple(out) -> tuple:
    return tuple(out) if isinstance(out, (tuple, list)) else (out,)


def _random_inputs(spec, batch: int, seed: int) -> tuple:
    """Inputs shaped like the example but with ``batch`` on dim 0: N(0, 1) for floating inputs,
    rows of the example drawn with replacement for integer/bool inputs."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for t in spec.example_inputs:
        t = t.detach().cpu()
        if t.is_floating_point():
            out.append(torch.randn((batch, *t.shape[1:]), generator=g, dtype=t.dtype))
        else:
            idx = torch.randint(0, t.shape[0], (batch,), generator=g)
            out.append(t[idx].clone())
    return tuple(out)


def check_parity(adapter_or_spec, path: str | Path, batch: int = 3, rtol: float = 1e-3, atol: float = 1e-5, seed: int = 0) -> dict:
    """Run ``path`` with onnxruntime (CPU) and the spec's module with PyTorch on the same random
    inputs with ``batch`` on dim 0 (must differ from the example's batch size), and compare.

    Passes when every element satisfies ``|onnx - torch| <= atol + rtol * |torch|`` (numpy's
    ``allclose`` rule) and the shapes match. Returns ``{"ok", "batch", "example_batch", "rtol",
    "atol", "seed", "max_abs_error", "max_rel_error", "tolerance_used", "outputs": {name: {shape, max_abs_error,
    max_rel_error, tolerance_used}}, "provider", "onnxruntime"}``. ``max_rel_error`` is |diff| / |torch|
    over the elements where the relative part of the tolerance dominates (|torch| >= atol / rtol), so
    round-off on values that are ~0 does not read as a huge ratio; ``tolerance_used`` is the largest
    |diff| / (atol + rtol * |torch|) over all elements (<= 1 passes).
    Raises :class:`ParityError` (an AssertionError) naming the worst output when outside tolerance.
    """
    import numpy as np
    import onnxruntime as ort

    spec = get_spec(adapter_or_spec)
    example_batch = int(spec.example_inputs[0].shape[0])
    if int(batch) < 1 or int(batch) == example_batch:
        raise ValueError(
            f"check_parity: batch must be >= 1 and differ from the example's batch size ({example_batch}) so the "
            f"dynamic batch dimension is exercised, got {batch}"
        )
    inputs = _random_inputs(spec, int(batch), seed)
    module = spec.module.eval()
    device = next((p.device for p in module.parameters()), torch.device("cpu"))
    with torch.no_grad():
        ref = _outputs_tuple(module(*(t.to(device) for t in inputs)))
    ref = [r.detach().cpu().numpy() for r in ref]
    if len(ref) != len(spec.output_names):
        raise ValueError(f"the module returns {len(ref)} outputs but ExportSpec.output_names has {len(spec.output_names)}")

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    session = ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
    try:
        got = session.run(list(spec.output_names), {n: t.numpy() for n, t in zip(spec.input_names, inputs)})
    except Exception as exc:  # onnxruntime raises its own exception types
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        result = {"ok": False, "batch": int(batch), "example_batch": example_batch, "error": first}
        raise ParityError(
            f"ONNX parity check failed for {path}: onnxruntime cannot run it at batch {batch} (traced at batch "
            f"{example_batch}; a batch size frozen into the graph by the trace, e.g. a reshape to x.shape[0]?): {first}",
            result,
        ) from exc

    per_output, ok, worst = {}, True, None
    for name, r, o in zip(spec.output_names, ref, got):
        if r.shape != o.shape:
            per_output[name] = {"shape": list(o.shape), "expected_shape": list(r.shape), "max_abs_error": None, "max_rel_error": None,
                                "tolerance_used": None, "within_tolerance": False}
            ok, worst = False, worst or f"output {name!r}: onnxruntime shape {tuple(o.shape)} != PyTorch {tuple(r.shape)}"
            continue
        r64, o64 = r.astype(np.float64), o.astype(np.float64)
        diff = np.abs(o64 - r64)
        rel = diff / np.maximum(np.abs(r64), 1e-30)
        finite = bool(np.isfinite(o64).all() and np.isfinite(r64).all())
        within = bool(np.allclose(o64, r64, rtol=rtol, atol=atol, equal_nan=False))
        max_abs = float(np.nanmax(diff)) if diff.size else 0.0
        big = np.abs(r64) >= atol / rtol if rtol > 0 else np.ones(r64.shape, bool)
        max_rel = float(np.nanmax(rel[big])) if big.any() else 0.0
        ratio = float(np.nanmax(diff / (atol + rtol * np.abs(r64)))) if diff.size else 0.0
        per_output[name] = {"shape": list(o.shape), "max_abs_error": max_abs, "max_rel_error": max_rel,
                            "tolerance_used": ratio, "within_tolerance": within}
        if not within:
            ok = False
            worst = worst or (
                f"output {name!r}: max abs error {max_abs:.3g}, max rel error {max_rel:.3g} exceed atol {atol:g} + rtol {rtol:g}"
                + ("" if finite else " (non-finite values)")
            )
    result = {
        "ok": ok,
        "batch": int(batch),
        "example_batch": example_batch,
        "rtol": rtol,
        "atol": atol,
        "seed": seed,
        "max_abs_error": max((v["max_abs_error"] or 0.0) for v in per_output.values()) if per_output else 0.0,
        "max_rel_error": max((v["max_rel_error"] or 0.0) for v in per_output.values()) if per_output else 0.0,
        "tolerance_used": max((v["tolerance_used"] or 0.0) for v in per_output.values()) if per_output else 0.0,
        "outputs": per_output,
        "provider": "CPUExecutionProvider",
        "onnxruntime": ort.__version__,
    }
    if not ok:
        raise ParityError(f"ONNX parity check failed for {path} at batch {batch}: {worst}", result)
    return result


def _graph_io(path: Path) -> tuple[list, list]:
    """[{name, shape (ints, or the symbolic name), dtype}] of the ONNX graph's inputs and outputs."""
    import onnx

    model = onnx.load(str(path))

    def describe(values):
        rows = []
        for v in values:
            tt = v.type.tensor_type
            shape = [d.dim_param if d.dim_param else int(d.dim_value) for d in tt.shape.dim]
            rows.append({"name": v.name, "shape": shape, "dtype": onnx.TensorProto.DataType.Name(tt.elem_type).lower()})
        return rows

    return describe(model.graph.input), describe(model.graph.output)


def _pin_static_dims(path: Path, spec, example_outputs: tuple) -> None:
    """Write the static sizes (every dim but 0) into the graph's declared input/output shapes.

    The exporter's shape inference sometimes leaves a dim symbolic (e.g. ``Concatrotations_dim_1``
    after a concatenation) although only dim 0 is dynamic; the sizes are then taken from the
    example (inputs) and from the module's output on the example (outputs). A declared static size
    that disagrees is an error. The model is checked with ``onnx.checker`` afterwards.
    """
    import onnx

    model = onnx.load(str(path))
    declared = {v.name: v for v in list(model.graph.input) + list(model.graph.output)}
    wanted = dict(zip(spec.input_names, (tuple(t.shape) for t in spec.example_inputs)))
    wanted.update(zip(spec.output_names, (tuple(t.shape) for t in example_outputs)))
    for name, shape in wanted.items():
        if name not in declared:
            raise ValueError(f"{path}: the exported graph has no input/output named {name!r} (has {sorted(declared)})")
        dims = declared[name].type.tensor_type.shape.dim
        if len(dims) != len(shape):
            raise ValueError(f"{path}: {name!r} has rank {len(dims)} in the graph, {len(shape)} in PyTorch {shape}")
        for i, (d, size) in enumerate(zip(dims, shape)):
            if i == 0:
                d.ClearField("dim_value")
                d.dim_param = "batch"
            elif d.HasField("dim_value") and d.dim_value != size:
                raise ValueError(f"{path}: {name!r} dim {i} is {d.dim_value} in the graph, {size} in PyTorch {shape}")
            else:
                d.ClearField("dim_param")
                d.dim_value = int(size)
    onnx.checker.check_model(model, full_check=True)
    onnx.save(model, str(path))


class MissingPackageError(ImportError):
    """A package export-onnx needs is not installed (the message says how to install it)."""


def _is_export_record(path: Path) -> bool:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and "onnx_sha256" in data and data.get("exporter") is not None


def check_export_target(path: str | Path, overwrite: bool = False, weights: str | Path | None = None) -> Path:
    """Before anything loads: ``path`` ends in .onnx, is not a folder, its folder is writable; it and
    its record (:func:`sidecar_path`) are not the ``weights`` read; without ``overwrite`` neither
    exists; with it, what is replaced was written by an export (an existing record must be an
    export record, and an existing .onnx must have one): a training record ``NAME.json`` beside
    ``NAME.pt`` is never overwritten. Returns the path."""
    from benchmark.core.outdir import OutDirError, check_out_dir

    path = Path(path)
    if path.suffix != ".onnx":
        raise ValueError(f"--out {path}: the output must end in .onnx (its record is written beside it as .json)")
    if path.is_dir():
        raise ValueError(f"--out {path}: is a folder; give the output file, e.g. {path / 'decoder.onnx'}")
    record = sidecar_path(path)
    if weights is not None:
        w = Path(weights).expanduser().resolve()
        for p in (path, record):
            if p.expanduser().resolve() == w:
                raise OutDirError(f"--out {path}: would overwrite the --weights file {weights} it reads; choose another --out")
    if not overwrite:
        for p in (path, record):
            if p.exists():
                raise FileExistsError(f"{p} exists: pass --force to overwrite it, or --out FILE to write elsewhere")
    else:
        if record.exists() and not _is_export_record(record):
            raise OutDirError(f"--out {path}: {record}, where the export's record goes, exists and was not written by "
                              "export-onnx (a training record?); --force does not replace it: choose another --out")
        if path.exists() and not record.exists():
            raise OutDirError(f"--out {path}: exists without the record {record.name} an export writes beside it, so it "
                              "was not written by export-onnx; --force does not replace it: choose another --out")
    check_out_dir(path.parent if str(path.parent) else Path("."), min_free_bytes=1 << 20, what="the folder of --out")
    return path


def require_onnx_packages() -> None:
    """Raise :class:`MissingPackageError` naming each missing package and the install command.
    ``onnx`` and ``onnxruntime`` are normal dependencies (``pip install -e .`` brings them); an
    environment made otherwise may lack them."""
    import importlib

    missing = []
    for name, pin in (("onnx", "onnx>=1.15"), ("onnxruntime", "onnxruntime>=1.16")):
        try:
            importlib.import_module(name)
        except ImportError:
            missing.append((name, pin))
    if missing:
        names = " and ".join(repr(n) for n, _ in missing)
        raise MissingPackageError(f"export-onnx needs the package(s) {names}, not installed in this environment; "
                                  f"install them with: pip install {' '.join(repr(p) for _, p in missing)} "
                                  "(or reinstall the project: pip install -e .)")


def export_onnx(
    adapter,
    path: str | Path,
    opset: int = DEFAULT_OPSET,
    overwrite: bool = False,
    check: bool = True,
    batch: int = 3,
    rtol: float = 1e-3,
    atol: float = 1e-5,
) -> dict:
    """Export ``adapter.export_decoder()`` to ``path`` (.onnx) and write the record beside it.

    Dim 0 of every input and output is dynamic (``batch``). With ``check`` the file is checked by
    :func:`check_parity` (at ``batch``) before it is moved into place; a failure raises
    :class:`ParityError` and leaves no file. Raises :class:`NotExportableError` (a ValueError) when
    the prior has no exportable decoder and FileExistsError when ``path`` or its record exists and
    ``overwrite`` is False. Returns the record (also written to ``sidecar_path(path)``).
    """
    require_onnx_packages()
    import onnx
    import onnxruntime as ort

    from benchmark.core.provenance import git_info

    lo, hi = supported_opsets()
    if not lo <= int(opset) <= hi:
        raise ValueError(f"--opset {opset}: out of range; this torch exports opsets {lo}..{hi}")
    path = check_export_target(path, overwrite, adapter.weights_path)
    record_path = sidecar_path(path)
    spec = get_spec(adapter)

    path.parent.mkdir(parents=True, exist_ok=True)
    names = list(spec.input_names) + list(spec.output_names)
    dynamic_axes = {n: {0: "batch"} for n in names}
    module = spec.module.eval()
    with torch.no_grad():
        example_outputs = _outputs_tuple(module(*spec.example_inputs))
    if len(example_outputs) != len(spec.output_names):
        raise ValueError(f"the module returns {len(example_outputs)} outputs but ExportSpec.output_names has {len(spec.output_names)}")
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with warnings.catch_warnings():
            # the legacy exporter announces its deprecation and the trace warns about shape checks on
            # Python values; the parity check at another batch size is what proves the trace generalises
            warnings.simplefilter("ignore", category=DeprecationWarning)
            warnings.simplefilter("ignore", category=torch.jit.TracerWarning)
            try:
                with _output_quiet():  # a failed TorchScript export prints its whole graph (C++, fd 1)
                    torch.onnx.export(
                        module, tuple(spec.example_inputs), str(tmp), input_names=list(spec.input_names),
                        output_names=list(spec.output_names), dynamic_axes=dynamic_axes, opset_version=int(opset),
                        dynamo=False,
                    )
            except torch.onnx.errors.UnsupportedOperatorError as exc:
                raise ValueError(_opset_problem(adapter.name, int(opset), str(exc))) from None
        _pin_static_dims(tmp, spec, example_outputs)
        parity = check_parity(spec, tmp, batch=batch, rtol=rtol, atol=atol) if check else None
        inputs, outputs = _graph_io(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()

    weights = adapter.weights_path
    weights_file = Path(weights) if weights else None
    record = {
        "file": str(path),
        "prior": adapter.name,
        "size": adapter.size,
        "paper": adapter.paper,
        "weights": str(weights_file) if weights_file else None,
        "weights_sha256": sha256_file(weights_file) if weights_file is not None and weights_file.is_file() else None,
        "decoder_parameters": sum(p.numel() for p in module.parameters()),
        "inputs": inputs,
        "outputs": outputs,
        "dynamic_axes": dynamic_axes,
        "example_batch": int(spec.example_inputs[0].shape[0]),
        "opset": int(opset),
        "exporter": EXPORTER,
        "onnx_bytes": path.stat().st_size,
        "onnx_sha256": sha256_file(path),
        "parity": parity if parity is not None else {"ok": None, "note": "not checked (--no-check)"},
        "versions": {"torch": torch.__version__, "onnxruntime": ort.__version__, "onnx": onnx.__version__},
        "git": git_info(),
    }
    tmp_record = record_path.with_name(f".{record_path.name}.tmp")
    tmp_record.write_text(json.dumps(record, indent=2) + "\n")
    os.replace(tmp_record, record_path)
    log.info("wrote %s (%d bytes) and %s", path, record["onnx_bytes"], record_path)
    return record


__all__ = ["export_onnx", "check_parity", "get_spec", "sidecar_path", "sha256_file", "NotExportableError", "ParityError", "DEFAULT_OPSET"]
