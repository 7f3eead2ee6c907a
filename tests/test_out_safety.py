"""What a command may write, replace or delete (issue 33).

- Nothing a user wrote is deleted or overwritten before every argument is checked, and then only
  what the command wrote itself: ``data make-scans --force`` and ``complete --force`` replace a
  folder only when it holds their marker (``benchmark.core.outdir.MARKER_NAME``) and nothing else.
- An output never goes into, onto or around its input (``complete CAP/SEQ --out CAP/SEQ``).
- Every command that writes checks ``--out`` first: a file or read-only ``--out`` fails in seconds,
  before any body, data, prior or measurement loads.
"""

from __future__ import annotations

import errno
import hashlib
import importlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmark.cli import main
from benchmark.core.outdir import MARKER_NAME

ROOT = Path(__file__).resolve().parents[1]

# a make-scans output that takes seconds: one sequence, 3 frames of 50 points
SMALL = ["--points", "50", "--duration", "0.3", "--fps", "10", "--noise-mm", "0"]


def tree(folder: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file below ``folder``."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def make_scans(out: Path, *ids: str, force: bool = False) -> int:
    return main(["data", "make-scans", "--out", str(out), "--ids", *ids, *SMALL] + (["--force"] if force else []))


@pytest.fixture(scope="module")
def scan_set(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scans") / "set"
    assert make_scans(out, "synthetic:test:0000") == 0
    return out


# -- make-scans --force -----------------------------------------------------------------------------
def test_make_scans_force_with_a_bad_argument_keeps_the_users_folder(tmp_path, capsys):
    folder = tmp_path / "X"
    folder.mkdir()
    (folder / "thesis.tex").write_text("x\n")
    assert main(["data", "make-scans", "--out", str(folder), "--force", "--ids", "no-such-id"]) == 2
    assert tree(folder) == {"thesis.tex": hashlib.sha256(b"x\n").hexdigest()}
    assert "nothing was deleted" in capsys.readouterr().err


def test_make_scans_force_with_a_bad_argument_keeps_its_own_earlier_output(scan_set, tmp_path, capsys):
    import shutil

    folder = tmp_path / "own"
    shutil.copytree(scan_set, folder)
    before = tree(folder)
    assert main(["data", "make-scans", "--out", str(folder), "--force", "--ids", "no-such-id"]) == 2
    assert "unknown test sequence ids" in capsys.readouterr().err
    assert main(["data", "make-scans", "--out", str(folder), "--force", "--ids", "synthetic:test:0000",
                 "--duration", "60"]) == 2
    assert "lasts only" in capsys.readouterr().err
    assert tree(folder) == before


def test_make_scans_force_refuses_a_folder_it_did_not_create(scan_set, tmp_path, capsys):
    import shutil

    # files, no marker: not make-scans' folder
    folder = tmp_path / "mine"
    (folder / "walk_01").mkdir(parents=True)
    (folder / "walk_01" / "frame_0000.ply").write_bytes(b"ply\n")
    before = tree(folder)
    assert make_scans(folder, "synthetic:test:0001", force=True) == 2
    err = capsys.readouterr().err
    assert f"no marker {MARKER_NAME}" in err and "nothing was deleted" in err
    assert tree(folder) == before
    # make-scans' folder with a file of the user's added: refused, both kept
    mixed = tmp_path / "mixed"
    shutil.copytree(scan_set, mixed)
    (mixed / "notes.txt").write_text("mine")
    before = tree(mixed)
    assert make_scans(mixed, "synthetic:test:0001", force=True) == 2
    err = capsys.readouterr().err
    assert "did not write (notes.txt)" in err and "nothing was deleted" in err
    assert tree(mixed) == before
    # another command's marker: refused
    other = tmp_path / "other"
    other.mkdir()
    (other / MARKER_NAME).write_text(json.dumps({"command": "complete", "entries": ["motion.npz"]}))
    (other / "motion.npz").write_bytes(b"x")
    assert make_scans(other, "synthetic:test:0001", force=True) == 2
    assert "'complete'" in capsys.readouterr().err and (other / "motion.npz").exists()


def test_a_second_make_scans_force_replaces_its_own_output(tmp_path, capsys):
    out = tmp_path / "s"
    assert make_scans(out, "synthetic:test:0000") == 0
    assert make_scans(out, "synthetic:test:0001") == 2  # not empty, no --force
    assert "exists and is not empty; pass --force" in capsys.readouterr().err
    assert make_scans(out, "synthetic:test:0001", force=True) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted([MARKER_NAME, "synthetic:test:0001"])
    assert json.loads((out / MARKER_NAME).read_text())["entries"] == ["synthetic:test:0001"]
    assert len(list((out / "synthetic:test:0001").glob("frame_*.ply"))) == 3


def test_make_scans_force_keeps_a_users_file_inside_a_folder_it_wrote(tmp_path, capsys):
    out = tmp_path / "s"
    assert make_scans(out, "synthetic:test:0000") == 0
    notes = out / "synthetic:test:0000" / "annotations.json"
    notes.write_text('{"label": "walk"}')
    assert make_scans(out, "synthetic:test:0000", force=True) == 2
    assert "synthetic:test:0000/annotations.json" in capsys.readouterr().err
    assert notes.read_text() == '{"label": "walk"}'
    notes.unlink()
    assert make_scans(out, "synthetic:test:0000", force=True) == 0  # its own files only: replaced


# -- complete: never into its input ------------------------------------------------------------------
def test_complete_into_the_capture_folder_is_refused_and_the_capture_unchanged(scan_set, capsys, monkeypatch):
    def started(*a, **k):
        raise AssertionError("complete loaded the body before checking --out")

    monkeypatch.setattr("benchmark.body.get_body", started)
    seq = scan_set / "synthetic:test:0000"
    before = tree(scan_set)
    for out, says in ((seq, "is the input scan folder itself"), (scan_set, "contains the input scan folder"),
                      (seq / "fit", "lies inside the input scan folder"),
                      (seq / ".." / seq.name, "is the input scan folder itself")):
        assert main(["complete", str(seq), "--prior", "no-prior", "--out", str(out), "--force"]) == 2, out
        err = capsys.readouterr().err
        assert says in err and "Traceback" not in err, err
    assert tree(scan_set) == before
    assert not (seq / "fit").exists()


def test_complete_force_replaces_only_its_own_output(tmp_path, capsys, monkeypatch):
    from benchmark.tools.complete import OUTPUT_ENTRIES, check_complete_args
    from benchmark.core.outdir import OutDirError, write_marker

    class Args:
        input = str(tmp_path / "m.npz")
        out = str(tmp_path / "o")
        force = True

    Path(Args.input).write_bytes(b"x")
    out = Path(Args.out)
    out.mkdir()
    (out / "motion.npz").write_bytes(b"user's")
    with pytest.raises(OutDirError, match="no marker"):
        check_complete_args(Args)
    write_marker(out, "complete", OUTPUT_ENTRIES)
    assert check_complete_args(Args) == (out, ["motion.npz"])  # replaced only after the fit
    (out / "thesis.tex").write_text("x")
    with pytest.raises(OutDirError, match=r"did not write \(thesis.tex\)"):
        check_complete_args(Args)
    assert sorted(p.name for p in out.iterdir()) == sorted([MARKER_NAME, "motion.npz", "thesis.tex"])
    # inside a folder of its own (meshes/), only the files it recorded writing there
    (out / "thesis.tex").unlink()
    (out / "meshes").mkdir()
    (out / "meshes" / "mesh_0000.obj").write_text("v 0 0 0")
    write_marker(out, "complete", OUTPUT_ENTRIES, files=True)
    assert check_complete_args(Args) == (out, ["meshes", "motion.npz"])
    (out / "meshes" / "notes.txt").write_text("mine")
    with pytest.raises(OutDirError, match=r"did not write \(meshes/notes.txt\)"):
        check_complete_args(Args)


# -- every command that writes: a bad --out first --------------------------------------------------------
def _no_work(mp):
    """Everything that would be work raises: a command that reaches it has checked --out too late."""
    def work(*a, **k):
        raise AssertionError("work started before --out was checked")

    for target in ("benchmark.body.get_body", "benchmark.protocols.completion.fit", "benchmark.run.table_run.run_table",
                   "benchmark.tools.perf.chamfer_compare", "benchmark.tools.perf.surface_compare", "benchmark.commands.export_onnx.make_adapter",
                   "priors.vposer.train.train_vposer", "benchmark.synthetic.splits.build_split",
                   "benchmark.report.build_report", "benchmark.tools.train_report._plot", "benchmark.loaders.convert.load_motion"):
        module, name = target.rsplit(".", 1)
        mp.setattr(importlib.import_module(module), name, work)  # a module, even where a function shares its name


def _commands(tmp: Path, out: Path) -> dict[str, list[str]]:
    """Every command that writes, each with ``out`` as its output folder (or the folder of its file)."""
    from test_bad_inputs import motion_file, table_json

    motion = motion_file(tmp / "m.npz")
    run = tmp / "run"
    run.mkdir(exist_ok=True)
    table_json(run, "table1.json")
    weights = tmp / "weights"
    weights.mkdir(exist_ok=True)
    (weights / "a.json").write_text(json.dumps({"steps": 5}))
    return {
        "run": ["run", "table1", "--prior", "no-prior", "--out", str(out)],
        "complete": ["complete", str(motion), "--prior", "no-prior", "--out", str(out)],
        "perf": ["perf", "--only", "chamfer", "--out", str(out)],
        "export-onnx": ["export-onnx", "vposer-slerp", "--out", str(out / "v.onnx")],
        "train": ["train", "vposer-slerp", "--steps", "1", "--out", str(out)],
        "fit-check": ["fit-check", "--out", str(out)],
        "report": ["report", str(run), "--out", str(out)],
        "data make-scans": ["data", "make-scans", "--out", str(out), "--sequences", "1"],
        "train-report": ["train-report", "--weights-dir", str(weights), "--out", str(out)],
        "data convert": ["data", "convert", str(motion), "--out", str(out / "m.npz")],
        "merge-rows": ["merge-rows", str(run / "table1.json"), str(run / "table1.json"), "--out", str(out)],
    }


COMMANDS = ["run", "complete", "perf", "export-onnx", "train", "fit-check", "report", "data make-scans", "train-report",
            "data convert", "merge-rows"]
FOLDER_OUT = [c for c in COMMANDS if c not in ("export-onnx", "data convert")]  # --out names a folder


@pytest.mark.parametrize("command", FOLDER_OUT)
def test_an_empty_out_is_refused_not_read_as_the_current_folder(command, tmp_path, monkeypatch, capsys):
    """``--out "$DIR"`` with DIR unset must not write into (and over files of) the current folder."""
    monkeypatch.chdir(tmp_path)
    argv = _commands(tmp_path, tmp_path / "x")[command]
    argv[argv.index("--out") + 1] = ""
    _no_work(monkeypatch)
    before = tree(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--out '': empty; give a folder path" in err, (command, err)
    assert tree(tmp_path) == before


def test_run_never_replaces_table_files_it_did_not_write(tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "table1.md").write_text("my notes")
    _no_work(monkeypatch)
    assert main(["run", "table1", "--prior", "no-prior", "--profile", "smoke", "--out", str(out)]) == 2
    assert "table1.md exists and is not an earlier run's table 'table1'" in capsys.readouterr().err
    assert (out / "table1.md").read_text() == "my notes"


@pytest.mark.parametrize("bad", ["file", "read-only"])
@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_that_writes_fails_on_a_bad_out_before_work(command, bad, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    if bad == "file":
        out = tmp_path / "out.txt"
        out.write_text("not a folder")
        says = "is a file, not a folder"
    else:
        out = tmp_path / "ro"
        says = "not writable"
    argv = _commands(tmp_path, out)[command]
    _no_work(monkeypatch)
    if bad == "read-only":
        def denied(*a, **k):
            raise PermissionError(errno.EACCES, "Permission denied")

        monkeypatch.setattr("benchmark.core.outdir.tempfile.mkstemp", denied)  # as root chmod cannot refuse a write
    t0 = time.perf_counter()
    rc = main(argv)
    elapsed = time.perf_counter() - t0
    err = capsys.readouterr().err.strip()
    lines = [line for line in err.splitlines() if not line.startswith(("INFO ", "WARNING "))]
    assert rc == 2 and len(lines) == 1 and says in lines[0], (command, err)
    assert "AssertionError" not in err
    assert elapsed < 15, (command, elapsed)
    if bad == "file":
        assert out.read_text() == "not a folder"


def test_complete_with_a_file_out_fails_within_seconds_in_a_new_process(tmp_path):
    """As a user runs it: a new interpreter, imports included."""
    from test_bad_inputs import motion_file

    target = tmp_path / "results.txt"
    target.write_text("mine")
    env = dict(os.environ, OMP_NUM_THREADS="1")
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "benchmark", "complete", str(motion_file(tmp_path / "m.npz")), "--prior",
                           "no-prior", "--out", str(target)], cwd=ROOT, capture_output=True, text=True, env=env, timeout=120)
    elapsed = time.perf_counter() - t0
    assert proc.returncode == 2 and elapsed < 15, (proc.returncode, elapsed, proc.stderr)
    assert proc.stderr.strip().splitlines()[-1].startswith(f"error: --out {target}: is a file, not a folder")
    assert "fitting" not in proc.stdout and target.read_text() == "mine"


# -- the pieces ---------------------------------------------------------------------------------------
def test_overlap_rules(tmp_path):
    from benchmark.core.outdir import OutDirError, check_not_overlapping

    (tmp_path / "a" / "b").mkdir(parents=True)
    for out, says in ((tmp_path / "a", "itself"), (tmp_path / "a" / "b", "lies inside"), (tmp_path, "contains"),
                      (tmp_path / "a" / "b" / ".." / ".", "itself")):
        with pytest.raises(OutDirError, match=says):
            check_not_overlapping(out, [("input", tmp_path / "a")])
    check_not_overlapping(tmp_path / "a2", [("input", tmp_path / "a")])  # a sibling sharing a prefix
    check_not_overlapping(tmp_path / "a" / "report", [("run folder", tmp_path / "a")], allow_inside=True)
    os.symlink(tmp_path / "a", tmp_path / "link")
    with pytest.raises(OutDirError, match="itself"):
        check_not_overlapping(tmp_path / "link", [("input", tmp_path / "a")])


def test_a_marker_cannot_name_a_path_outside_its_folder(tmp_path):
    from benchmark.core.outdir import remove_entries, write_marker

    (tmp_path / "keep").write_text("x")
    (tmp_path / "out").mkdir()
    with pytest.raises(ValueError, match="plain names"):
        write_marker(tmp_path / "out", "complete", ["../keep"])
    remove_entries(tmp_path / "out", ["../keep", "..", "/", MARKER_NAME])
    assert (tmp_path / "keep").read_text() == "x"


def test_number_types_name_the_range():
    import argparse

    from benchmark.core import argtypes as at

    assert at.positive_int("3") == 3 and at.positive_int("1e3") == 1000 and at.non_negative_int("0") == 0
    assert at.fps("1") == 1.0 and at.fps("1000") == 1000.0 and at.fraction("0") == 0.0
    assert at.seed(str(2**32 - 1)) == 2**32 - 1
    for t, text, says in ((at.positive_int, "0", "0 is out of range (allowed: an integer >= 1)"),
                          (at.positive_int, "2.5", "'2.5' is not an integer >= 1"),
                          (at.fps, "1000.5", "1000.5 is out of range (allowed: a number in 1..1000 frames per second)"),
                          (at.fraction, "1", "[0, 1)"), (at.positive_float, "-inf", "not finite"),
                          (at.positive_float, "0", "> 0"), (at.seed, "-1", "0..4294967295"),
                          (at.points, "abc", "'abc' is not an integer in 1..1000000 points per frame")):
        with pytest.raises(argparse.ArgumentTypeError) as info:
            t(text)
        assert says in str(info.value), (text, str(info.value))


def test_opset_range_is_torchs_and_checked_by_the_library_too(tmp_path):
    from torch.onnx import _constants

    from benchmark.tools.export_onnx import MIN_DYNAMIC_BATCH_OPSET, export_onnx, supported_opsets

    lo, hi = supported_opsets()
    assert lo == max(_constants.ONNX_MIN_OPSET, MIN_DYNAMIC_BATCH_OPSET) and hi == _constants.ONNX_MAX_OPSET
    assert lo <= 17 <= hi  # the default
    with pytest.raises(ValueError, match=f"this torch exports opsets {lo}..{hi}"):
        export_onnx(torch.nn.Linear(2, 2), tmp_path / "x.onnx", opset=hi + 1)
    assert not list(tmp_path.iterdir())


def test_the_training_recipes_check_their_numbers(capsys):
    from priors.motion_dvae.train import main as dvae_main
    from priors.vposer.train import main as vposer_main

    for run, argv, says in ((vposer_main, ["--steps", "0"], "argument --steps: 0 is out of range"),
                            (vposer_main, ["--batch-size", "0"], "argument --batch-size: 0 is out of range"),
                            (dvae_main, ["--steps", "-1"], "argument --steps: -1 is out of range (allowed: an integer >= 0)"),
                            (dvae_main, ["--lr", "0"], "argument --lr: 0 is out of range")):
        with pytest.raises(SystemExit) as info:
            run(argv)
        assert info.value.code == 2 and says in capsys.readouterr().err


def test_zero_and_negative_never_mean_the_default():
    """No ``args.x or default`` is left where 0 would be swallowed: the parsers default to None and
    the code tests ``is None``."""
    import re

    pattern = re.compile(r"args\.(steps|window|points|fps|start|seed|jobs|sequences|workers)\s+or\b|\bif steps:|\bint\(steps\) if steps else")
    hits = []
    for f in sorted((ROOT / "benchmark").rglob("*.py")) + sorted((ROOT / "priors").rglob("*.py")):
        for i, line in enumerate(f.read_text().splitlines(), 1):
            if pattern.search(line):
                hits.append(f"{f.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not hits, hits


def test_report_pre_checks(tmp_path, capsys):
    from test_bad_inputs import table_json

    run = tmp_path / "run"
    run.mkdir()
    table_json(run, "table1.json")
    # a folder holding the user's files is refused (the report replaces index.html and img/)
    site = tmp_path / "site"
    site.mkdir()
    (site / "index.html").write_text("<html>my page</html>")
    assert main(["report", str(run), "--out", str(site)]) == 2
    assert "holds files the report did not write" in capsys.readouterr().err
    assert (site / "index.html").read_text() == "<html>my page</html>"
    # --out around the run folder
    assert main(["report", str(run), "--out", str(tmp_path)]) == 2
    assert "contains the run folder" in capsys.readouterr().err
    np.testing.assert_equal(sorted(p.name for p in run.iterdir()), ["table1.json"])
    # a damaged table JSON is named as such, not "no table JSON here"
    text = (run / "table1.json").read_text()
    (run / "table1.json").write_text(text[: len(text) // 2])
    assert main(["report", str(run), "--out", str(tmp_path / "r")]) == 2
    assert "table1.json (" in capsys.readouterr().err


def test_an_empty_profile_is_unknown_not_the_default(tmp_path, monkeypatch, capsys):
    _no_work(monkeypatch)
    assert main(["run", "table1", "--prior", "no-prior", "--profile", "", "--out", str(tmp_path / "o")]) == 2
    assert "unknown profile ''" in capsys.readouterr().err


def test_a_prior_named_twice_is_refused_before_work(tmp_path, monkeypatch, capsys):
    _no_work(monkeypatch)
    argv = ["run", "table1", "--prior", "no-prior", "--prior", "no-prior", "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    assert "--prior no-prior given twice" in capsys.readouterr().err


def test_report_replaces_only_its_own_earlier_output(tmp_path, capsys):
    """The report used to take a folder for an earlier report of its own when its index.html merely
    contained the text "python -m benchmark report" (or img/ held its old marker), and deleted that
    folder's img/: now only the marker it writes with the files it wrote, and the checksum of its
    index.html, make a folder its own; anything else is refused with nothing written or deleted."""
    from test_bad_inputs import table_json

    run = tmp_path / "run"
    run.mkdir()
    table_json(run, "table1.json")
    notes = tmp_path / "notes"
    (notes / "img").mkdir(parents=True)
    (notes / "index.html").write_text("<p>Made the plots with python -m benchmark report, then edited them</p>")
    (notes / "img" / "figure.png").write_bytes(b"mine")
    args = ["report", str(run), "--sequences", "0", "--out"]
    assert main(args + [str(notes)]) == 2
    err = capsys.readouterr().err
    assert "holds files the report did not write (img, index.html; no marker" in err and "Traceback" not in err
    assert (notes / "img" / "figure.png").read_bytes() == b"mine" and sorted(p.name for p in notes.iterdir()) == ["img", "index.html"]
    (notes / "img" / ".benchmark-report").write_text("written by python -m benchmark report\n")  # an older report's
    assert main(args + [str(notes)]) == 2
    assert "from an older harness" in capsys.readouterr().err and (notes / "img" / "figure.png").exists()
    # its own earlier report is replaced; a file added to it, or an edited page, is not
    rep = tmp_path / "rep"
    assert main(args + [str(rep)]) == 0 and main(args + [str(rep)]) == 0
    assert json.loads((rep / MARKER_NAME).read_text())["command"] == "report"
    (rep / "img" / "mine.png").write_bytes(b"mine")
    assert main(args + [str(rep)]) == 2
    assert "did not write (img/mine.png)" in capsys.readouterr().err and (rep / "img" / "mine.png").exists()
    (rep / "img" / "mine.png").unlink()
    page = (rep / "index.html").read_text() + "<p>my note</p>"
    (rep / "index.html").write_text(page)
    assert main(args + [str(rep)]) == 2
    assert "index.html (changed since the report wrote it)" in capsys.readouterr().err
    assert (rep / "index.html").read_text() == page
