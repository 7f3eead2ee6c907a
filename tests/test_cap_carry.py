"""Units carried over when a profile's step cap rises (benchmark.run.cap_carry): a fit whose every
sequence converged under the plateau rule is the same computation under any larger cap, so its
stored unit stands for the larger cap; a fit at the cap, other rules or a smaller cap are rerun."""

import copy
import json

import numpy as np
import pytest
import torch

from benchmark.core.work_units import checksum_problem, unit_path
from benchmark.data.unit_arrays import arrays_path, read_arrays
from benchmark.protocols.registry import make_protocol
from benchmark.protocols.step_rules import PlateauRule, optimise_to_plateau
from benchmark.run.runner import run_units
from benchmark.run.table_derive import derive_table
from benchmark.run.table_merge import replace_rows
from benchmark.run.writers import format_markdown
from fake_units import FakeExecutor, meta, plan, profile, table_spec
from test_plateau_rule import _problem

def single_start(**objective_changes) -> dict:
    """table1's spec with one start per sequence (version 8 races two copies of the encoded rows,
    whose choice depends on every copy's end: a unit under it is never carried)."""
    spec = table_spec(**objective_changes)
    spec["objective"].pop("multi_start", None)
    return spec


V7 = PlateauRule(window=20, tolerance=0.005, smoothing=5, check_every=5, anneal_steps=10, reductions=2, factor=0.3)


def _fit(cap, scales=(1.0, 1.0), targets=(0.5, 3.0)):
    x, trace, step_loss = _problem(list(scales), list(targets))
    history, log = optimise_to_plateau("toy", [x], cap, 0.05, 0.1, step_loss, trace, V7)
    return x.detach(), torch.stack(trace), history, log


def test_a_converged_fit_is_the_same_computation_under_any_larger_cap():
    x, trace, history, log = _fit(2000)
    assert log["converged"] == [True, True] and log["steps"] < 2000
    for cap in (log["steps"] + 1, 5000):
        x2, trace2, history2, log2 = _fit(cap)
        assert torch.equal(x2, x) and torch.equal(trace2, trace)  # bit for bit
        assert history2 == history and log2 == log


def test_a_fit_at_the_cap_goes_on_under_a_larger_one():
    _, _, _, short = _fit(150)
    x, _, _, long = _fit(2000)
    assert short["stopped"] == "cap" and not all(short["converged"])
    assert long["converged"] == [True, True] and long["steps"] > 150


class _Converging(FakeExecutor):
    """FakeExecutor whose sequences carry a convergence verdict (``open``: unit ids with one
    unconverged fit) and whose units keep arrays (the fitted motion's ``.npz``)."""

    def __init__(self, open_units=()):
        super().__init__()
        self.open = set(open_units)

    def __call__(self, unit):
        out = super().__call__(unit)
        for i, row in enumerate(out["per_sequence"]):
            row["diagnostics"] = {"converged": not (unit.unit_id in self.open and i == 0), "final_data_mm": 10.0,
                                  "steps": 300, "plateau_decrease": 0.001}
        out["arrays"] = {"spec_hash": np.array(unit.spec_hash), "x": np.arange(3.0)}
        return out


def _carry(spec):
    protocol = make_protocol(spec["protocol"])
    return lambda unit: protocol.carry_problem(spec)


