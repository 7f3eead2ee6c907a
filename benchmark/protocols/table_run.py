"""Running a table: data, units, execution (resumable), derivation, writing."""

from __future__ import annotations

import hashlib
import logging
from collections import defaultdict
from pathlib import Path

log = logging.getLogger(__name__)


def load_motions(data: str | None, min_duration: float, body=None) -> dict:
    """Test motions by id: the synthetic test split by default, or a folder of motion files (each
    checked by its loader: :mod:`benchmark.plausibility`)."""
    files_by_id = {}
    if data is None:
        from benchmark.synthetic.splits import build_split

        motions = build_split("test")
        by_id = {m.source: m for m in motions}
    elif data.startswith("scans="):
        raise ValueError(f"--data {data}: captured scans are read by the completion protocol (table1) only")
    else:
        from benchmark.loaders.amass import load_amass
        from benchmark.motion import Motion

        root = Path(data.split("=", 1)[-1])
        files = sorted(root.rglob("*.npz")) if root.is_dir() else [root]
        if not files:
            raise FileNotFoundError(f"--data {data}: no .npz motion files under {root}")
        import numpy as np

        by_id = {}
        for f in files:
            try:
                with np.load(f, allow_pickle=False) as npz:
                    keys = set(npz.files)
            except Exception as exc:  # not a zip, a pickle, truncated...
                raise ValueError(f"--data {data}: {f} is not a readable .npz file ({type(exc).__name__}: {exc}); "
                                 "remove it from the folder or re-export it (python -m benchmark data convert)") from None
            try:
                m = load_amass(f) if "mocap_framerate" in keys or "mocap_frame_rate" in keys else Motion.load(f)
            except KeyError as exc:
                text = exc.args[0] if exc.args and isinstance(exc.args[0], str) and " " in exc.args[0] else \
                    f"{f}: no field {exc} (fields present: {sorted(keys)})"
                raise ValueError(f"--data {data}: {text}; convert the file with "
                                 "`python -m benchmark data convert FILE --out FILE.npz`") from None
            key = str(f.relative_to(root) if root.is_dir() else f.name)
            by_id[key], files_by_id[key] = m, str(f)
    if body is not None:
        by_id = {k: _shape_for_body(m, body, files_by_id.get(k)) for k, m in by_id.items()}
    short = [k for k, m in by_id.items() if m.duration + 1e-6 < min_duration]
    if short:
        log.warning("skipping %d motions shorter than the %.1f s window: %s", len(short), min_duration, short[:5])
    return {k: m for k, m in by_id.items() if k not in short}


def _shape_for_body(motion, body, where: str | None = None):
    """Keep a motion's shape when it belongs to this body family; SMPL betas are truncated or
    zero-padded to the body's count; a shape of another body is replaced by the neutral shape.
    The length is checked first (:func:`benchmark.plausibility.check_shape`: an implausible one is
    an error naming ``where``, the motion's file; default its source)."""
    import dataclasses

    import torch

    from benchmark.plausibility import SMPL_FAMILY, check_shape, shape_family

    if motion.shape is None:
        return motion
    src = shape_family(motion.body)
    kind = shape_family(str(getattr(body, "model_type", None) or body.name))  # "smplh-female" -> "smplh"
    if src == kind or (src in SMPL_FAMILY and kind in SMPL_FAMILY):
        check_shape(motion.shape, where or motion.source or "motion", body.name, kind, body.shape_dim)
        s = motion.shape.reshape(-1)[: body.shape_dim]
        s = torch.cat([s, s.new_zeros(body.shape_dim - s.numel())])
        return dataclasses.replace(motion, shape=s, body=body.name)
    log.info("motion %s: its %s shape does not apply to body %r; using the neutral shape", motion.source, src, body.name)
    return dataclasses.replace(motion, shape=None, body=None)


