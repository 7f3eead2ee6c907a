"""Bad inputs, as a new user makes them: each fails fast with exit code 2 and one line that names
the file / field / fix (no traceback), or, for library loaders, with a ValueError /
FileNotFoundError whose message does. ``tests/README.md`` lists every case with its message
(``python tests/test_bad_inputs.py`` prints that table).

Each case builds its input under ``tmp`` and returns either the CLI's argv or a callable. Cases
marked ``multiline`` are the body-model resolution errors, which list every path tried.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import torch

if __name__ == "__main__":  # this checkout's benchmark, not an installed one
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmark.cli import main  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@dataclasses.dataclass
class Case:
    name: str
    where: str  # the command or loader
    build: Callable  # (tmp: Path, monkeypatch) -> argv list | callable raising
    expect: tuple  # substrings of the message
    multiline: bool = False
    needs: str | None = None  # "no-cuda": skipped where CUDA exists


CASES: list[Case] = []


def case(name, where, *expect, multiline=False, needs=None):
    def deco(fn):
        CASES.append(Case(name, where, fn, expect, multiline, needs))
        return fn

    return deco


# ------------------------------------------------------------------------------------------------
# inputs


def motion_file(path: Path, seconds: float = 4.0) -> Path:
    from benchmark.motion import Motion

    n = int(seconds * 30) + 1
    g = torch.Generator().manual_seed(0)
    Motion(poses=torch.randn(n, 22, 3, generator=g) * 0.1, trans=torch.zeros(n, 3),
           timestamps=torch.arange(n, dtype=torch.float64) / 30, source="test", meta={"subject": "s"}).save(path)
    return path


def data_folder(tmp: Path, extra: dict | None = None) -> Path:
    folder = tmp / "data"
    motion_file(folder / "a.npz")
    for name, writer in (extra or {}).items():
        writer(folder / name)
    return folder


def amass_pose_transl(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, pose=np.zeros((130, 156)), transl=np.zeros((130, 3)), mocap_framerate=np.array(30.0))
    return path


def text_file(path: Path, text: str = "hello, not a checkpoint\n") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def truncated_copy(src: Path, dst: Path, nbytes: int = 5000) -> Path:
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_bytes(src.read_bytes()[:nbytes])
    return dst


def table_json(tmp: Path, name: str, **changes) -> Path:
    table = {"table": "t", "protocol_version": 1, "profile": "smoke", "format_version": 1, "grid": {"points": [100]},
             "metrics": [{"name": "chamfer_mm"}],
             "rows": [{"prior": "p", "cells": [{"points": 100, "chamfer_mm": 10.0, "fingerprint": "f"}]}]}
    table.update(changes)
    path = tmp / name
    path.write_text(json.dumps(table))
    return path


def tiny_model(tmp: Path, kind: str, layout: str) -> Path:
    """A tiny random SMPL-family model file at ``<tmp>/models/<layout>``; returns the root."""
    from test_smpl_body import make_model, write_npz

    write_npz(tmp / "models" / layout, make_model(kind, num_betas=16 if kind == "smplh" else 10))
    return tmp / "models"


WEIGHTS = ROOT / "priors" / "weights"


def no_body_models(mp, tmp):
    """Resolution sees nothing: no $BENCHMARK_BODY_MODELS, an empty user data directory."""
    mp.delenv("BENCHMARK_BODY_MODELS", raising=False)
    mp.setenv("XDG_DATA_HOME", str(tmp / "xdg"))


# ------------------------------------------------------------------------------------------------
# run


@case("unknown table", "run", "unknown table 'tabel1'", "Did you mean 'table1'")
def _(tmp, mp):
    return ["run", "tabel1", "--prior", "no-prior", "--out", str(tmp / "o")]


@case("unknown profile", "run", "unknown profile 'nope'", "smoke")
def _(tmp, mp):
    return ["run", "table1", "--prior", "no-prior", "--profile", "nope", "--out", str(tmp / "o")]


@case("--device tpu", "run", "--device 'tpu'", "cpu, cuda")
def _(tmp, mp):
    return ["run", "table1", "--prior", "no-prior", "--device", "tpu", "--out", str(tmp / "o")]


@case("--device cuda:x (malformed)", "run", "--device 'cuda:x'")
def _(tmp, mp):
    return ["run", "table1", "--prior", "no-prior", "--device", "cuda:x", "--out", str(tmp / "o")]


@case("--device cuda without CUDA", "run", "no CUDA device", "--device cpu", needs="no-cuda")
def _(tmp, mp):
    return ["run", "table1", "--prior", "no-prior", "--device", "cuda", "--out", str(tmp / "o")]


@case("misspelt --prior", "run", "unknown prior 'vposer-slrp'", "Did you mean 'vposer-slerp'")
def _(tmp, mp):
    return ["run", "table1", "--prior", "vposer-slrp", "--out", str(tmp / "o")]


@case("--out is a file", "run", "is a file, not a folder")
def _(tmp, mp):
    return ["run", "table1", "--prior", "no-prior", "--out", str(text_file(tmp / "out.txt"))]


@case("--out below a file", "run", "cannot be created because", "is a file")
def _(tmp, mp):
    return ["run", "table1", "--prior", "no-prior", "--out", str(text_file(tmp / "out.txt") / "sub")]


@case("--out not writable", "run", "not writable", "chmod u+w")
def _(tmp, mp):
    def denied(*a, **k):
        raise PermissionError(errno.EACCES, "Permission denied")

    mp.setattr("benchmark.outdir.tempfile.mkstemp", denied)  # as root, chmod cannot make a folder read-only
    return ["run", "table1", "--prior", "no-prior", "--out", str(tmp / "ro")]


@case("--out on a full disk", "run", "MiB free", "free some space")
def _(tmp, mp):
    import shutil

    mp.setattr("benchmark.outdir.shutil.disk_usage", lambda p: shutil._ntuple_diskusage(10 << 30, 10 << 30, 4096))
    return ["run", "table1", "--prior", "no-prior", "--out", str(tmp / "full")]


@case("--out locked by a live run", "run", "another run is writing there", "pid")
def _(tmp, mp):
    import socket

    out = tmp / "locked"
    out.mkdir()
    (out / ".lock").write_text(json.dumps({"pid": os.getppid(), "host": socket.gethostname(), "started": time.time()}))
    return ["run", "table1", "--prior", "no-prior", "--out", str(out)]


@case("--weights without NAME=", "run", "--weights must look like NAME=VALUE")
def _(tmp, mp):
    return ["run", "table1", "--prior", "vposer-slerp", "--weights", "vposer.pt", "--out", str(tmp / "o")]


@case("--weights for a prior not run", "run", "not being run", "--prior")
def _(tmp, mp):
    return ["run", "table1", "--prior", "no-prior", "--weights", "hmvae=x.pt", "--out", str(tmp / "o")]


@case("--weights file missing", "run", "no such file", "nope.pt")
def _(tmp, mp):
    return ["run", "table1", "--prior", "hmvae", "--weights", f"hmvae={tmp / 'nope.pt'}", "--out", str(tmp / "o")]


@case("--data folder missing", "run", "--data", "no such file or folder")
def _(tmp, mp):
    return ["run", "table1", "--prior", "no-prior", "--data", str(tmp / "nowhere"), "--out", str(tmp / "o")]


@case("--data folder without .npz", "run", "no .npz motion files")
def _(tmp, mp):
    (tmp / "empty").mkdir()
    return ["run", "table1", "--prior", "no-prior", "--data", str(tmp / "empty"), "--out", str(tmp / "o")]


@case("--data holds a non-npz file named .npz", "run", "fake.npz", "not a readable .npz")
def _(tmp, mp):
    folder = data_folder(tmp, {"fake.npz": text_file})
    return ["run", "table1", "--prior", "no-prior", "--data", str(folder), "--out", str(tmp / "o")]


@case("--data AMASS file with keys pose/transl", "run", "bad.npz", "'pose' / 'transl' are not AMASS names")
def _(tmp, mp):
    folder = data_folder(tmp, {"bad.npz": amass_pose_transl})
    return ["run", "table1", "--prior", "no-prior", "--data", str(folder), "--out", str(tmp / "o")]


@case("--data harness file missing 'trans'", "run", "b.npz", "missing field 'trans'", "data convert")
def _(tmp, mp):
    def partial(path):
        np.savez(path, poses=np.zeros((10, 22, 3)), timestamps=np.arange(10) / 30.0)

    folder = data_folder(tmp, {"b.npz": partial})
    return ["run", "table1", "--prior", "no-prior", "--data", str(folder), "--out", str(tmp / "o")]


@case("--body misspelt", "run", "unknown body model 'smpll'", "Did you mean 'smpl'")
def _(tmp, mp):
    return ["run", "table1", "--prior", "no-prior", "--body", "smpll", "--out", str(tmp / "o")]


@case("--resume always (not a policy)", "run", "invalid choice: 'always'")
def _(tmp, mp):
    return ["run", "table1", "--prior", "no-prior", "--resume", "always", "--out", str(tmp / "o")]


@case("--weights truncated vposer.pt", "run", "vposer.pt", "not a readable torch checkpoint")
def _(tmp, mp):
    bad = truncated_copy(WEIGHTS / "vposer.pt", tmp / "w" / "vposer.pt")
    folder = data_folder(tmp)
    return ["run", "table1", "--prior", "vposer-slerp", "--weights", f"vposer-slerp={bad}", "--data", str(folder),
            "--out", str(tmp / "o")]


# ------------------------------------------------------------------------------------------------
# compare


@case("compare: file missing", "compare", "no such table JSON")
def _(tmp, mp):
    return ["compare", str(tmp / "a.json"), str(table_json(tmp, "b.json"))]


@case("compare: not JSON", "compare", "not valid JSON")
def _(tmp, mp):
    return ["compare", str(text_file(tmp / "a.json")), str(table_json(tmp, "b.json"))]


@case("compare: format_version 99", "compare", "'format_version' is 99")
def _(tmp, mp):
    return ["compare", str(table_json(tmp, "a.json")), str(table_json(tmp, "b.json", format_version=99))]


@case("compare: a metric holds a string", "compare", "b.json", "prior 'p'", "100", "'chamfer_mm' is '10.0'")
def _(tmp, mp):
    rows = [{"prior": "p", "cells": [{"points": 100, "chamfer_mm": "10.0", "fingerprint": "f"}]}]
    return ["compare", str(table_json(tmp, "a.json")), str(table_json(tmp, "b.json", rows=rows))]


@case("compare: a folder", "compare", "is a folder", "table1.json")
def _(tmp, mp):
    return ["compare", str(tmp), str(table_json(tmp, "b.json"))]


@case("compare: JSON without table fields", "compare", "not a table JSON", "missing")
def _(tmp, mp):
    (tmp / "a.json").write_text("{}")
    return ["compare", str(tmp / "a.json"), str(table_json(tmp, "b.json"))]


@case("compare: rows not a list", "compare", "'rows' must be a list")
def _(tmp, mp):
    return ["compare", str(table_json(tmp, "a.json", rows={"p": 1})), str(table_json(tmp, "b.json"))]


@case("compare: --tol not a number", "compare", "bad --tol 'chamfer_mm=abc'")
def _(tmp, mp):
    return ["compare", str(table_json(tmp, "a.json")), str(table_json(tmp, "b.json")), "--tol", "chamfer_mm=abc"]


@case("compare: --tol unknown metric", "compare", "--tol names unknown metric(s) ['mpjpe_m']")
def _(tmp, mp):
    return ["compare", str(table_json(tmp, "a.json")), str(table_json(tmp, "b.json")), "--tol", "mpjpe_m=1"]


# ------------------------------------------------------------------------------------------------
# data convert


@case("convert: input missing", "data convert", "nope.bvh")
def _(tmp, mp):
    return ["data", "convert", str(tmp / "nope.bvh"), "--out", str(tmp / "o.npz")]


@case("convert: unsupported format", "data convert", "unsupported input format '.c3d'")
def _(tmp, mp):
    return ["data", "convert", str(text_file(tmp / "m.c3d")), "--out", str(tmp / "o.npz")]


@case("convert: AMASS keys pose/transl", "data convert", "m.npz", "'pose' / 'transl' are not AMASS names")
def _(tmp, mp):
    return ["data", "convert", str(amass_pose_transl(tmp / "m.npz")), "--out", str(tmp / "o.npz")]


@case("convert: non-npz file named .npz", "data convert", "m.npz", "not a readable .npz")
def _(tmp, mp):
    return ["data", "convert", str(text_file(tmp / "m.npz")), "--out", str(tmp / "o.npz")]


@case("convert: --out not .npz", "data convert", "ending in .npz")
def _(tmp, mp):
    return ["data", "convert", str(motion_file(tmp / "m.npz")), "--out", str(tmp / "o.pkl")]


@case("convert: --out exists", "data convert", "already exists", "--force")
def _(tmp, mp):
    return ["data", "convert", str(motion_file(tmp / "m.npz")), "--out", str(motion_file(tmp / "o.npz"))]


@case("convert: --out is a folder", "data convert", "is a folder")
def _(tmp, mp):
    (tmp / "o.npz").mkdir()
    return ["data", "convert", str(motion_file(tmp / "m.npz")), "--out", str(tmp / "o.npz")]


@case("convert: --out folder is a file", "data convert", "the folder of --out", "is a file")
def _(tmp, mp):
    return ["data", "convert", str(motion_file(tmp / "m.npz")), "--out", str(text_file(tmp / "f") / "o.npz")]


@case("convert: --out folder read-only", "data convert", "the folder of --out", "not writable")
def _(tmp, mp):
    def denied(*a, **k):
        raise PermissionError(errno.EACCES, "Permission denied")

    source = motion_file(tmp / "m.npz")
    mp.setattr("benchmark.outdir.tempfile.mkstemp", denied)
    return ["data", "convert", str(source), "--out", str(tmp / "ro" / "o.npz")]


# ------------------------------------------------------------------------------------------------
# check-prior, describe, export-onnx, perf: weights files and prior names


@case("check-prior: empty motion_dvae.pt", "check-prior", "motion_dvae.pt", "not a readable torch checkpoint", "EOFError")
def _(tmp, mp):
    empty = text_file(tmp / "motion_dvae.pt", "")
    return ["check-prior", "motion-dvae", "--weights", str(empty)]


@case("check-prior: unknown prior", "check-prior", "unknown prior 'hmvea'", "Did you mean 'hmvae'")
def _(tmp, mp):
    return ["check-prior", "hmvea"]


@case("check-prior: text file as weights", "check-prior", "notes.pt", "not a readable torch checkpoint")
def _(tmp, mp):
    return ["check-prior", "vposer-slerp", "--weights", str(text_file(tmp / "notes.pt"))]


@case("describe: truncated vposer.pt", "describe", "vposer.pt", "not a readable torch checkpoint")
def _(tmp, mp):
    return ["describe", "vposer-slerp", "--weights", str(truncated_copy(WEIGHTS / "vposer.pt", tmp / "vposer.pt"))]


@case("describe: truncated frequency_guided.pt", "describe", "frequency_guided.pt", "not a readable torch checkpoint")
def _(tmp, mp):
    bad = truncated_copy(WEIGHTS / "frequency_guided.pt", tmp / "frequency_guided.pt")
    return ["describe", "frequency-guided", "--weights", str(bad)]


@case("describe: corrupt embedded weights", "describe", "motion_dvae.pt", "git checkout", "train motion-dvae")
def _(tmp, mp):
    import priors.motion_dvae.adapter as module

    mp.setattr(module, "DEFAULT_WEIGHTS", truncated_copy(WEIGHTS / "motion_dvae.pt", tmp / "motion_dvae.pt"))
    return ["describe", "motion-dvae"]


@case("describe: no prior, no --body", "describe", "describe needs a prior NAME")
def _(tmp, mp):
    return ["describe"]


@case("export-onnx: prior without decoder", "export-onnx", "no-prior", "no decoder")
def _(tmp, mp):
    return ["export-onnx", "no-prior", "--out", str(tmp / "np.onnx")]


@case("export-onnx: --out not .onnx", "export-onnx", "must end in .onnx")
def _(tmp, mp):
    return ["export-onnx", "vposer-slerp", "--out", str(tmp / "v.onx")]


@case("export-onnx: --out exists", "export-onnx", "exists", "--force")
def _(tmp, mp):
    return ["export-onnx", "vposer-slerp", "--out", str(text_file(tmp / "v.onnx"))]


@case("export-onnx: onnx not installed", "export-onnx", "'onnx'", "pip install 'onnx>=1.15'")
def _(tmp, mp):
    mp.setitem(sys.modules, "onnx", None)  # import onnx -> ImportError, as without the package
    return ["export-onnx", "vposer-slerp", "--out", str(tmp / "v.onnx")]


@case("export-onnx: empty hmvae.pt", "export-onnx", "hmvae.pt", "not a readable torch checkpoint", "EOFError")
def _(tmp, mp):
    return ["export-onnx", "hmvae", "--weights", str(text_file(tmp / "hmvae.pt", "")), "--out", str(tmp / "h.onnx")]


@case("perf --device cuda without CUDA", "perf", "no CUDA device", needs="no-cuda")
def _(tmp, mp):
    return ["perf", "--device", "cuda"]


# ------------------------------------------------------------------------------------------------
# licensed bodies


@case("--body smpl: no model file anywhere", "run (licensed body)", "no SMPL model file", "Paths tried",
      "SMPL_NEUTRAL.pkl", "BENCHMARK_BODY_MODELS", multiline=True)
def _(tmp, mp):
    no_body_models(mp, tmp)
    return ["run", "table1", "--prior", "no-prior", "--body", "smpl", "--data", str(data_folder(tmp)), "--out", str(tmp / "o")]


@case("--body smplh=ROOT: empty root", "describe (licensed body)", "no SMPLH model file", "neutral/model.npz",
      "an explicit path was given", multiline=True)
def _(tmp, mp):
    (tmp / "models").mkdir()
    return ["describe", "--body", f"smplh={tmp / 'models'}"]


@case("--body smplx: truncated .npz", "data convert (licensed body)", "SMPLX_NEUTRAL.npz", "not a readable .npz")
def _(tmp, mp):
    text_file(tmp / "models" / "smplx" / "SMPLX_NEUTRAL.npz", "PK\x03\x04 truncated")
    return ["data", "convert", str(motion_file(tmp / "m.npz")), "--out", str(tmp / "o.npz"), "--body",
            f"smplx={tmp / 'models'}"]


@case("--body smplh given an SMPL file", "describe (licensed body)", "asked for a 'smplh' model", "holds 'smpl'")
def _(tmp, mp):
    root = tiny_model(tmp, "smpl", "smpl/SMPL_NEUTRAL.npz")
    return ["describe", "--body", f"smplh={root / 'smpl' / 'SMPL_NEUTRAL.npz'}"]


@case("--body smpl:gender unknown", "describe (licensed body)", "unknown gender 'other'")
def _(tmp, mp):
    root = tiny_model(tmp, "smpl", "smpl/SMPL_NEUTRAL.npz")
    return ["describe", "--body", f"smpl={root}:other"]


@case("--body smpl .pkl that is not a pickle", "describe (licensed body)", "SMPL_NEUTRAL.pkl", "could not unpickle")
def _(tmp, mp):
    text_file(tmp / "models" / "smpl" / "SMPL_NEUTRAL.pkl")
    return ["describe", "--body", f"smpl={tmp / 'models'}"]


# ------------------------------------------------------------------------------------------------
# the scans loader (library: load_scan_folder)


def _scans(folder, **kw):
    from benchmark.loaders.scans import load_scan_folder

    return lambda: load_scan_folder(folder, **kw)


@case("scans: folder missing", "scans loader", "does not exist")
def _(tmp, mp):
    return _scans(tmp / "nowhere", fps=30)


@case("scans: no frame files", "scans loader", "no frames found", "frame_0001.ply")
def _(tmp, mp):
    text_file(tmp / "s" / "notes.txt")
    return _scans(tmp / "s", fps=30)


@case("scans: .npz frame without 'points'", "scans loader", "frame_1.npz", "points")
def _(tmp, mp):
    (tmp / "s").mkdir()
    np.savez(tmp / "s" / "frame_1.npz", pts=np.zeros((5, 3)))
    return _scans(tmp / "s", fps=30)


@case("scans: NaN points", "scans loader", "frame_1.npz", "non-finite")
def _(tmp, mp):
    (tmp / "s").mkdir()
    np.savez(tmp / "s" / "frame_1.npz", points=np.full((5, 3), np.nan))
    return _scans(tmp / "s", fps=30)


@case("scans: non-increasing timestamps", "scans loader", "strictly increasing")
def _(tmp, mp):
    (tmp / "s").mkdir()
    for i in (1, 2):
        np.savez(tmp / "s" / f"frame_{i}.npz", points=np.zeros((5, 3)) + i)
    (tmp / "s" / "timestamps.txt").write_text("0.5\n0.5\n")
    return _scans(tmp / "s")


@case("scans: garbage .ply", "scans loader", "frame_1.ply")
def _(tmp, mp):
    text_file(tmp / "s" / "frame_1.ply", "not a ply at all\n")
    return _scans(tmp / "s", fps=30)


# ------------------------------------------------------------------------------------------------


def run_case(c: Case, tmp: Path, mp) -> tuple[int | None, str]:
    """(exit code or None for a loader case, the message)."""
    built = c.build(tmp, mp)
    if callable(built):
        with pytest.raises((ValueError, FileNotFoundError)) as info:
            built()
        return None, str(info.value)
    err = sys.stderr
    import io

    buf = io.StringIO()
    sys.stderr = buf
    try:
        try:
            rc = main(built)
        except SystemExit as exc:  # argparse's own usage errors
            rc = exc.code
    finally:
        sys.stderr = err
    return rc, buf.getvalue().strip()


@pytest.mark.parametrize("c", CASES, ids=[c.name for c in CASES])
def test_bad_input_fails_clearly(c, tmp_path, monkeypatch, capsys):
    if c.needs == "no-cuda" and torch.cuda.is_available():
        pytest.skip("CUDA is available here")
    monkeypatch.chdir(tmp_path)
    rc, message = run_case(c, tmp_path, monkeypatch)
    capsys.readouterr()
    if rc is not None:
        assert rc == 2, f"{c.name}: exit code {rc}, message {message!r}"
        assert message.startswith(("error: ", "usage: ")), message
    assert "Traceback" not in message
    if not c.multiline and rc is not None:
        lines = [line for line in message.splitlines() if not line.startswith(("usage:", "  ", "INFO ", "WARNING "))]
        assert len(lines) == 1, f"{c.name}: expected one line, got {message!r}"
    for needle in c.expect:
        assert needle in message, f"{c.name}: {needle!r} not in {message!r}"


def test_at_least_forty_distinct_bad_inputs():
    assert len({c.name for c in CASES}) == len(CASES) >= 40
    assert {c.where.split(" (")[0] for c in CASES} >= {"run", "compare", "data convert", "check-prior", "describe",
                                                      "export-onnx", "scans loader"}


def test_wrong_out_fails_in_seconds_before_any_fitting(tmp_path):
    """A new process, as a user runs it: a wrong --out is refused before the body, data or priors load."""
    target = tmp_path / "results.json"
    target.write_text("{}")
    env = dict(os.environ, OMP_NUM_THREADS="1")
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "benchmark", "run", "table1", "--prior", "no-prior", "--out", str(target)], cwd=ROOT,
                          capture_output=True, text=True, env=env, timeout=120)
    elapsed = time.perf_counter() - t0
    assert proc.returncode == 2 and elapsed < 15, (proc.returncode, elapsed, proc.stderr)
    assert proc.stderr.strip().splitlines() == [f"error: --out {target}: is a file, not a folder; give a folder path "
                                                "(it is created if missing), e.g. --out runs/mytable"]
    assert "table table1" not in proc.stdout  # nothing started


def test_debug_shows_the_traceback(tmp_path, capsys):
    assert main(["--debug", "run", "table1", "--device", "tpu", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and err.strip().splitlines()[-1].startswith("error: --device 'tpu'")


def test_an_unexpected_exception_is_one_line_naming_its_type(monkeypatch, capsys):
    def boom(args):
        raise AssertionError("internal invariant broken")

    monkeypatch.setattr("benchmark.cli._cmd_list", boom)  # build_parser binds it when main() runs
    assert main(["list"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "error: AssertionError: internal invariant broken (run with --debug for the traceback)"


if __name__ == "__main__":  # print the table of tests/README.md: python tests/test_bad_inputs.py
    import tempfile

    assert Path(sys.modules["benchmark"].__file__).resolve().parents[1] == ROOT, "run from the repository root"

    class _MP:
        def __init__(self):
            self.mp = pytest.MonkeyPatch()

        def __getattr__(self, name):
            return getattr(self.mp, name)

    print("| # | where | bad input | message |")
    print("|--:|:--|:--|:--|")
    for i, c in enumerate(CASES, 1):
        mp = _MP()
        with tempfile.TemporaryDirectory() as d:
            cwd = os.getcwd()
            os.chdir(d)
            try:
                rc, message = run_case(c, Path(d), mp)
            except BaseException as exc:  # noqa: BLE001
                rc, message = "?", f"(case failed: {exc!r})"
            finally:
                os.chdir(cwd)
                mp.undo()
        text = message.replace(d, "TMP").splitlines()
        if text and text[0].startswith("usage:"):  # argparse: usage lines, then the error line
            text = text[-1:]
        shown = text[0] if len(text) == 1 else text[0] + " ... (" + str(len(text) - 1) + " more lines: paths tried)"
        shown = shown.replace("|", "\\|")
        print(f"| {i} | {c.where} | {c.name} | `{shown}` |")