def test_converged_units_are_carried_to_a_raised_cap_and_the_others_rerun(tmp_path):
    spec = single_start()
    old = plan(spec, profile(batch_sequences=2, steps=400))
    open_id = old[0].unit_id
    run_units(old, _Converging(open_units={open_id}), tmp_path, announce=False)
    before = {u.unit_id: json.loads(unit_path(tmp_path, u.unit_id).read_text()) for u in old}

    new = plan(spec, profile(batch_sequences=2, steps=800))
    execute = _Converging()
    report = run_units(new, execute, tmp_path, announce=False, carry=_carry(spec))
    assert execute.calls == [open_id]  # the unit with a fit at its cap is computed again
    assert sorted(report.carried) == sorted(u.unit_id for u in new if u.unit_id != open_id)
    assert report.resume_counts()["carried"] == len(new) - 1
    for unit in new:
        stored = json.loads(unit_path(tmp_path, unit.unit_id).read_text())
        assert stored["spec_hash"] == unit.spec_hash and checksum_problem(stored) is None
        assert read_arrays(arrays_path(tmp_path, unit.unit_id))["spec_hash"] == unit.spec_hash
        if unit.unit_id == open_id:
            assert "carried" not in stored
            continue
        assert stored["carried"]["from_steps"] == 400 and stored["carried"]["to_steps"] == 800
        assert stored["per_sequence"] == before[unit.unit_id]["per_sequence"]
        stale = tmp_path / "units" / "stale" / stored["carried"]["stale_file"]
        assert json.loads(stale.read_text()) == before[unit.unit_id]  # the original, untouched
        assert read_arrays(stale.with_suffix(".npz"))["spec_hash"] == before[unit.unit_id]["spec_hash"]
    again = run_units(new, _Converging(), tmp_path, announce=False, carry=_carry(spec))
    assert len(again.reused) == len(new) and not again.carried and not again.ran


def test_a_carry_that_fails_midway_reruns_the_unit_and_keeps_the_original(tmp_path, monkeypatch):
    import benchmark.run.runner as runner

    spec = single_start()
    old = plan(spec, profile(batch_sequences=2, steps=400))[:1]
    run_units(old, _Converging(), tmp_path, announce=False)
    before = json.loads(unit_path(tmp_path, old[0].unit_id).read_text())

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(runner, "carry_unit", broken)
    new = plan(spec, profile(batch_sequences=2, steps=800))[:1]
    execute = _Converging()
    report = run_units(new, execute, tmp_path, announce=False, carry=_carry(spec))
    assert execute.calls == [new[0].unit_id] and not report.carried and report.ok
    assert "carrying it to the new cap failed (disk full)" in report.moved_why[new[0].unit_id]
    (stale,) = (tmp_path / "units" / "stale").glob("*.json")
    assert json.loads(stale.read_text()) == before
    assert read_arrays(stale.with_suffix(".npz"))["spec_hash"] == before["spec_hash"]  # its fitted motions too


@pytest.mark.parametrize("case", ["cap fell", "no carry", "several starts", "other sizes"])
def test_units_are_rerun_where_the_cap_did_not_rise_or_the_rules_forbid_it(tmp_path, case):
    spec = single_start()
    run_units(plan(spec, profile(batch_sequences=2, steps=400)), _Converging(), tmp_path, announce=False)
    new_spec = table_spec(multi_start={"starts": 2}) if case == "several starts" else spec
    sizes = {"cap fell": {"steps": 200}, "other sizes": {"steps": 800, "loss_vertices": 100}}.get(case, {"steps": 800})
    new = plan(new_spec, profile(batch_sequences=2, **sizes))
    execute = _Converging()
    report = run_units(new, execute, tmp_path, announce=False, carry=None if case == "no carry" else _carry(new_spec))
    assert not report.carried and len(execute.calls) == len(new)
    for target in report.moved:  # each stored result moved aside with its fitted motions, not overwritten
        stale = json.loads(target.read_text())
        assert read_arrays(target.with_suffix(".npz"))["spec_hash"] == stale["spec_hash"]
    if case == "several starts":
        assert all("several starts" in why for why in report.moved_why.values())


def test_the_protocols_declare_which_rules_are_cap_independent():
    completion = make_protocol("completion")
    assert "several starts" in completion.carry_problem(table_spec())  # table1 version 8: two copies raced
    assert completion.carry_problem(single_start()) is None
    assert make_protocol("sls").carry_problem(copy.deepcopy(single_start())) is None
    assert "cosine" in completion.carry_problem(single_start(step_rule="cosine"))
    assert "optimiser" in completion.carry_problem(single_start(optimiser="lbfgs"))
    assert "minimum" in completion.carry_problem(single_start(plateau={"min_steps": 100}))
    assert "does not declare" in make_protocol("denoise").carry_problem({})


