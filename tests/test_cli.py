"""The command line: help, list, conformance kit, describe, error paths."""

import pytest

from benchmark.cli import main
from benchmark.registry import get_prior_class, register, unregister


def test_help_and_list(capsys):
    assert main([]) == 0
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for needle in ("table1", "no-prior", "vposer-slerp", "synthetic:test", "anny", "smplh", "quick", "smoke", "full"):
        assert needle in out


def test_unknown_prior_says_did_you_mean():
    with pytest.raises(KeyError, match="did you mean|Did you mean"):
        get_prior_class("vposer-slrp")


def test_broken_plugin_is_reported_not_fatal(capsys):
    register("broken-example", "no_such_module_xyz:Prior")
    try:
        assert main(["list", "priors"]) == 0
        out = capsys.readouterr().out
        assert "broken-example" in out and "LOAD ERROR" in out
    finally:
        unregister("broken-example")


def test_check_prior_passes_for_no_prior(capsys):
    assert main(["check-prior", "no-prior"]) == 0
    out = capsys.readouterr().out
    assert "FAIL" not in out and out.strip().endswith("PASS")


def test_describe_prints_parameter_count(capsys):
    assert main(["describe", "vposer-slerp"]) == 0
    assert "parameters:" in capsys.readouterr().out


def test_bad_input_is_a_clear_error(capsys, tmp_path):
    missing = tmp_path / "nope.bvh"
    assert main(["data", "convert", str(missing), "--out", str(tmp_path / "o.npz")]) == 2
    assert "nope.bvh" in capsys.readouterr().err
