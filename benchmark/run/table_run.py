"""Running a table: data, units, execution (resumable), derivation, writing."""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def _version(package: str) -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(package)
    except PackageNotFoundError:
        return None


def _sha_file(path: str | None) -> str | None:
    if not path or not Path(path).is_file():
        return None
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def motion_sha256(motion) -> str:
    """Content hash of a motion as a unit reads it: its arrays (dtype, shape and bytes of poses,
    translation, timestamps, shape), its body name and its metadata. Two files holding different
    motions under one name hash differently; the same motion hashes the same wherever it lies."""
    import numpy as np

    if hasattr(motion, "content_sha256"):  # a capture (benchmark.loaders.scans.ScanSequence), under the scan rules' revision
        from benchmark.protocols.scan_completion import SCAN_RULES_REVISION

        return hashlib.sha256(f"{motion.content_sha256()};scan-rules:{SCAN_RULES_REVISION}".encode()).hexdigest()
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
    meta = {k: v for k, v in (motion.meta or {}).items() if k not in PROVENANCE_ONLY}
    h.update(json.dumps(meta, sort_keys=True, default=str).encode())
    return h.hexdigest()


# metadata that says where a motion was read from, not what it is: left out of its hash (a moved or
# re-spelt --data folder reuses its units)
PROVENANCE_ONLY = ("file",)


def body_identity(body) -> dict | None:
    """What identifies a body model read from a user's file (its kind, name, shape components and the
    file's sha256), which enters every unit's data hash: another SMPL file, gender or kind reruns the
    units. None for the embedded Anny body (its units' hashes stay as stored; its observations'
    fingerprints cover its cache build)."""
    path = getattr(body, "source_path", None)
    if path is None:
        return None
    return {"body": body.name, "kind": getattr(body, "model_type", None), "shape_dim": int(body.shape_dim),
            "file_sha256": _sha_file(str(path))}


def with_body(data_hash: str, identity: dict | None) -> str:
    """A sequence's data hash on a body read from a file (:func:`body_identity`); as it is on Anny."""
    if identity is None:
        return data_hash
    return hashlib.sha256(f"{data_hash};body:{json.dumps(identity, sort_keys=True)}".encode()).hexdigest()


def prior_identity(adapter, size: str, weights: str | None, name: str | None = None) -> dict:
    """What identifies a prior's numbers in its work units' spec hash: its size, the weights given,
    the content of every weights file it read (embedded or given: new weights under the same file
    name invalidate stored results) and, from revision 2 on, its adapter's revision
    (:attr:`priors.base.PriorAdapter.adapter_revision`: a change of its code that moves its numbers).
    ``name``: the registry name it was built under (its entry point; default ``adapter.name``), which
    finds the distribution of a plugged-in prior."""
    from benchmark.run.registry import weights_content_sha256

    info = {"size": size, "weights": weights, "weights_sha256": _sha_file(weights),
            "embedded_sha256": weights_content_sha256(adapter)}
    if info["weights_sha256"] is None and info["embedded_sha256"] is None and adapter.parameter_count() > 0:
        info["untrained"] = True  # a network that read no weights file (left out otherwise: stored hashes keep)
    revision = int(getattr(adapter, "adapter_revision", 1))
    if revision != 1:
        info["adapter_revision"] = revision
    plugin = plugin_origin(name or adapter.name)
    if plugin is not None:  # a prior from another package: its distribution and version (a new version reruns it)
        info["plugin"] = plugin
    return info


PROJECT_DISTRIBUTION = "motion-prior-benchmark"


def plugin_origin(name: str) -> str | None:
    """``"<distribution> <version> (<module:Class>)"`` of a prior another installed package
    registers by entry point; None for this project's own priors and those registered at run time."""
    from benchmark.run.registry import registry

    entry = registry().get(name)
    if entry is None or entry.origin == "runtime" or entry.origin.split(" ")[0] == PROJECT_DISTRIBUTION:
        return None
    return f"{entry.origin} ({entry.target})"


def table_protocol(spec):
    """The protocol instance of a table spec: its ``protocol`` field looked up in the protocol
    registry (:mod:`benchmark.protocols.registry`, entry-point group ``benchmark.protocols``); the
    interface is :class:`benchmark.protocols.base.Protocol`. A key of the spec's rule sections the
    protocol does not accept (its ``spec_keys``) is refused here, before any work."""
    from benchmark.protocols.base import check_spec_keys
    from benchmark.protocols.registry import make_protocol

    name = spec.get("protocol")
    try:
        protocol = make_protocol(name)
    except KeyError as exc:
        raise ValueError(f"{spec.get('_source', spec.get('name'))}: field 'protocol' is {name!r}: {exc.args[0]}") from None
    check_spec_keys(spec, protocol)
    return protocol