def _table(units, results, steps, priors):
    return derive_table(single_start(), results, meta(units, prof=profile(batch_sequences=2, steps=steps), priors=priors))


def test_a_table_takes_a_row_run_under_a_raised_cap_when_its_kept_rows_converged():
    priors = ["no-prior", "hmvae"]
    old = plan(priors=priors, prof=profile(batch_sequences=2, steps=400))
    new = plan(priors=["hmvae"], prof=profile(batch_sequences=2, steps=800))
    hm_open = [u.unit_id for u in old if u.prior == "hmvae"]
    base = _table(old, [_Converging(open_units=hm_open)(u) for u in old], 400, priors)
    row = _table(new, [_Converging()(u) for u in new], 800, ["hmvae"])
    merged = replace_rows(base, row)
    assert merged["profile_sizes"]["steps"] == 800
    assert merged["provenance"]["rows_replaced"][-1]["step_cap_raised"] == {"from": 400, "to": 800,
                                                                             "rows_kept": ["no-prior"]}
    assert all(c["diagnostics"]["not_converged"] == 0 for r in merged["rows"] for c in r["cells"])
    assert "the step cap raised from 400 to 800" in format_markdown(merged)

    np_open = [u.unit_id for u in old if u.prior == "no-prior"][:1]
    stuck = _table(old, [_Converging(open_units=np_open)(u) for u in old], 400, priors)
    with pytest.raises(ValueError, match="no-prior points=100, fps=5 \\(1 of 3\\).*rerun those priors"):
        replace_rows(stuck, row, base_source="BASE.json")
    fell = _table(new, [_Converging()(u) for u in new], 200, ["hmvae"])
    with pytest.raises(ValueError, match="profile_sizes"):
        replace_rows(base, fell)


@pytest.mark.slow  # two real fits, about 30 s
def test_a_real_unit_carried_to_a_raised_cap_equals_the_unit_computed_under_it(tmp_path, monkeypatch, anny_body):
    """table1's fit (a shrunk run: 100 points, 200 loss vertices, one sequence) converged under a cap of
    1,000 steps: carried to 1,500, its stored result is the one a run under 1,500 computes, value for value."""
    import shutil

    import benchmark.run.catalog as catalog
    from benchmark.run.table_run import run_table
    from tiny_run import tiny_table1

    tiny_table1(monkeypatch)
    spec = copy.deepcopy(catalog.load_table_spec("table1"))
    spec["objective"].pop("multi_start", None)  # one start per sequence: a unit that can be carried
    run = lambda steps, out: run_table(spec, {**catalog.get_profile("smoke", "table1"), "steps": steps},  # noqa: E731
                                       ["no-prior"], anny_body, "cpu", 0, tmp_path / out, backend_options={"jobs": 1})
    first = run(1000, "a")
    diag = first["table"]["rows"][0]["cells"][0]["diagnostics"]
    assert diag["not_converged"] == 0 and diag["steps_max"] < 1000
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    carried, fresh = run(1500, "b"), run(1500, "c")
    assert carried["table"]["provenance"]["resume"]["carried"] == 1
    assert fresh["table"]["provenance"]["resume"]["ran"] == 1
    (uid,) = [p.stem for p in (tmp_path / "c" / "units").glob("*.json")]
    b, c = (json.loads((tmp_path / d / "units" / f"{uid}.json").read_text()) for d in "bc")
    assert b["spec_hash"] == c["spec_hash"]
    for key in ("per_sequence", "fingerprint", "fit_log"):
        assert b[key] == c[key], key
    untimed = lambda t: [[{k: v for k, v in c.items() if k not in ("fit_s", "eval_s")} for c in r["cells"]]  # noqa: E731
                         for r in t["table"]["rows"]]
    assert untimed(carried) == untimed(fresh)