def select_sequences(motions_by_id: dict, count) -> list[str]:
    """A deterministic selection spread evenly over subjects (round robin over sorted ids)."""
    ids = sorted(motions_by_id)
    if count == "all" or count is None or int(count) >= len(ids):
        return ids
    groups = defaultdict(list)
    for sid in ids:
        groups[motions_by_id[sid].meta.get("subject", "")].append(sid)
    # spread within each subject too: take evenly spaced sequences
    n = int(count)
    order = sorted(groups)
    chosen = []
    for i, s in enumerate(order):
        g, q = groups[s], n // len(order) + (1 if i < n % len(order) else 0)
        step = len(g) / max(q, 1)
        chosen += [g[int(k * step)] for k in range(min(q, len(g)))]
    return sorted(chosen)


def _sha_file(path: str | None) -> str | None:
    if not path or not Path(path).is_file():
        return None
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def motion_sha256(motion) -> str:
    """Content hash of a motion as a unit reads it: its arrays (dtype, shape and bytes of poses,
    translation, timestamps, shape), its body name and its metadata. Two files holding different
    motions under one name hash differently; the same motion hashes the same wherever it lies."""
    import json

    import numpy as np

    if hasattr(motion, "content_sha256"):  # a capture (benchmark.loaders.scans.ScanSequence)
        return motion.content_sha256()
    h = hashlib.sha256()
    for name in ("poses", "trans", "timestamps", "shape"):
        value = getattr(motion, name, None)
        if value is None:
            h.update(f"{name}:none;".encode())
            continue
        arr = np.ascontiguousarray(value.detach().cpu().numpy() if hasattr(value, "detach") else np.asarray(value))
        h.update(f"{name}:{arr.dtype.str}:{arr.shape};".encode())
        h.update(arr.tobytes())
    h.update(f"body:{motion.body};".encode())
    h.update(json.dumps(motion.meta or {}, sort_keys=True, default=str).encode())
    return h.hexdigest()


# Protocol modules, by the ``protocol`` field of a table spec. Each module provides
#   make_source(spec, body, motions_by_id, seed) -> data source (builds and caches unit inputs)
#   run_unit(unit, spec, profile, adapter, body, source, device) -> unit result dict
#       {unit_id, spec_hash, prior, cell, sequence_ids, fingerprint, per_sequence: [{id, frames,
#        sums: {<si metric>: sum over frames}}], timings: {fit_s, eval_s}, device, na_reason, ...}
# and optionally
#   load_motions(spec, data, body) -> {id: Motion}   (default: :func:`load_motions` with the window)
#   na_reason(spec, adapter) -> str | None            (a prior that cannot serve the table: n/a cells)
PROTOCOL_MODULES = {
    "completion": "benchmark.protocols.completion_unit",
    "sls": "benchmark.protocols.sls",
    "denoise": "benchmark.protocols.denoise",
    "inbetween": "benchmark.protocols.inbetween",
    "reconstruction": "benchmark.protocols.reconstruction",
}


def protocol_module(spec):
    import importlib

    name = spec.get("protocol")
    if name not in PROTOCOL_MODULES:
        raise ValueError(f"{spec.get('_source', spec.get('name'))}: field 'protocol' is {name!r}; "
                         f"known protocols: {sorted(PROTOCOL_MODULES)}")
    return importlib.import_module(PROTOCOL_MODULES[name])


def na_result(unit, reason: str) -> dict:
    """The result of a unit that a prior cannot serve: no numbers, the reason in the JSON."""
    return {
        "unit_id": unit.unit_id, "spec_hash": unit.spec_hash, "prior": unit.prior, "cell": dict(unit.cell),
        "sequence_ids": list(unit.sequence_ids), "fingerprint": "n/a", "per_sequence": [],
        "timings": {"fit_s": 0.0, "eval_s": 0.0}, "device": "none", "na_reason": reason,
    }


