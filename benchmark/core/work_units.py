"""Work units and their stored results: seeds, table-spec helpers, unit planning
(:func:`plan_units`), unit-result validation, checksums and loading (canonical JSON, its hashes and
the atomic files they are written with: :mod:`benchmark.core.json_io`).

A table run is split into independent *work units*: one prior x one grid cell x one batch of
sequences (:class:`WorkUnit`, planned by :func:`plan_units`). Each unit is fitted and evaluated by
the protocol (an ``execute(unit) -> dict`` callable that the caller provides) and its result is
stored as one JSON file per unit (:mod:`benchmark.run.runner` writes them). The public table is
*derived* from those per-sequence rows (:func:`benchmark.run.table_derive.derive_table`), never
accumulated by hand.

Unit-result dict (what ``execute`` returns; validated by :func:`validate_unit_result`)::

    {"unit_id": str, "spec_hash": str, "prior": str, "cell": {...}, "sequence_ids": [str],
     "fingerprint": str,                 # hash of the degraded observation this unit saw
     "per_sequence": [{"id": str, "frames": int,
                       "sums": {"chamfer_m": float, "chamfer_surface_m": float, "mpjpe_m": float}}],
     "timings": {"fit_s": float, "eval_s": float},
     "device": str,
     "na_reason": None | str}            # a unit whose prior cannot serve the cell: reason, no rows

Metric sums are SI (metres) summed over the output frames of one sequence, so merging is
addition: the mean over all frames of all sequences is ``total sum / total frames``. The
derivation (:mod:`benchmark.run.table_derive`) is the one place that converts to reported units
(``chamfer_m`` -> ``chamfer_mm``, :data:`UNIT_CONVERSIONS`).
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import logging
import math
import os
import re
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from benchmark.core.json_io import canonical_json, sha256_json

log = logging.getLogger("benchmark.results")  # the name it had before the split

# Keys of a table spec that do not change any unit's result (presentation, or the grid as a
# whole: a unit's own cell is part of its spec). Every other key is a rule and enters the hash.
NON_RULE_KEYS = frozenset({"name", "title", "paper", "grid", "description", "protocol_version", "headline_metric",
                           "default_priors", "same_cells", "scored_frames"})  # same_cells: benchmark.run.same_cells; scored_frames: the tables' header
# Keys of a profile that are not sizes.
NON_SIZE_PROFILE_KEYS = frozenset({"name", "description"})
# Reported-unit suffix -> (SI suffix used in the unit results' sums, factor SI -> reported).
UNIT_CONVERSIONS = {"_mm": ("_m", 1e3), "_cm": ("_m", 1e2), "_deg": ("_rad", 180.0 / math.pi)}
RESULT_KEYS = ("unit_id", "spec_hash", "prior", "cell", "sequence_ids", "fingerprint", "per_sequence",
               "timings", "device", "na_reason")
TABLE_FORMAT_VERSION = 1
_SAFE = re.compile(r"[^A-Za-z0-9._=-]+")


# --------------------------------------------------------------------------------------------
# Seeds
# --------------------------------------------------------------------------------------------

def derive_seed(table_seed: int, table: str, prior: str, cell: Mapping, batch_index: int) -> int:
    """Seed of one work unit, in [0, 2**32): a stable hash (sha256, not Python's salted ``hash()``)
    of the table run's seed, the table name, the prior name, the cell and the batch index. Usable
    by ``torch.Generator.manual_seed``, ``numpy.random.default_rng`` and ``random.seed`` alike."""
    digest = hashlib.sha256(canonical_json([int(table_seed), table, prior, dict(cell), int(batch_index)]).encode()).digest()
    return int.from_bytes(digest[:4], "big")


# --------------------------------------------------------------------------------------------
# Table spec helpers
# --------------------------------------------------------------------------------------------

def spec_source(table_spec: Mapping) -> str:
    """Where a table spec comes from, for error messages."""
    return str(table_spec.get("_source") or f"benchmark/tables/{table_spec.get('name', '<unnamed>')}.yaml")


def spec_field(table_spec: Mapping, key: str):
    if key not in table_spec:
        raise ValueError(f"{spec_source(table_spec)}: field {key!r} is missing; add it (see benchmark/tables/table1.yaml)")
    return table_spec[key]


def grid_cells(table_spec: Mapping) -> list[dict]:
    """Every cell of the spec's ``grid`` in grid order: the product of the value lists, the first
    key varying slowest (table1: points=100/fps=5, points=100/fps=10, points=1000/fps=5, ...)."""
    grid = spec_field(table_spec, "grid")
    if not isinstance(grid, Mapping) or not grid:
        raise ValueError(f"{spec_source(table_spec)}: field 'grid' must map each axis to a list of values, got {grid!r}")
    for key, values in grid.items():
        if not isinstance(values, list) or not values:
            raise ValueError(f"{spec_source(table_spec)}: grid axis {key!r} must be a non-empty list, got {values!r}")
        if len(set(map(canonical_json, values))) != len(values):
            raise ValueError(f"{spec_source(table_spec)}: grid axis {key!r} repeats a value: {values!r}")
    keys = list(grid)
    return [dict(zip(keys, combo)) for combo in itertools.product(*(grid[k] for k in keys))]


def grid_axes(table: Mapping) -> list[str]:
    """A table's grid axes in its spec's order (the first varying slowest). A table read back from
    JSON lists them sorted (table1: fps, points); its cells keep the grid order, so the order is the
    one under which the first row's cells are the product of the axes' values (:func:`grid_cells`).
    The listed order where none or several fit."""
    keys = list(table["grid"])
    cells = table["rows"][0]["cells"] if table.get("rows") else []
    fits = [list(order) for order in itertools.permutations(keys)
            if [tuple(c.get(k) for k in order) for c in cells]
            == list(itertools.product(*(table["grid"][k] for k in order)))]
    return fits[0] if len(fits) == 1 else keys


def table_rules(table_spec: Mapping) -> dict:
    """The rules of a table (everything that changes a unit's result): the spec without its
    presentation keys (:data:`NON_RULE_KEYS`); metrics reduced to their names."""
    rules = copy.deepcopy({k: v for k, v in table_spec.items() if k not in NON_RULE_KEYS and not k.startswith("_")})
    if "metrics" in rules:
        rules["metrics"] = [m["name"] for m in metric_specs(table_spec)]
    return rules


METRIC_DIRECTIONS = ("lower", "higher", "closest", "none")


def metric_specs(table_spec: Mapping) -> list[dict]:
    """The spec's ``metrics`` list, validated: each ``{name, better, description}``, ``better`` one of
    :data:`METRIC_DIRECTIONS`: ``lower`` / ``higher`` is better; ``closest``: the nearer to the metric
    named by ``reference`` (e.g. an acceleration to the ground truth's own) the better; ``none``: a
    reference figure, never ranked (no arrow, no best prior, no paired comparison). Optional:
    ``tolerance`` (``compare``'s default for it, in its unit) and ``timing: true`` (a measured time:
    ``compare`` reports it, never fails on it)."""
    metrics = spec_field(table_spec, "metrics")
    if not isinstance(metrics, list) or not metrics:
        raise ValueError(f"{spec_source(table_spec)}: field 'metrics' must be a non-empty list")
    out, seen = [], set()
    names = {m.get("name") for m in metrics if isinstance(m, Mapping)}
    for i, m in enumerate(metrics):
        if not isinstance(m, Mapping) or not isinstance(m.get("name"), str):
            raise ValueError(f"{spec_source(table_spec)}: metrics[{i}] must be a mapping with a 'name'")
        where = f"{spec_source(table_spec)}: metrics[{i}] ({m['name']})"
        better = m.get("better", "lower")
        if better not in METRIC_DIRECTIONS:
            raise ValueError(f"{where}: 'better' must be one of {', '.join(METRIC_DIRECTIONS)}, got {better!r}")
        if m["name"] in seen:
            raise ValueError(f"{spec_source(table_spec)}: metric {m['name']!r} is listed twice")
        seen.add(m["name"])
        entry = {"name": m["name"], "better": better, "description": m.get("description", "")}
        if better == "closest":
            ref = m.get("reference")
            if ref not in names or ref == m["name"]:
                raise ValueError(f"{where}: 'better: closest' needs 'reference', another metric of the table; got {ref!r}")
            entry["reference"] = ref
        if "tolerance" in m:
            tol = m["tolerance"]
            if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not tol >= 0:
                raise ValueError(f"{where}: 'tolerance' must be a number >= 0 (in the metric's unit), got {tol!r}")
            entry["tolerance"] = float(tol)
        if m.get("timing") is not None:
            if not isinstance(m["timing"], bool):
                raise ValueError(f"{where}: 'timing' must be true or false, got {m['timing']!r}")
            if m["timing"]:
                entry["timing"] = True
        out.append(entry)
    return out


def si_metric(name: str) -> tuple[str, float]:
    """The SI sum key and the SI -> reported factor of a reported metric name
    (``chamfer_mm`` -> ``("chamfer_m", 1000.0)``); a name without a known unit suffix is its own
    SI key (factor 1)."""
    for suffix, (si_suffix, factor) in UNIT_CONVERSIONS.items():
        if name.endswith(suffix):
            return name[: -len(suffix)] + si_suffix, factor
    return name, 1.0


def profile_sizes(profile: Mapping) -> dict:
    """A profile's sizes (everything but its name and description)."""
    return {k: v for k, v in profile.items() if k not in NON_SIZE_PROFILE_KEYS}


# --------------------------------------------------------------------------------------------
# Work units
# --------------------------------------------------------------------------------------------

def _safe(text: str) -> str:
    return _SAFE.sub("-", str(text)).strip("-") or "x"


def make_unit_id(table: str, prior: str, cell: Mapping, batch_index: int) -> str:
    """Readable, filesystem-safe id: ``table1__vposer-slerp__points=100_fps=5__b000``."""
    cell_part = "_".join(f"{_safe(k)}={_safe(v)}" for k, v in cell.items())
    return f"{_safe(table)}__{_safe(prior)}__{cell_part}__b{batch_index:03d}"


@dataclass(frozen=True, eq=True)
class WorkUnit:
    """One prior x one grid cell x one batch of sequences.

    ``spec`` holds everything that determines the result (table name, protocol version, the
    table's rules, profile sizes, the prior's identity, the cell, the sequence ids, the seed);
    ``spec_hash`` is the sha256 of its canonical JSON. A stored result is "done" for this unit
    when its file exists and its ``spec_hash`` matches.
    """

    table: str
    prior: str
    cell: dict
    sequence_ids: list
    batch_index: int
    seed: int
    profile: str
    device: str
    spec: dict = field(repr=False)
    spec_hash: str = ""

    __hash__ = None  # holds dicts and lists: not hashable; use unit_id as a key

    @property
    def unit_id(self) -> str:
        return make_unit_id(self.table, self.prior, self.cell, self.batch_index)

    @property
    def cell_key(self) -> str:
        return canonical_json(self.cell)


def plan_units(
    table_spec: Mapping,
    profile: Mapping,
    priors: Sequence[str],
    sequence_ids: Sequence[str],
    seed: int,
    device: str,
    prior_info: Mapping[str, Mapping],
    data_hashes: Mapping[str, str] | None = None, threads: int = 1,
) -> list[WorkUnit]:
    """Split a table run into work units: every prior x every cell x every batch.

    table_spec: a table spec (``catalog.load_table_spec``); never mutated.
    profile: a profile dict with its ``name`` (``catalog.get_profile``); ``batch_sequences`` sets
        the batch size.
    priors: prior names, in the order the table lists them.
    sequence_ids: the test sequences (already chosen by the profile), split in this order into
        batches of ``profile["batch_sequences"]``.
    seed: the table run's seed; each unit's seed is :func:`derive_seed` of it.
    prior_info: for every prior, a JSON-serialisable dict of what identifies its model (size,
        weights sha256...); it enters the spec hash so new weights invalidate stored results.
        Pass ``{}`` for a prior with nothing to identify.
    data_hashes: sequence id -> content hash of the motion data a unit reads for it
        (:func:`benchmark.run.table_run.motion_sha256`). When given, each unit's spec holds
        ``"data": [hash per sequence of the batch]``, so a sequence whose file was replaced by
        another motion under the same name invalidates the stored result.
    threads: each unit's torch threads (the backend's); other than 1, ``torch_threads`` in the spec (it changes numbers).

    Returns units in prior-major, then grid, then batch order.
    """
    src = spec_source(table_spec)
    table = spec_field(table_spec, "name")
    protocol_version = spec_field(table_spec, "protocol_version")
    cells = grid_cells(table_spec)
    rules = table_rules(table_spec)
    metric_specs(table_spec)  # validate early
    if "name" not in profile:
        raise ValueError("profile has no 'name': pass catalog.get_profile(NAME), which adds it")
    batch = profile.get("batch_sequences")
    if not isinstance(batch, int) or isinstance(batch, bool) or batch < 1:
        raise ValueError(f"profile {profile['name']!r}: 'batch_sequences' must be a positive integer, got {batch!r} (benchmark/profiles.yaml)")
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise ValueError(f"seed must be an int, got {seed!r}")
    priors = list(priors)
    if not priors:
        raise ValueError(f"{src}: no priors to run")
    if len(set(priors)) != len(priors):
        raise ValueError(f"priors listed twice: {priors!r}")
    missing = [p for p in priors if p not in prior_info]
    if missing:
        raise ValueError(f"prior_info has no entry for {missing!r}; pass {{}} for a prior with no weights to identify")
    ids = [str(s) for s in sequence_ids]
    if not ids:
        raise ValueError(f"{src}: no sequences to run (profile {profile['name']!r})")
    if len(set(ids)) != len(ids):
        dup = sorted({s for s in ids if ids.count(s) > 1})
        raise ValueError(f"sequence ids repeat: {dup[:5]!r}")
    if data_hashes is not None:
        lost = [s for s in ids if not isinstance(data_hashes.get(s), str)]
        if lost:
            raise ValueError(f"data_hashes has no content hash for sequence(s) {lost[:5]!r}")
    batches = [ids[i : i + batch] for i in range(0, len(ids), batch)]
    sizes = profile_sizes(profile)

    units: list[WorkUnit] = []
    for prior in priors:
        prior_spec = {"name": prior, **dict(prior_info[prior])}
        for cell in cells:
            for b, batch_ids in enumerate(batches):
                unit_seed = derive_seed(seed, table, prior, cell, b)
                spec = {
                    "table": table,
                    "protocol_version": protocol_version,
                    "rules": rules,
                    "profile": sizes,
                    "prior": prior_spec,
                    "cell": dict(cell),
                    "sequence_ids": list(batch_ids),
                    "seed": unit_seed,
                }
                if data_hashes is not None:
                    spec["data"] = [data_hashes[s] for s in batch_ids]
                spec.update({"torch_threads": int(threads)} if threads != 1 else {})
                units.append(WorkUnit(table=table, prior=prior, cell=dict(cell), sequence_ids=list(batch_ids),
                                      batch_index=b, seed=unit_seed, profile=profile["name"], device=device,
                                      spec=spec, spec_hash=sha256_json(spec)))
    seen: dict[str, WorkUnit] = {}
    for u in units:
        if u.unit_id in seen:
            raise ValueError(f"two work units share the id {u.unit_id!r} (prior names {seen[u.unit_id].prior!r} and "
                             f"{u.prior!r} differ only in characters a file name cannot hold); rename one")
        seen[u.unit_id] = u
    return units


# --------------------------------------------------------------------------------------------
# Unit results
# --------------------------------------------------------------------------------------------

def _finite_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def validate_unit_result(result: Any, unit: WorkUnit | None = None, source: str = "unit result") -> dict:
    """Check a unit-result dict (see the module docstring); return it unchanged or raise ValueError
    naming ``source`` and the field. With ``unit``, also check it belongs to that unit (id, spec
    hash, and exactly its sequences)."""
    if not isinstance(result, Mapping):
        raise ValueError(f"{source}: expected a dict, got {type(result).__name__}")
    missing = [k for k in RESULT_KEYS if k not in result]
    if missing:
        raise ValueError(f"{source}: missing field(s) {missing}; a unit result has {list(RESULT_KEYS)}")
    uid = result["unit_id"]
    if unit is not None:
        if uid != unit.unit_id:
            raise ValueError(f"{source}: unit_id {uid!r} does not match the unit {unit.unit_id!r}")
        if result["spec_hash"] != unit.spec_hash:
            raise ValueError(f"{source}: spec_hash {result['spec_hash']!r} does not match the unit's {unit.spec_hash!r}; "
                             "return unit.spec_hash unchanged")
        if result["prior"] != unit.prior or dict(result["cell"]) != unit.cell:
            raise ValueError(f"{source}: prior/cell {result['prior']!r} {result['cell']!r} do not match the unit's "
                             f"{unit.prior!r} {unit.cell!r}")
    if not isinstance(result["fingerprint"], str) or not result["fingerprint"]:
        raise ValueError(f"{source}: 'fingerprint' must be a non-empty string (a hash of the degraded observation)")
    timings = result["timings"]
    if not isinstance(timings, Mapping) or any(not _finite_number(timings.get(k)) or timings[k] < 0 for k in ("fit_s", "eval_s")):
        raise ValueError(f"{source}: 'timings' must hold finite, non-negative 'fit_s' and 'eval_s' seconds, got {timings!r}")
    na = result["na_reason"]
    rows = result["per_sequence"]
    if na is not None:
        if not isinstance(na, str) or not na.strip():
            raise ValueError(f"{source}: 'na_reason' must be None or a non-empty string, got {na!r}")
        if rows:
            raise ValueError(f"{source}: a unit with na_reason {na!r} must have no per_sequence rows")
        return result
    if not isinstance(rows, list) or not rows:
        raise ValueError(f"{source}: 'per_sequence' must be a non-empty list (or set na_reason)")
    ids = []
    for i, row in enumerate(rows):
        where = f"{source}: per_sequence[{i}]"
        if not isinstance(row, Mapping) or not isinstance(row.get("id"), str):
            raise ValueError(f"{where}: needs a string 'id'")
        frames = row.get("frames")
        if not isinstance(frames, int) or isinstance(frames, bool) or frames < 1:
            raise ValueError(f"{where} ({row['id']}): 'frames' must be a positive int, got {frames!r}")
        sums = row.get("sums")
        if not isinstance(sums, Mapping) or not sums:
            raise ValueError(f"{where} ({row['id']}): 'sums' must be a non-empty dict of metric sums in SI units")
        for k, v in sums.items():
            if not _finite_number(v):
                raise ValueError(f"{where} ({row['id']}): sums[{k!r}] = {v!r} is not a finite number")
        ids.append(row["id"])
    if len(set(ids)) != len(ids):
        raise ValueError(f"{source}: per_sequence repeats a sequence id")
    expected = unit.sequence_ids if unit is not None else result["sequence_ids"]
    if sorted(ids) != sorted(expected):
        extra, lost = sorted(set(ids) - set(expected)), sorted(set(expected) - set(ids))
        raise ValueError(f"{source}: per_sequence ids differ from the unit's sequences (extra {extra[:5]}, missing {lost[:5]})")
    return result


CHECKSUM_KEY = "checksum"


def unit_checksum(record: Mapping) -> str:
    """sha256 of a stored unit record's canonical JSON, without its own ``checksum`` field. The
    runner stores it in the file and checks it before reuse: a file edited by hand (or damaged)
    no longer matches and is moved aside instead of trusted."""
    return sha256_json({k: v for k, v in record.items() if k != CHECKSUM_KEY})


def with_checksum(record: Mapping) -> dict:
    """``record`` plus its ``checksum`` field (:func:`unit_checksum`)."""
    out = {k: v for k, v in record.items() if k != CHECKSUM_KEY}
    out[CHECKSUM_KEY] = unit_checksum(out)
    return out


def checksum_problem(record: Mapping) -> str | None:
    """Why a stored record's checksum does not vouch for it, or None when it matches."""
    stored = record.get(CHECKSUM_KEY)
    if not isinstance(stored, str):
        return "no checksum (written by an older version, or edited)"
    if stored != unit_checksum(record):
        return "contents do not match the file's own checksum (edited or damaged)"
    return None


def unit_path(out_dir: str | os.PathLike, unit_id: str) -> Path:
    """Where a unit's result lives: ``<out_dir>/units/<unit_id>.json``."""
    return Path(out_dir) / "units" / f"{unit_id}.json"


def load_unit_results(out_dir: str | os.PathLike, units: Iterable[WorkUnit]) -> list[dict]:
    """The stored results of ``units`` that are done (file exists, spec hash matches, valid, its
    own checksum matches), in plan order. Missing or stale ones are skipped (the derived cell then says it is incomplete)."""
    found = []
    for unit in units:
        path = unit_path(out_dir, unit.unit_id)
        if not path.exists():
            continue
        try:
            result = json.loads(path.read_text(encoding="utf-8"))
            validate_unit_result(result, unit, source=str(path))
            problem = checksum_problem(result)
            if problem:
                raise ValueError(problem)
        except (ValueError, OSError) as exc:
            log.warning("skipping %s: %s", path, exc)
            continue
        found.append(result)
    return found


# -- what the protocols and the runner share about a unit -------------------------------------------
def select_sequences(motions_by_id: dict, count) -> list[str]:
    """A deterministic selection spread evenly over subjects (meta "subject"; a non-string one by its JSON)."""
    ids = sorted(motions_by_id)
    if count == "all" or count is None or int(count) >= len(ids):
        return ids
    groups = defaultdict(list)
    for sid in ids:
        s = motions_by_id[sid].meta.get("subject", "")
        groups[s if isinstance(s, str) else canonical_json(s)].append(sid)
    # spread within each subject too: take evenly spaced sequences
    n = int(count)
    order = sorted(groups)
    chosen = []
    for i, s in enumerate(order):
        g, q = groups[s], n // len(order) + (1 if i < n % len(order) else 0)
        step = len(g) / max(q, 1)
        chosen += [g[int(k * step)] for k in range(min(q, len(g)))]
    return sorted(chosen)


def stable_seed(*parts) -> int:
    """A 32-bit seed from any parts (their ``str`` joined by ``|``, SHA-256): the same parts give the
    same seed on every machine and in every process."""
    h = hashlib.sha256("|".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(h[:4], "little")


_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?")


def estimate_cost(unit) -> float:
    """A unit's relative cost for ordering (only its rank matters): the number of sequences times
    the product of ``1 + |v|`` over the numbers in its cell (table1: points and fps; sls:
    ``p10000`` reads as 10000). A heuristic: more observed points, frames, noise or gap cost more."""
    cost = float(max(1, len(unit.sequence_ids)))
    for value in unit.cell.values():
        if isinstance(value, bool):
            continue
        if isinstance(value, (int, float)):
            numbers = [float(value)]
        else:
            numbers = [float(m) for m in _NUMBER.findall(str(value))]
        for v in numbers:
            if math.isfinite(v):
                cost *= 1.0 + abs(v)
    return cost


def na_result(unit, reason: str) -> dict:
    """The result of a unit that a prior cannot serve: no numbers, the reason in the JSON."""
    return {
        "unit_id": unit.unit_id, "spec_hash": unit.spec_hash, "prior": unit.prior, "cell": dict(unit.cell),
        "sequence_ids": list(unit.sequence_ids), "fingerprint": "n/a", "per_sequence": [],
        "timings": {"fit_s": 0.0, "eval_s": 0.0}, "device": "none", "na_reason": reason,
    }
