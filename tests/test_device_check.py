"""device-check: each (table, prior) runs on its own, a failure is recorded with where it happened and
the others still run; the report compares what ran with the committed smoke tables."""

from __future__ import annotations

import json

import pytest

from benchmark.cli import main
from benchmark.tools import device_check


def test_pair_order_runs_no_prior_everywhere_first():
    order = device_check.pair_order(["table1", "sls"], {"table1": ["no-prior", "hmvae"], "sls": ["hmvae", "no-prior"]})
    assert order == [("table1", "no-prior"), ("sls", "no-prior"), ("table1", "hmvae"), ("sls", "hmvae")]


def test_failures_are_collected_and_the_rest_runs(tmp_path, monkeypatch, capsys):
    from benchmark.run import table_run

    real = table_run.run_table

    def flaky(spec, profile, priors, *args, **kwargs):
        if spec["name"] == "denoise":  # as a device mix-up does, deep inside the harness
            def deep():
                raise RuntimeError("Expected all tensors to be on the same device, but found at least two devices")
            deep()
        return real(spec, profile, priors, *args, **kwargs)

    monkeypatch.setattr(table_run, "run_table", flaky)
    out = tmp_path / "dc"
    code = main(["device-check", "--device", "cpu", "--table", "inbetween", "--table", "denoise",
                 "--prior", "no-prior", "--prior", "slerp", "--out", str(out)])
    assert code == 1
    report = json.loads((out / "device-check.json").read_text())
    status = {(p["table"], p["prior"]): p["status"] for p in report["pairs"]}
    assert status == {("inbetween", "no-prior"): "ok", ("denoise", "no-prior"): "failed",
                      ("inbetween", "slerp"): "ok", ("denoise", "slerp"): "failed"}
    bad = next(p for p in report["pairs"] if p["status"] == "failed")
    assert bad["error"] == "RuntimeError" and "same device" in bad["message"]
    assert "(deep)" in bad["innermost_frame"] and "device_check.py" in bad["project_frame"]
    ok = next(p for p in report["pairs"] if p["status"] == "ok")
    assert "mpjpe_mm" in ok["against_smoke_golden"]  # compared with results/inbetween.smoke.json
    md = (out / "device-check.md").read_text()
    assert "| denoise | no-prior | failed |" in md and "same device" in md and "peak GiB" in md
    assert "2 of 4 pairs ran without error, 2 failed;" in capsys.readouterr().out


def test_a_pair_whose_units_all_fail_is_failed_with_where(tmp_path, monkeypatch, capsys):
    """The runner catches a unit's exception and goes on: a pair whose units raised used to be
    reported "ok" (exit 0) with nothing compared. It is "failed", with the unit's frames."""
    from benchmark.protocols import inbetween

    def broken(*args, **kwargs):
        raise RuntimeError("Expected all tensors to be on the same device, but found at least two devices")

    monkeypatch.setattr(inbetween, "run_unit", broken)
    out = tmp_path / "dc"
    assert main(["device-check", "--device", "cpu", "--table", "inbetween", "--prior", "slerp", "--out", str(out)]) == 1
    pair = json.loads((out / "device-check.json").read_text())["pairs"][0]
    assert pair["status"] == "failed" and pair["error"] == "RuntimeError" and "same device" in pair["message"]
    assert "4 unit(s) failed" in pair["message"] and "(broken)" in pair["innermost_frame"]


def test_budget_stops_new_pairs(tmp_path):
    report = device_check.check_device("cpu", ["inbetween"], ["no-prior", "slerp"], tmp_path / "dc",
                                       tmp_path / "no-results", budget_s=-1.0, log=lambda *a: None)
    assert [p["status"] for p in report["pairs"]] == ["not run (budget spent)"] * 2
    assert not device_check.failed(report)


def test_a_check_that_ran_nothing_does_not_pass(tmp_path, monkeypatch, capsys):
    """Pairs not started for the budget are counted as not run, never as run; a check that ran none
    exits 1, and a budget of 0 or less is refused by the parser."""
    code = main(["device-check", "--device", "cpu", "--table", "inbetween", "--prior", "no-prior", "--prior", "slerp",
                 "--budget", "1e-6", "--out", str(tmp_path / "dc")])  # spent while the body loads
    captured = capsys.readouterr()
    assert code == 1 and "0 of 2 pairs ran without error, 2 not run (--budget 1e-06 s spent)" in captured.out
    assert "nothing was checked" in captured.err
    with pytest.raises(SystemExit):
        main(["device-check", "--device", "cpu", "--budget", "0", "--out", str(tmp_path / "dc2")])
