"""The runner: results store, resume policies, stale files, failures, backends."""

import io
import json
import logging

import pytest

from benchmark.run import runner
from benchmark.run.backends import BACKENDS
from benchmark.run.table_derive import derive_table
from benchmark.core.work_units import load_unit_results, unit_path
from fake_units import FakeExecutor, meta, plan, table_spec


def _files(folder):
    return sorted(p.name for p in folder.iterdir() if p.is_file())


def test_run_writes_one_file_per_unit_and_resume_reuses(tmp_path):
    units = plan()
    ex = FakeExecutor()
    report = runner.run_units(units, ex, tmp_path, progress=False)
    assert report.ok and len(ex.calls) == len(units) == len(report.ran) == 36
    assert list(report.results) == [u.unit_id for u in units]  # plan order
    assert _files(tmp_path / "units") == sorted(f"{u.unit_id}.json" for u in units)  # no temp files left
    stored = json.loads(unit_path(tmp_path, units[0].unit_id).read_text())
    assert stored["spec_hash"] == units[0].spec_hash and stored["spec"] == units[0].spec
    assert stored["per_sequence"] == ex(units[0])["per_sequence"]

    ex2 = FakeExecutor()
    again = runner.run_units(plan(), ex2, tmp_path, progress=False)
    assert ex2.calls == [] and len(again.reused) == 36 and again.results == report.results
    assert load_unit_results(tmp_path, units) == list(report.results.values())


def test_changed_rules_move_old_results_aside_and_rerun(tmp_path):
    units = plan()
    runner.run_units(units, FakeExecutor(), tmp_path, progress=False)
    old_text = {u.unit_id: unit_path(tmp_path, u.unit_id).read_text() for u in units}

    new_units = plan(spec=table_spec(lambda_prior=0.1))
    ex = FakeExecutor()
    report = runner.run_units(new_units, ex, tmp_path, progress=False)
    assert len(ex.calls) == 36 and len(report.moved) == 36
    stale = tmp_path / "units" / "stale"
    for u in units:  # nothing lost: every old file is under stale/ with its old hash, byte for byte
        moved = stale / f"{u.unit_id}.{u.spec_hash[:8]}.json"
        assert moved.read_text() == old_text[u.unit_id]
    for u in new_units:
        assert json.loads(unit_path(tmp_path, u.unit_id).read_text())["spec_hash"] == u.spec_hash


def test_policy_never_reruns_everything_and_never_overwrites_stale_files(tmp_path):
    units = plan(priors=["p"])
    runner.run_units(units, FakeExecutor(), tmp_path, progress=False)
    for round_ in (1, 2):
        ex = FakeExecutor()
        report = runner.run_units(units, ex, tmp_path, resume="never", progress=False)
        assert len(ex.calls) == len(units) == len(report.ran) and report.reused == []
    stale = _files(tmp_path / "units" / "stale")
    u = units[0]
    assert f"{u.unit_id}.{u.spec_hash[:8]}.json" in stale and f"{u.unit_id}.{u.spec_hash[:8]}.1.json" in stale
    assert len(stale) == 2 * len(units)


def test_a_failing_unit_is_logged_skipped_and_rerun_later(tmp_path, caplog):
    units = plan()
    bad = units[5].unit_id
    ex = FakeExecutor(fail={bad})
    with caplog.at_level(logging.ERROR, logger="benchmark.run.runner"):
        report = runner.run_units(units, ex, tmp_path, progress=False)
    assert not report.ok and list(report.failed) == [bad]
    assert "simulated failure" in report.failed[bad] and bad in report.summary()
    (rec,) = [r for r in caplog.records if r.getMessage().startswith(f"unit {bad} failed")]
    assert rec.exc_info is None and rec.getMessage().endswith("(--debug shows its traceback)")  # one line
    assert len(ex.calls) == 36 and len(report.ran) == 35
    assert not unit_path(tmp_path, bad).exists()
    table = derive_table(table_spec(), report.results.values(), meta(units))
    failed_unit = units[5]
    cell = next(c for r in table["rows"] if r["prior"] == failed_unit.prior for c in r["cells"]
                if all(c[k] == v for k, v in failed_unit.cell.items()))
    assert cell["na_reason"] == "incomplete: 1 of 2 units"

    ex2 = FakeExecutor()
    report2 = runner.run_units(units, ex2, tmp_path, progress=False)
    assert ex2.calls == [bad] and report2.ok and len(report2.results) == 36
    results, failures = report  # the report also unpacks as (results in plan order, failures)
    assert results == list(report.results.values()) and failures == report.failed