class TableExecutor:
    """``execute(unit) -> unit result`` for one table run: the protocol
    (:class:`benchmark.protocols.base.Protocol`), the built adapters (their weights), the body, and
    the data source with the test motions.

    It holds no closures and no open resources, so a backend can pickle it once and ship it to
    worker processes or Ray workers (:mod:`benchmark.run.backends`): the weights and the test split
    travel once per worker, never per unit (the protocol instance travels by reference to its
    class). ``unit_cost`` lets a parallel backend order units longest-first.
    """

    def __init__(self, protocol, spec: dict, profile: dict, adapters: dict, body, source, device,
                 start_cache_folder: Path | None = None):
        self.protocol = protocol
        self.spec = spec
        self.profile = profile
        self.adapters = adapters
        self.body = body
        self.source = source
        self.device = device
        self.start_cache = None  # (folder, namespace): the prior-free searches on disk (use_start_cache)
        if start_cache_folder is not None:
            self.use_start_cache(start_cache_folder)

    def use_start_cache(self, folder: Path) -> None:
        """Keep the prior-free searches (facing, limb start) in ``folder``, for the run's other workers
        and its resumptions (:mod:`benchmark.protocols.start_cache`)."""
        from benchmark.core.work_units import table_rules
        from benchmark.protocols.start_cache import search_rules, start_namespace

        body = body_identity(self.body) or {"body": self.body.name, "anny": _version("anny")}
        identity = {"table": self.spec.get("name"), "protocol_version": self.spec.get("protocol_version"),
                    "rules": search_rules(table_rules(self.spec)), "body": body}
        self.start_cache = (Path(folder), start_namespace(identity))

    def __call__(self, unit) -> dict:
        from benchmark.protocols.start_cache import use_start_cache

        adapter = self.adapters[unit.prior]
        reason = self.protocol.na_reason(self.spec, adapter)
        if reason:
            from benchmark.core.work_units import na_result

            return na_result(unit, reason)
        with use_start_cache(*(self.start_cache or (None, ""))):
            return self.protocol.run_unit(unit, self.spec, self.profile, adapter, self.body, self.source, self.device)

    def unit_cost(self, unit) -> float:
        """Relative cost of a unit (for longest-first ordering): the protocol's ``unit_cost``
        (default :func:`benchmark.core.work_units.estimate_cost`)."""
        return float(self.protocol.unit_cost(unit, self.spec, self.profile))


def run_table(spec, profile, priors, body, device, seed, out_dir: Path, resume="only-missing", size="embedded",
              weights=None, data=None, backend="local", backend_options: dict | None = None) -> dict:
    """Run a table and write it. ``backend``: ``"local"`` or ``"ray"`` (or a backend callable, see
    :mod:`benchmark.run.runner`); ``backend_options``: its options (local: ``jobs``; ray: ``address``,
    ``cpus_per_unit``, ``gpus_per_unit``), see :func:`benchmark.run.backends.make_backend`. The backend
    never changes a number."""
    from benchmark.run.backends import backend_threads, make_backend
    from benchmark.run.registry import check_weights_option, make_adapter
    from benchmark.run.runner import run_units
    from benchmark.run.table_derive import derive_table
    from benchmark.core.work_units import plan_units, select_sequences
    from benchmark.run.writers import format_markdown, write_table

    from benchmark.run.same_cells import same_cells
    from benchmark.protocols.start_cache import START_CACHE_FOLDER, forget_starts

    protocol = table_protocol(spec)
    same_cells(spec)  # a malformed same_cells entry fails here, not when the table is derived after every unit
    weights = weights or {}
    check_weights_option(weights, priors)
    # build the backend first: a bad option fails before any data is loaded
    run_backend = backend if callable(backend) else make_backend(backend, device=str(device), **(backend_options or {}))
    motions = protocol.load_motions(spec, data, body)
    ids = select_sequences(motions, profile["sequences"])
    n_cells = 1
    for values in spec["grid"].values():
        n_cells *= len(values)
    capped = str((spec.get("objective") or {}).get("step_rule", "cosine")) == "plateau"
    steps = f"each fit to its plateau, at most {profile['steps']} steps" if capped else f"{profile['steps']} steps per fit"
    print(f"{len(ids)} sequences, {len(priors)} priors, {n_cells} cells, {steps}")

    # build every adapter before planning, so the spec hash covers the embedded weights' hashes
    adapters = {}
    prior_info = {}
    for name in priors:
        w = weights.get(name)
        adapters[name] = make_adapter(name, size=size, weights=w, device=device)
        prior_info[name] = prior_identity(adapters[name], size, w, name)
        if prior_info[name].get("untrained"):
            log.warning("%s read no weights file: its row measures an untrained network (the table marks it)", name)

    # the content of the motion data each sequence id stands for, and the body file it is posed on,
    # enter its units' spec hash
    body_id = body_identity(body)
    data_hashes = {sid: with_body(motion_sha256(motions[sid]), body_id) for sid in ids}
    units = plan_units(spec, profile, priors, ids, seed, device, prior_info, data_hashes=data_hashes,
                       threads=backend_threads(run_backend))
    source = protocol.make_source(spec, body, motions, seed)
    # the prior-free searches on disk, for the other workers and a resumed run (Ray's workers may not share this disk)
    starts = Path(out_dir) / Path(*START_CACHE_FOLDER)
    if resume == "never" and forget_starts(starts):
        log.info("--resume never: the stored prior-free starts are searched again")
    execute = TableExecutor(protocol, spec, profile, adapters, body, source, device, None if backend == "ray" else starts)

    report = run_units(units, execute, out_dir, resume=resume, backend=run_backend,
                       carry=lambda unit: protocol.carry_problem(spec))
    results, failures = report
    meta = {"units": units, "profile": profile, "seed": seed, "device": str(device), "priors": prior_info,
            "sequences": ids, "data": data or "synthetic:test", "body": body.name, "resume": report.resume_counts()}
    table = derive_table(spec, results, meta)
    files = write_table(table, out_dir)
    return {"table": table, "markdown": format_markdown(table), "files": files, "failures": failures,
            "errors": report.errors}
