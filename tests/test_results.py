"""Work-unit planning, unit-result validation, atomic files and the table derivation."""

import hashlib
import json
import os

import numpy as np
import pytest

from benchmark.run.table_derive import derive_table
from benchmark.core.json_io import atomic_write_json, atomic_write_text, canonical_json
from benchmark.core.work_units import validate_unit_result
from benchmark.run.catalog import load_table_spec
from benchmark.core.provenance import collect_provenance
from fake_units import PRIORS, FakeExecutor, frame_errors, meta, plan, profile, table_spec


# ---------------------------------------------------------------- planning

def test_plan_counts_batches_and_order():
    units = plan(seqs=[f"s{i}" for i in range(5)], prof=profile(batch_sequences=2))
    assert len(units) == 3 * 6 * 3  # priors x cells x ceil(5 / 2) batches
    first = units[:3]
    assert [u.sequence_ids for u in first] == [["s0", "s1"], ["s2", "s3"], ["s4"]]
    assert [u.batch_index for u in first] == [0, 1, 2]
    assert first[0].unit_id == "table1__vposer-slerp__points=100_fps=5__b000"
    assert first[2].unit_id == "table1__vposer-slerp__points=100_fps=5__b002"
    # prior-major, then grid order (first axis slowest), then batch
    assert [u.prior for u in units[::18]] == PRIORS
    assert [tuple(u.cell.values()) for u in units[:18:3]] == [(100, 5), (100, 10), (1000, 5), (1000, 10), (10000, 5), (10000, 10)]
    assert all(u.profile == "smoke" and u.device == "cpu" and u.table == "table1" for u in units)
    assert len({u.unit_id for u in units}) == len(units)


def test_plan_is_stable_and_seeds_are_a_stable_hash():
    a, b = plan(), plan()
    assert [(u.unit_id, u.seed, u.spec_hash) for u in a] == [(u.unit_id, u.seed, u.spec_hash) for u in b]
    assert len({u.seed for u in a}) == len(a)  # every unit its own stream
    u = a[0]
    # independent recomputation of the documented derivation (sha256 of the canonical JSON)
    text = json.dumps([0, "table1", "vposer-slerp", {"fps": 5, "points": 100}, 0], separators=(",", ":"))
    assert u.seed == int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "big")
    assert u.seed == 2419270992  # golden: must not change between processes, machines or versions
    assert 0 <= u.seed < 2**32
    assert u.spec_hash == hashlib.sha256(canonical_json(u.spec).encode()).hexdigest()
    assert u.spec["seed"] == u.seed and u.spec["sequence_ids"] == u.sequence_ids and u.spec["cell"] == u.cell


def test_spec_hash_follows_the_rules_not_the_presentation():
    base = {u.unit_id: u.spec_hash for u in plan()}

    def hashes(**kw):
        return {u.unit_id: u.spec_hash for u in plan(**kw)}

    changed_rule = hashes(spec=table_spec(lambda_prior=0.02))
    assert changed_rule.keys() == base.keys() and all(changed_rule[k] != base[k] for k in base)
    spec = table_spec()
    spec["title"] = "another title"
    spec["paper"] = {}
    spec["metrics"][0]["description"] = "reworded"
    assert hashes(spec=spec) == base
    assert all(v != base[k] for k, v in hashes(prof=profile(batch_sequences=2, steps=31)).items())
    assert all(v != base[k] for k, v in hashes(seed=1).items())
    new_weights = hashes(prior_info={"vposer-slerp": {}, "hmvae": {"weights_sha256": "ab12"}, "sequential-primitives": {}})
    assert {k for k in base if new_weights[k] != base[k]} == {k for k in base if "__hmvae__" in k}


def test_spec_hash_follows_the_protocol_version():
    """``protocol_version`` is kept out of the rules (a presentation key there) but enters every
    unit's spec itself: a version bump (a protocol change in code, e.g. how frames are scored, with
    no rule field changed) must never reuse a unit computed under the old version."""
    base = {u.unit_id: u.spec_hash for u in plan()}
    spec = table_spec()
    spec["protocol_version"] = int(spec["protocol_version"]) + 1
    bumped = {u.unit_id: u.spec_hash for u in plan(spec=spec)}
    assert bumped.keys() == base.keys() and all(bumped[k] != base[k] for k in base)


def test_unit_ids_are_filesystem_safe_and_collisions_are_errors():
    units = plan(priors=["my prior/v2"])
    assert units[0].unit_id == "table1__my-prior-v2__points=100_fps=5__b000"
    with pytest.raises(ValueError, match="share the id"):
        plan(priors=["a/b", "a b"])


@pytest.mark.parametrize("kwargs, match", [
    ({"prof": {**profile(), "batch_sequences": 0}}, "batch_sequences"),
    ({"seqs": ["s0", "s0"]}, "repeat"),
    ({"seqs": []}, "no sequences"),
    ({"prior_info": {"vposer-slerp": {}}}, "prior_info has no entry"),
    ({"priors": ["hmvae", "hmvae"]}, "twice"),
])
def test_plan_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        plan(**kwargs)