class TableExecutor:
    """``execute(unit) -> unit result`` for one table run: the protocol, the built adapters (their
    weights), the body, and the data source with the test motions.

    It holds no closures and no open resources, so a backend can pickle it once and ship it to
    worker processes or Ray workers (:mod:`benchmark.backends`): the weights and the test split
    travel once per worker, never per unit. ``unit_cost`` lets a parallel backend order units
    longest-first.
    """

    def __init__(self, module_name: str, spec: dict, profile: dict, adapters: dict, body, source, device):
        self.module_name = module_name
        self.spec = spec
        self.profile = profile
        self.adapters = adapters
        self.body = body
        self.source = source
        self.device = device

    @property
    def module(self):
        import importlib

        return importlib.import_module(self.module_name)

    def __call__(self, unit) -> dict:
        module = self.module
        adapter = self.adapters[unit.prior]
        reason = module.na_reason(self.spec, adapter) if hasattr(module, "na_reason") else None
        if reason:
            return na_result(unit, reason)
        return module.run_unit(unit, self.spec, self.profile, adapter, self.body, self.source, self.device)

    def unit_cost(self, unit) -> float:
        """Relative cost of a unit (for longest-first ordering): the protocol's ``unit_cost`` when
        it has one, else :func:`benchmark.backends.estimate_cost`."""
        module = self.module
        if hasattr(module, "unit_cost"):
            return float(module.unit_cost(unit, self.spec, self.profile))
        from benchmark.backends import estimate_cost

        return estimate_cost(unit)


def run_table(spec, profile, priors, body, device, seed, out_dir: Path, resume="only-missing", size="embedded",
              weights=None, data=None, backend="local", backend_options: dict | None = None) -> dict:
    """Run a table and write it. ``backend``: ``"local"`` or ``"ray"`` (or a backend callable, see
    :mod:`benchmark.runner`); ``backend_options``: its options (local: ``jobs``; ray: ``address``,
    ``cpus_per_unit``, ``gpus_per_unit``), see :func:`benchmark.backends.make_backend`. The backend
    never changes a number."""
    from benchmark.backends import make_backend
    from benchmark.registry import make_adapter, weights_content_sha256
    from benchmark.results import derive_table, plan_units
    from benchmark.runner import run_units
    from benchmark.writers import format_markdown, write_table

    module = protocol_module(spec)
    weights = weights or {}
    unknown = set(weights) - set(priors)
    if unknown:
        raise ValueError(f"--weights given for priors not being run: {sorted(unknown)}")
    # build the backend first: a bad option fails before any data is loaded
    run_backend = backend if callable(backend) else make_backend(backend, device=str(device), **(backend_options or {}))
    if hasattr(module, "load_motions"):
        motions = module.load_motions(spec, data, body)
    else:
        motions = load_motions(data, float(spec["data"]["window_s"]), body)
    ids = select_sequences(motions, profile["sequences"])
    n_cells = 1
    for values in spec["grid"].values():
        n_cells *= len(values)
    print(f"{len(ids)} sequences, {len(priors)} priors, {n_cells} cells, {profile['steps']} steps per fit")

    # build every adapter before planning, so the spec hash covers the embedded weights' hashes
    adapters = {}
    prior_info = {}
    for name in priors:
        w = weights.get(name)
        adapters[name] = make_adapter(name, size=size, weights=w, device=device)
        # the content of every weights file the adapter read (embedded or given): new weights under
        # the same file name invalidate stored results
        prior_info[name] = {"size": size, "weights": w, "weights_sha256": _sha_file(w),
                            "embedded_sha256": getattr(adapters[name], "weights_sha256", None)
                            or weights_content_sha256(adapters[name])}

    # the content of the motion data each sequence id stands for enters its units' spec hash
    data_hashes = {sid: motion_sha256(motions[sid]) for sid in ids}
    units = plan_units(spec, profile, priors, ids, seed, device, prior_info, data_hashes=data_hashes)
    source = module.make_source(spec, body, motions, seed)
    execute = TableExecutor(module.__name__, spec, profile, adapters, body, source, device)

    report = run_units(units, execute, out_dir, resume=resume, backend=run_backend)
    results, failures = report
    meta = {"units": units, "profile": profile, "seed": seed, "device": str(device), "priors": prior_info,
            "sequences": ids, "data": data or "synthetic:test", "body": body.name, "resume": report.resume_counts()}
    table = derive_table(spec, results, meta)
    files = write_table(table, out_dir)
    return {"table": table, "markdown": format_markdown(table), "files": files, "failures": failures}
