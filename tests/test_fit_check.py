"""``python -m benchmark fit-check``: the completion fit of no-prior against its targets (issue 11).

The run itself is slow (4 quick sequences at 10,000 points / 10 fps, the table1 v2 schedule), so it
is behind the ``slow`` marker; the default suite checks the command's argument errors."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

from benchmark.tools.fit_check import TARGETS


def _cli(*args, timeout=3000):
    return subprocess.run([sys.executable, "-m", "benchmark", *args], capture_output=True, text=True, timeout=timeout)


def test_fit_check_refuses_a_cell_outside_the_grid(tmp_path):
    r = _cli("fit-check", "--points", "500", "--out", str(tmp_path / "fc"), timeout=300)
    assert r.returncode == 2
    assert "--points 500 / --fps 10 is not a table1 cell" in r.stderr


def test_fit_check_refuses_an_unknown_prior(tmp_path):
    r = _cli("fit-check", "--prior", "no-such-prior", "--out", str(tmp_path / "fc"), timeout=300)
    assert r.returncode == 2 and "no-such-prior" in r.stderr


@pytest.fixture(scope="module")
def fit_check_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("fit_check")
    r = _cli("fit-check", "--out", str(out))
    rows = dict(re.findall(r"^(\w+)\s+\S+\s+<= \S+\s+(ok|FAIL)$", r.stdout, flags=re.M))
    return r, rows


@pytest.mark.slow
def test_fit_check_faces_every_sequence_the_right_way_and_converges(fit_check_run):
    r, rows = fit_check_run
    assert r.returncode in (0, 1), r.stderr[-2000:]
    assert set(rows) == set(TARGETS), r.stdout[-3000:]
    for name in ("root_err_deg_max", "backwards", "not_converged"):
        assert rows[name] == "ok", r.stdout[-3000:]


@pytest.mark.slow
@pytest.mark.xfail(strict=False, reason="issue 11: no-prior at 10,000 pts / 10 fps reaches MPJPE ~45 mm and vertex "
                                        "Chamfer ~17.5 mm (targets 40 and 12): limb local minima of the per-frame fit")
def test_fit_check_meets_every_target(fit_check_run):
    r, rows = fit_check_run
    assert r.returncode == 0, r.stdout[-3000:]


# -- fit-check --robustness --

def test_robustness_probes_move_the_observation_and_triple_the_steps():
    from benchmark.run.catalog import get_profile, load_table_spec
    from benchmark.tools.fit_check import LONGER, PERTURBATION_M, robustness_specs

    spec = load_table_spec("table1")
    profile = get_profile("quick", table="table1")
    probes = robustness_specs(spec, profile, base_steps=240)
    perturbed, p_profile = probes["perturbed"]
    assert perturbed["data"]["observation_offset_m"] == PERTURBATION_M and p_profile == profile
    assert "observation_offset_m" not in spec["data"]  # the table's own spec untouched

    # a rule with reductions (table1 since version 7) keeps its tolerance (each reduction needs its
    # plateau) and descends longer instead
    assert int(spec["objective"]["plateau"]["reductions"]) == 2
    longer, l_profile = probes["longer"]
    plateau = longer["objective"]["plateau"]
    assert plateau["tolerance"] == spec["objective"]["plateau"]["tolerance"] > 0 and plateau["reductions"] == 2
    assert plateau["min_steps"] == LONGER * 240 - plateau["anneal_steps"] and l_profile["steps"] == LONGER * 240
    assert "min_steps" not in spec["objective"]["plateau"]

    # a rule without reductions (table1 version 6): tolerance 0, so the fit descends at its constant rate to the cap
    constant = {**spec, "objective": {**spec["objective"], "plateau": {**spec["objective"]["plateau"], "reductions": 0}}}
    longer, l_profile = robustness_specs(constant, profile, base_steps=240)["longer"]
    assert longer["objective"]["plateau"]["tolerance"] == 0.0 and l_profile["steps"] == LONGER * 240
    assert constant["objective"]["plateau"]["tolerance"] > 0  # untouched


def test_robustness_moves_are_read_per_cell_and_per_sequence():
    from benchmark.tools.fit_check import mpjpe_moves

    base = {"mpjpe_mm": 40.0, "per_sequence": {"id": ["a", "b"], "mpjpe_mm": [30.0, 50.0]}}
    probe = {"mpjpe_mm": 40.5, "per_sequence": {"id": ["b", "a"], "mpjpe_mm": [48.0, 33.0]}}
    assert mpjpe_moves(base, probe) == pytest.approx((0.5, 3.0))


def test_a_probe_offset_moves_every_observed_point(tmp_path):
    """data.observation_offset_m reaches the fit's observation: the unit's fingerprint changes."""
    import copy

    from benchmark.body import get_body
    from benchmark.run.catalog import get_profile, load_table_spec
    from benchmark.run.table_run import run_table

    spec = load_table_spec("table1")
    spec = {**spec, "grid": {"points": [100], "fps": [5]},  # the version 1 start: this tests the data path, not the fit
            "objective": {**spec["objective"], "facing": "heading8", "start_search": "none"}}
    spec.pop("paper", None)
    profile = dict(get_profile("smoke", table="table1"), steps=2)
    body = get_body("anny", device="cpu")
    prints = []
    for offset in (0.0, 1e-6):
        s = copy.deepcopy(spec)
        if offset:
            s["data"]["observation_offset_m"] = offset
        result = run_table(s, profile, ["no-prior"], body, "cpu", 0, tmp_path / str(offset))
        prints.append(result["table"]["rows"][0]["cells"][0]["fingerprint"])
    assert prints[0] != prints[1]


def test_robustness_refuses_a_start_search_override(tmp_path):
    r = _cli("fit-check", "--robustness", "--start-search", "limbs", "--out", str(tmp_path / "fc"), timeout=300)
    assert r.returncode == 2 and "--robustness" in r.stderr


def _default_priors():
    from benchmark.run.catalog import default_priors
    from benchmark.run.catalog import load_table_spec

    return default_priors(load_table_spec("table1"))


@pytest.mark.slow
@pytest.mark.parametrize("prior", _default_priors())
def test_every_default_prior_is_robust(prior):
    """Each default prior's quick fits at the sparsest and densest cell move by at most 1 mm under a
    1e-6 m perturbation of the observation and under 3 x the steps (no-prior: about 25 min on 2
    cores; the window priors take longer)."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        r = _cli("fit-check", "--robustness", "--prior", prior, "--out", f"{tmp}/fc", timeout=6 * 3600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert "every cell robust" in r.stdout