def test_spec_without_grid_names_the_file_and_field():
    spec = table_spec()
    del spec["grid"]
    with pytest.raises(ValueError, match=r"benchmark/tables/table1.yaml: field 'grid'"):
        plan(spec=spec)


# ---------------------------------------------------------------- atomic files

def test_atomic_write_replaces_and_leaves_no_temp(tmp_path):
    path = tmp_path / "sub" / "x.json"
    atomic_write_json(path, {"a": 1})
    atomic_write_json(path, {"a": 2})
    assert json.loads(path.read_text()) == {"a": 2}
    assert sorted(os.listdir(path.parent)) == ["x.json"]
    with pytest.raises(ValueError):  # NaN is never written
        atomic_write_json(path, {"a": float("nan")})
    assert json.loads(path.read_text()) == {"a": 2}


def test_atomic_write_failure_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "x.txt"
    atomic_write_text(path, "old")

    def broken_fsync(fd):
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", broken_fsync)
    with pytest.raises(OSError, match="disk full"):
        atomic_write_text(path, "new")
    assert path.read_text() == "old"
    assert os.listdir(tmp_path) == ["x.txt"]  # the temp file was removed


# ---------------------------------------------------------------- unit-result validation

def test_validate_unit_result_rejects_bad_numbers_and_ids():
    unit = plan()[0]
    good = FakeExecutor()(unit)
    assert validate_unit_result(good, unit) is good
    bad = json.loads(json.dumps(good))
    bad["per_sequence"][0]["sums"]["chamfer_m"] = float("nan")
    with pytest.raises(ValueError, match="not a finite number"):
        validate_unit_result(bad, unit)
    bad = json.loads(json.dumps(good))
    bad["per_sequence"][0]["id"] = "other"
    with pytest.raises(ValueError, match="differ from the unit's sequences"):
        validate_unit_result(bad, unit)
    bad = dict(good, spec_hash="0" * 64)
    with pytest.raises(ValueError, match="spec_hash"):
        validate_unit_result(bad, unit)
    bad = dict(good, na_reason="cannot")
    with pytest.raises(ValueError, match="no per_sequence rows"):
        validate_unit_result(bad, unit)
    bad = {k: v for k, v in good.items() if k != "fingerprint"}
    with pytest.raises(ValueError, match="fingerprint"):
        validate_unit_result(bad, unit)


# ---------------------------------------------------------------- derivation

def _cell(table, prior, points, fps):
    row = next(r for r in table["rows"] if r["prior"] == prior)
    return next(c for c in row["cells"] if c["points"] == points and c["fps"] == fps)


def test_mean_over_all_frames_differs_from_mean_of_sequence_means():
    """Hand-computed: 10 frames at 1 mm and 30 frames at 3 mm -> 2.5 mm (not 2.0), std 1.0 mm."""
    units = plan(priors=["p"], seqs=["short", "long"], prof=profile(batch_sequences=1))
    lengths = {"short": (10, 0.001), "long": (30, 0.003)}
    results = []
    for u in units:
        r = FakeExecutor(metrics=("chamfer_m",))(u)
        (sid,) = u.sequence_ids
        frames, per_frame = lengths[sid]
        r["per_sequence"] = [{"id": sid, "frames": frames, "sums": {"chamfer_m": frames * per_frame,
                                                                     "chamfer_surface_m": 0.0, "mpjpe_m": 0.0}}]
        results.append(r)
    table = derive_table(table_spec(), results, meta(units, prof=profile(batch_sequences=1)))
    cell = _cell(table, "p", 100, 5)
    assert cell["chamfer_mm"] == pytest.approx(2.5, abs=1e-12)
    assert cell["chamfer_mm_std"] == pytest.approx(1.0, abs=1e-12)
    assert (cell["sequences"], cell["frames"], cell["units"]) == (2, 40, 2)


def test_derived_cells_match_a_naive_per_frame_reference():
    units = plan(seqs=["a", "b", "c", "d", "e"])
    results = [FakeExecutor()(u) for u in units]
    table = derive_table(table_spec(), results, meta(units))
    assert [r["prior"] for r in table["rows"]] == PRIORS
    cell = _cell(table, "hmvae", 1000, 10)
    group = [u for u in units if u.prior == "hmvae" and u.cell == {"points": 1000, "fps": 10}]
    assert len(group) == 3
    for metric in ("chamfer", "chamfer_surface", "mpjpe"):
        per_seq = [frame_errors(u.seed, s, f"{metric}_m") for u in group for s in u.sequence_ids]
        all_frames = np.concatenate(per_seq)
        assert cell[f"{metric}_mm"] == pytest.approx(1000 * all_frames.mean(), rel=1e-12)
        assert cell[f"{metric}_mm_std"] == pytest.approx(1000 * np.std([e.mean() for e in per_seq]), rel=1e-9)
        assert cell[f"{metric}_mm"] != pytest.approx(1000 * np.mean([e.mean() for e in per_seq]), rel=1e-6)
    assert cell["frames"] == sum(len(frame_errors(u.seed, s, "chamfer_m")) for u in group for s in u.sequence_ids)
    assert cell["fingerprint"] == hashlib.sha256(
        canonical_json(sorted(r["fingerprint"] for r in results if r["unit_id"] in {u.unit_id for u in group})).encode()
    ).hexdigest()
    assert table["counts"] == {"units_planned": 54, "units_done": 54, "cells": 18, "cells_na": 0}
    assert table["provenance"]["timings"]["fit_s"] == pytest.approx(54 * 1.5)
    assert table["protocol_version"] == load_table_spec("table1")["protocol_version"] and table["profile"] == "smoke"
    assert table["seed"] == 0
    assert table["spec"]["objective"]["lambda_prior"] == 0.01
    assert table["prior_info"] == {p: {"name": p} for p in PRIORS}
    json.dumps(table, allow_nan=False)  # plain JSON
    table["spec"]["objective"]["lambda_prior"] = 99  # the table holds copies, never the catalog's cached spec
    units[0].spec["rules"]["objective"]["lr"] = 99
    assert table_spec()["objective"]["lambda_prior"] == 0.01 and table_spec()["objective"]["lr"] == 0.03


