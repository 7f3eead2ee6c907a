"""A fake protocol for the runner/results tests: deterministic made-up per-frame errors per sequence.

Each sequence's per-frame errors (metres) are drawn from a numpy generator seeded by a stable hash of
the unit seed and the sequence id, so tests can recompute the naive reference (concatenate every
frame, take the mean) independently of the derivation.
"""

from __future__ import annotations

import copy
import hashlib

import numpy as np

from benchmark.run.catalog import load_table_spec
from benchmark.core.work_units import plan_units

PRIORS = ["vposer-slerp", "hmvae", "sequential-primitives"]


def table_spec(**objective_changes) -> dict:
    spec = copy.deepcopy(load_table_spec("table1"))  # the catalog caches it: never mutate the original
    spec["objective"].update(objective_changes)
    return spec


def profile(name: str = "smoke", **changes) -> dict:
    """A fixed profile (independent of the shipped profiles.yaml, which may be retuned)."""
    base = {"name": name, "description": f"{name} (test fixture)", "sequences": 2, "steps": 30, "batch_sequences": 8}
    return {**base, **changes}


def plan(spec=None, prof=None, priors=PRIORS, seqs=("s0", "s1", "s2"), seed=0, prior_info=None):
    spec = spec or table_spec()
    prof = prof or profile(batch_sequences=2)
    info = prior_info if prior_info is not None else {p: {} for p in priors}
    return plan_units(spec, prof, list(priors), list(seqs), seed, "cpu", info)


def frame_errors(unit_seed: int, seq_id: str, metric: str) -> np.ndarray:
    """Per-frame errors (metres) of one sequence; its length (frames) varies with the sequence."""
    h = int.from_bytes(hashlib.sha256(f"{unit_seed}/{seq_id}/{metric}".encode()).digest()[:8], "big")
    rng = np.random.default_rng(h)
    frames = 20 + int.from_bytes(hashlib.sha256(seq_id.encode()).digest()[:2], "big") % 100
    scale = {"chamfer_m": 0.02, "chamfer_surface_m": 0.008, "mpjpe_m": 0.05}[metric]
    return scale * rng.gamma(2.0, 1.0, size=frames)


class FakeExecutor:
    """execute(unit) -> unit result; counts calls; can fail or return n/a for chosen units."""

    def __init__(self, fail=(), na=None, metrics=("chamfer_m", "chamfer_surface_m", "mpjpe_m")):
        self.calls: list[str] = []
        self.fail = set(fail)  # unit ids that raise
        self.na = na or (lambda unit: None)  # unit -> reason or None
        self.metrics = metrics

    def __call__(self, unit) -> dict:
        self.calls.append(unit.unit_id)
        if unit.unit_id in self.fail:
            raise RuntimeError(f"simulated failure in {unit.unit_id}")
        reason = self.na(unit)
        rows = []
        if reason is None:
            for sid in unit.sequence_ids:
                errs = {m: frame_errors(unit.seed, sid, m) for m in self.metrics}
                frames = len(next(iter(errs.values())))
                rows.append({"id": sid, "frames": frames, "sums": {m: float(e.sum()) for m, e in errs.items()}})
        return {
            "unit_id": unit.unit_id, "spec_hash": unit.spec_hash, "prior": unit.prior, "cell": unit.cell,
            "sequence_ids": unit.sequence_ids,
            "fingerprint": hashlib.sha256(f"obs/{unit.cell}/{unit.sequence_ids}".encode()).hexdigest(),  # one observation per cell and batch, as every protocol
            "per_sequence": rows, "timings": {"fit_s": 1.5, "eval_s": 0.25}, "device": "cpu", "na_reason": reason,
        }


def meta(units, prof=None, **extra) -> dict:
    return {"units": units, "profile": prof or profile(batch_sequences=2), "seed": 0, "device": "cpu",
            "provenance": {"git": {"revision": "0123456789abcdef", "dirty": False}, "timestamp": "2026-01-01T00:00:00+00:00"},
            **extra}