def test_base_run_units_are_copied_not_moved_and_never_overwrite(tmp_path):
    from benchmark.tools.fit_check import seed_base_units

    run = tmp_path / "run" / "units"
    run.mkdir(parents=True)
    names = ["table1__hmvae__points=100_fps=5__b000.json", "table1__hmvae__points=100_fps=5__b000.npz",
             "table1__hmvae__points=10000_fps=10__b000.json", "table1__hmvae__points=10000_fps=10__b001.json",
             "table1__hmvae__points=1000_fps=5__b000.json",       # not a robustness cell
             "table1__no-prior__points=100_fps=5__b000.json",     # another prior
             "table1__hmvae__points=100_fps=5__b000.json.tmp"]    # not a unit file
    for n in names:
        (run / n).write_text(n)
    out = tmp_path / "out"
    kept = out / "base-10000x10" / "units" / "table1__hmvae__points=10000_fps=10__b000.json"
    kept.parent.mkdir(parents=True)
    kept.write_text("already here")
    copied = seed_base_units(tmp_path / "run", out, "hmvae")
    assert sorted(p.name for p in copied) == ["table1__hmvae__points=10000_fps=10__b001.json",
                                              "table1__hmvae__points=100_fps=5__b000.json",
                                              "table1__hmvae__points=100_fps=5__b000.npz"]
    assert all(p.read_text() == p.name for p in copied) and kept.read_text() == "already here"
    assert sorted(p.name for p in run.iterdir()) == sorted(names)  # the run folder only read
    assert seed_base_units(tmp_path / "run", out, "hmvae") == []  # a rerun copies nothing
    with pytest.raises(FileNotFoundError, match="no units/ folder"):
        seed_base_units(tmp_path / "nowhere", out, "hmvae")