def test_without_a_bar_each_finished_unit_prints_one_line(tmp_path, capsys):
    """A run whose output is not a terminal (a log file, a batch job) shows no bar: it says as each
    unit is stored instead, so a run of hours shows it is moving; a failed unit has its error line."""
    units = plan()[:3]
    runner.run_units(units, FakeExecutor(fail={units[1].unit_id}), tmp_path, progress=False)
    done = [line for line in capsys.readouterr().out.splitlines() if line.startswith("unit ")]
    assert [line.split(" stored (")[0] for line in done] == [f"unit 1 of 3 done: {units[0].unit_id}",
                                                             f"unit 3 of 3 done: {units[2].unit_id}"]
    assert all(line.endswith(" into the run)") for line in done)
    runner.run_units(units, FakeExecutor(), tmp_path / "quiet", progress=False, announce=False)
    assert "done:" not in capsys.readouterr().out
    assert (runner.clock(42.4), runner.clock(185), runner.clock(3725)) == ("42 s", "3 min 05 s", "1 h 02 min")


def test_an_invalid_result_is_a_failure_and_is_not_stored(tmp_path):
    units = plan(priors=["p"])

    def wrong_hash(unit):
        r = FakeExecutor()(unit)
        return dict(r, spec_hash="0" * 64) if unit.batch_index == 1 else r

    report = runner.run_units(units, wrong_hash, tmp_path, progress=False)
    assert len(report.failed) == 6 and all("spec_hash" in m for m in report.failed.values())
    assert len(_files(tmp_path / "units")) == 6


def test_unreadable_file_is_moved_aside_and_rerun(tmp_path):
    units = plan(priors=["p"])
    path = unit_path(tmp_path, units[0].unit_id)
    path.parent.mkdir(parents=True)
    path.write_text("{ half a file")
    ex = FakeExecutor()
    report = runner.run_units(units, ex, tmp_path, progress=False)
    assert report.ok and units[0].unit_id in ex.calls
    assert (tmp_path / "units" / "stale" / f"{units[0].unit_id}.unreadable.json").read_text() == "{ half a file"


def test_unknown_backend_and_policy_are_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown backend 'dask'; available: local, ray"):
        runner.run_units(plan(), FakeExecutor(), tmp_path, backend="dask")
    with pytest.raises(ValueError, match="unknown resume policy 'always'; choose one of only-missing, never"):
        runner.run_units(plan(), FakeExecutor(), tmp_path, resume="always")
    assert not (tmp_path / "units").exists()


def test_backend_seam_accepts_out_of_order_completion(tmp_path, monkeypatch):
    def reversed_backend(units, execute, on_done):  # finishes units in another order, like a cluster would
        for unit in reversed(list(units)):
            on_done(unit, execute(unit), None)

    monkeypatch.setitem(BACKENDS, "reversed", reversed_backend)
    units = plan(priors=["p"])
    ex = FakeExecutor()
    report = runner.run_units(units, ex, tmp_path, backend="reversed", progress=False)
    assert ex.calls == [u.unit_id for u in reversed(units)]
    assert list(report.results) == [u.unit_id for u in units]


def test_progress_is_off_when_stdout_is_not_a_terminal(monkeypatch):
    class Tty(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr("sys.stdout", io.StringIO())
    assert runner.progress_enabled(None) is False
    monkeypatch.setattr("sys.stdout", Tty())
    assert runner.progress_enabled(None) is True
    assert runner.progress_enabled(False) is False

