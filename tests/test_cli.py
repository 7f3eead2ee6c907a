"""The command line: help, list, conformance kit, describe, error paths."""

import pytest
from pathlib import Path

from benchmark.cli import main
from benchmark.run.registry import get_prior_class, register, unregister


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


def test_check_prior_takes_runs_name_equals_path_form_of_weights(tmp_path, capsys):
    """``--weights NAME=PATH`` (run's form, as docs/real-data.md shows it) is this prior's PATH; another
    prior's name is refused; a file name holding '=' (VPoser's snapshots) stays a plain path."""
    from benchmark.run.registry import registry

    weights = str(registry()["vposer-slerp"].load().default_weights)
    assert main(["check-prior", "vposer-slerp", "--weights", f"vposer-slerp={weights}"]) == 0
    capsys.readouterr()
    assert main(["check-prior", "vposer-slerp", "--weights", f"hmvae={weights}"]) == 2
    assert "names prior 'hmvae', but the prior checked is 'vposer-slerp'" in capsys.readouterr().err
    odd = tmp_path / "V02_05_epoch=13_val_loss=0.03.pt"
    odd.write_bytes(Path(weights).read_bytes())
    assert main(["check-prior", "vposer-slerp", "--weights", str(odd)]) == 0


def test_describe_prints_parameter_count(capsys):
    assert main(["describe", "vposer-slerp"]) == 0
    assert "parameters:" in capsys.readouterr().out


def test_bad_input_is_a_clear_error(capsys, tmp_path):
    missing = tmp_path / "nope.bvh"
    assert main(["data", "convert", str(missing), "--out", str(tmp_path / "o.npz")]) == 2
    assert "nope.bvh" in capsys.readouterr().err


def test_describe_paper_size_without_weights(capsys):
    assert main(["describe", "vposer-slerp", "--size", "paper"]) == 0
    out = capsys.readouterr().out
    assert "parameters: 936,252 (trainable 936,252)" in out and "random weights" in out
    assert "encoder_net" in out and "592,062" in out and "344,190" in out  # per top-level child


def test_describe_embedded_counts_per_child(capsys):
    assert main(["describe", "vposer-slerp"]) == 0
    out = capsys.readouterr().out
    assert "parameters: 271,676 (trainable 0" in out
    assert "vposer.encoder_net" in out and "165,054" in out and "vposer.decoder_net" in out and "106,622" in out


def test_export_onnx_cli(capsys, tmp_path):
    out = tmp_path / "v.onnx"
    assert main(["export-onnx", "vposer-slerp", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert str(out) in text and "z ('batch', 32)" in text and "rotations ('batch', 22, 3, 3)" in text
    assert "PASS" in text and out.with_suffix(".json").exists()
    assert main(["export-onnx", "vposer-slerp", "--out", str(out), "--no-check"]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["export-onnx", "vposer-slerp", "--out", str(out), "--no-check", "--force"]) == 0
    assert "not checked" in capsys.readouterr().out


def test_export_onnx_no_prior_is_a_clear_error(capsys, tmp_path):
    assert main(["export-onnx", "no-prior", "--out", str(tmp_path / "np.onnx")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "no-prior" in err and "no decoder" in err
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def _subparsers(parser):
    """Every parser under ``parser`` (sub-commands and their own sub-commands), by its prog."""
    import argparse

    found = {parser.prog: parser}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found.update(_subparsers(sub))
    return found


def test_help_states_each_default_once():
    """An option whose help says its default (``default: full on CUDA, quick on CPU``) gets no
    second, argparse-made one (``(default: None)``) beside it."""
    from benchmark.cli import build_parser

    parsers = _subparsers(build_parser())
    assert "python -m benchmark run" in parsers and "python -m benchmark data make-scans" in parsers
    twice = []
    for prog, parser in parsers.items():
        formatter = parser._get_formatter()
        for action in parser._actions:
            if action.help:
                text = formatter._get_help_string(action)
                if "default" in action.help.lower() and text != action.help:  # argparse added a second one
                    twice.append(f"{prog} {'/'.join(action.option_strings) or action.dest}: {text}")
    assert not twice, "\n".join(twice)
    run_help = parsers["python -m benchmark run"].format_help()
    assert "(default: runs/latest)" in run_help  # the defaults argparse knows are still shown