def test_cli_base_run_needs_robustness_and_an_existing_run(tmp_path, capsys):
    from benchmark.cli import main

    assert main(["fit-check", "--base-run", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "--base-run gives the base fits of --robustness" in capsys.readouterr().err
    assert main(["fit-check", "--robustness", "--prior", "hmvae", "--base-run", str(tmp_path / "none"),
                 "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err
    assert "no units/ folder" in err and "MPJPE" not in err


def test_the_start_probe_reports_every_stage_and_a_deterministic_start(monkeypatch, brief_searches):
    """``fit-check --start-probe``: the facing and each limb stage, with the joints' move per
    sequence and the per-frame choices on both observations; with no move the start is the same
    computation (every move 0, the same choices); a cell outside the grid is refused. (The search's
    sizes cut for speed: one limb stage of the legs, a few steps.)"""
    from benchmark.protocols import start_search
    from benchmark.tools.start_probe import format_probe, start_probe

    monkeypatch.setattr(start_search, "LIMB_START_STAGES", start_search.LIMB_START_STAGES[1:])
    same = start_probe(100, 5, sequences=1, profile_name="smoke", offset_m=0.0)
    assert [r["stage"] for r in same["stages"]] == ["facing", "limb stage 1", "limb stage 2"]
    assert all(r["move_mm"] == [0.0] for r in same["stages"])
    frames = sum(same["stages"][1]["choices"][0])
    assert frames == 20 and all(r["choices"][0] == r["choices"][1] for r in same["stages"][1:])
    lines = format_probe(same)
    assert len(lines) == 5 and "limb stage 2" in lines[-1] and "moved by 0 m" in lines[0]
    with pytest.raises(ValueError, match="not a table1 cell"):
        start_probe(50, 5)


def test_the_longer_probe_reads_the_base_runs_stored_starts(tmp_path, monkeypatch):
    """fit-check --robustness hands each cell's longer probe the starts its base run stored (the same
    observation and search); the perturbed probe, another observation, searches its own."""
    import benchmark.body
    import benchmark.run.table_run
    from benchmark.tools import fit_check

    seen = {}

    def fake_run_table(spec, profile, priors, body, device, seed, out, backend_options=None):
        starts = Path(out) / "cache" / "starts"
        seen[Path(out).name] = sorted(p.name for p in starts.glob("*.pt")) if starts.is_dir() else []
        if Path(out).name.startswith("base-"):
            starts.mkdir(parents=True, exist_ok=True)
            (starts / (Path(out).name[-1] * 64 + ".pt")).write_bytes(b"start")
        cell = {"mpjpe_mm": 40.0, "sequences": 1, "per_sequence": {"id": ["s0"], "mpjpe_mm": [40.0]},
                "diagnostics": {"steps_max": 300, "sequences": 1, "not_converged": 0}}
        return {"failures": [], "table": {"rows": [{"cells": [cell]}]}}

    monkeypatch.setattr(benchmark.run.table_run, "run_table", fake_run_table)
    monkeypatch.setattr(benchmark.body, "get_body", lambda *a, **k: object())
    assert fit_check.run_robustness("no-prior", out=str(tmp_path / "fc")) == 0
    assert seen["longer-100x5"] == ["5" * 64 + ".pt"] and seen["longer-10000x10"] == ["0" * 64 + ".pt"]
    assert seen["perturbed-100x5"] == [] and seen["base-100x5"] == []