def test_na_and_incomplete_cells():
    units = plan()
    ex = FakeExecutor(na=lambda u: "2 s windows cannot hold 100 points" if u.prior == "hmvae" and u.cell["points"] == 100 else None)
    results = [ex(u) for u in units]
    dropped = next(u for u in units if u.prior == "vposer-slerp" and u.cell == {"points": 1000, "fps": 5})
    results = [r for r in results if r["unit_id"] != dropped.unit_id]
    order = {"hmvae": {}, "vposer-slerp": {}, "sequential-primitives": {}}  # priors may be a dict: its keys give the row order
    table = derive_table(table_spec(), results, meta(units, priors=order))
    assert [r["prior"] for r in table["rows"]] == list(order)
    na = _cell(table, "hmvae", 100, 10)
    assert na["na_reason"] == "2 s windows cannot hold 100 points" and "chamfer_mm" not in na
    inc = _cell(table, "vposer-slerp", 1000, 5)
    assert inc["na_reason"] == "incomplete: 1 of 2 units"
    assert not any(k.startswith(("chamfer", "mpjpe")) for k in inc)
    assert "chamfer_mm" in _cell(table, "vposer-slerp", 1000, 10)
    assert table["counts"]["cells_na"] == 3


def test_metric_missing_from_some_sequences_is_na_not_averaged():
    units = plan(priors=["p"])
    results = [FakeExecutor()(u) for u in units]
    for r in results:
        del r["per_sequence"][0]["sums"]["mpjpe_m"]  # first sequence of each batch has no joints
    cell = _cell(derive_table(table_spec(), results, meta(units)), "p", 100, 5)
    assert cell["mpjpe_mm"] is None and cell["metric_na"]["mpjpe_mm"] == "incomplete: reported for 1 of 3 sequences"
    assert cell["chamfer_mm"] is not None


def test_derive_rejects_results_from_other_rules():
    units = plan()
    old = [FakeExecutor()(u) for u in units]
    new_units = plan(spec=table_spec(lr=0.01))
    with pytest.raises(ValueError, match="computed under other rules"):
        derive_table(table_spec(lr=0.01), old, meta(new_units))
    with pytest.raises(ValueError, match="unknown meta key"):
        derive_table(table_spec(), old, {**meta(units), "sed": 1})


def test_provenance_has_versions_git_and_time():
    prov = collect_provenance(device="cpu", argv=["python", "-m", "benchmark", "run", "table 1"])
    assert set(prov) >= {"git", "versions", "platform", "cpu", "gpu", "timestamp", "command"}
    assert prov["command"] == "python -m benchmark run 'table 1'"
    assert prov["gpu"] is None
    for lib in ("torch", "numpy", "scipy", "roma", "anny", "trimesh", "python"):
        assert prov["versions"][lib], lib
    assert set(prov["git"]) == {"revision", "dirty", "note"}
    assert prov["git"]["revision"] is None or len(prov["git"]["revision"]) == 40


def test_a_revised_adapter_gets_new_unit_identities_and_revision_1_keeps_the_old():
    """``adapter_revision`` (priors.base) enters a prior's identity from 2 on: units stored under the
    older code are planned under another spec hash, so they are recomputed, not reused; revision 1
    leaves the identity (and every unit stored before revisions existed) unchanged."""
    from benchmark.run.table_run import prior_identity
    from priors.no_prior import NoPrior

    class Revised(NoPrior):
        adapter_revision = 2

    plain, revised = prior_identity(NoPrior(), "embedded", None), prior_identity(Revised(), "embedded", None)
    assert "adapter_revision" not in plain and revised == {**plain, "adapter_revision": 2}
    hashes = lambda info: {u.unit_id: u.spec_hash for u in plan(priors=["p"], prior_info={"p": info})}  # noqa: E731
    assert hashes(plain).keys() == hashes(revised).keys()
    assert all(hashes(plain)[k] != hashes(revised)[k] for k in hashes(plain))
