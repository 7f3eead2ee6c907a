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
    from benchmark.core.motion import Motion

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

    mp.setattr("benchmark.core.outdir.tempfile.mkstemp", denied)  # as root, chmod cannot make a folder read-only
    return ["run", "table1", "--prior", "no-prior", "--out", str(tmp / "ro")]


@case("--out on a full disk", "run", "MiB free", "free some space")
def _(tmp, mp):
    import shutil

    mp.setattr("benchmark.core.outdir.shutil.disk_usage", lambda p: shutil._ntuple_diskusage(10 << 30, 10 << 30, 4096))
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


@case("--data .npz cut short", "run", "cut.npz", "300 bytes are not a zip archive", "cut short")
def _(tmp, mp):
    def cut(path):
        motion_file(tmp / "whole.npz")
        truncated_copy(tmp / "whole.npz", path, 300)

    folder = data_folder(tmp, {"cut.npz": cut})
    return ["run", "table1", "--prior", "no-prior", "--data", str(folder), "--out", str(tmp / "o")]


@case("--data AMASS file with NaN poses", "run", "gaps.npz", "field 'poses'", "non-finite", "in 2 frames (the first: [3, 4])", "trim the sequence")
def _(tmp, mp):
    def gaps(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        poses = np.zeros((130, 156))
        poses[3:5] = np.nan
        np.savez(path, poses=poses, trans=np.zeros((130, 3)), mocap_framerate=np.array(30.0), betas=np.zeros(16))

    folder = data_folder(tmp, {"gaps.npz": gaps})
    return ["run", "table1", "--prior", "no-prior", "--data", str(folder), "--out", str(tmp / "o")]


@case("--data where every motion is shorter than the window", "run", "every motion is shorter than the 4.0 s window",
      "short.npz", "lasts 1.0", "at least 4.0 s")
def _(tmp, mp):
    def short(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, poses=np.zeros((31, 156)), trans=np.zeros((31, 3)), mocap_framerate=np.array(30.0), betas=np.zeros(16))

    short(tmp / "data" / "short.npz")  # alone: a folder with one long enough motion runs it
    return ["run", "table1", "--prior", "no-prior", "--data", str(tmp / "data"), "--out", str(tmp / "o")]


@case("sls --data without a motion cycle", "run", "sls found no usable motion cycle of 0.3-3.0 s", "short.npz",
      "repeat a movement")
def _(tmp, mp):
    path = tmp / "data" / "short.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, poses=np.zeros((31, 156)), trans=np.zeros((31, 3)), mocap_framerate=np.array(30.0), betas=np.zeros(16))
    return ["run", "sls", "--prior", "no-prior", "--data", str(tmp / "data"), "--out", str(tmp / "o")]


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


@case("compare: format_version 99", "compare", "'format_version' is 99", "Compare it with the harness version")
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
    mp.setattr("benchmark.core.outdir.tempfile.mkstemp", denied)
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
    from priors.motion_dvae import MotionDVAEPrior

    mp.setattr(MotionDVAEPrior, "default_weights", truncated_copy(WEIGHTS / "motion_dvae.pt", tmp / "motion_dvae.pt"))
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
# files that must never run code when opened (checkpoints, SMPL .pkl, resume state)
# (section: security)
class _EvilPayload:
    """Unpickling it would create ``marker`` (os.system, pickled as ``posix.system``)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def evil_torch_file(path: Path) -> Path:
    """Weights-looking torch checkpoint with a payload; the marker it would create is ``PWNED`` beside it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": {"w": torch.zeros(2)}, "epoch": _EvilPayload(path.parent / "PWNED")}, path)
    return path


@case("EVIL vposer --weights (pickled os.system)", "describe", "EVIL.ckpt", "will not unpickle", "posix.system",
      "fix:", "state_dict")
def _(tmp, mp):
    return ["describe", "vposer-slerp", "--size", "paper", "--weights", str(evil_torch_file(tmp / "EVIL.ckpt"))]


@case("EVIL frequency-guided weights pair (pickled os.system)", "describe", "EVIL.pth", "will not unpickle",
      "posix.system", "torch.save(model.state_dict()")
def _(tmp, mp):
    pair = f"{evil_torch_file(tmp / 'EVIL.pth')},{evil_torch_file(tmp / 'EVIL.pt')}"
    return ["describe", "frequency-guided", "--size", "paper", "--weights", pair]


@case("EVIL smpl .pkl (pickled os.system)", "describe (licensed body)", "EVIL.pkl", "will not unpickle",
      "posix.system", ".npz")
def _(tmp, mp):
    import pickle

    (tmp / "EVIL.pkl").write_bytes(pickle.dumps({"v_template": np.zeros((4, 3)), "f": _EvilPayload(tmp / "PWNED")},
                                                protocol=2))
    return ["describe", "no-prior", "--body", f"smpl={tmp / 'EVIL.pkl'}"]


@case("truncated Anny cache file", "Anny body (library)", "Anny's model cache file", ".safetensors",
      "Error while deserializing header", "rm ", "rebuilds")
def _(tmp, mp):
    import anny.paths

    from benchmark.body.anny_body import _make_anny, load_anny_body

    real = Path(anny.paths.get_anny_cache_path())
    if not list(real.glob("v*/*.safetensors")):
        load_anny_body("cpu")  # a fresh machine: build the real cache once (~1 min), to copy its file names
    for f in sorted(real.glob("v*/*.safetensors")):  # the same names, cut to 4 kB (an interrupted first build)
        dst = tmp / "anny_cache" / f.parent.name / f.name
        dst.parent.mkdir(parents=True, exist_ok=True)
        with open(f, "rb") as src:
            dst.write_bytes(src.read(4096))
    mp.setattr(anny.paths, "_ANNY_CACHE_DIR", [tmp / "anny_cache"])  # what get_anny_cache_path() returns
    return _make_anny

# (end of section: security)


# ------------------------------------------------------------------------------------------------
# implausible motions, scans and shapes: refused or warned before any unit starts
# (section: plausibility)
# Implausible data (issue 33): millisecond timestamps, translations x 1e6, a shape vector of another
# length, bad scan frames, binary or one-frame BVH. Each is refused while the data loads: the CLI
# cases below make planning or running a work unit an error of its own (_pl_no_units), so a case
# that reached the units would fail on its message.


def _pl_no_units(mp):
    def started(*args, **kwargs):
        raise AssertionError("a work unit was planned or run: the bad input was not refused while loading")

    mp.setattr("benchmark.core.work_units.plan_units", started)
    mp.setattr("benchmark.run.runner.run_units", started)


def _pl_motion_folder(tmp: Path, n: int = 121, ms: bool = False, trans_scale: float = 1.0, shape=None,
                      body=None) -> Path:
    """``tmp/data/a.npz``: a 4 s, 30 fps harness motion walking 2 m (the Motion constructor checks
    no plausibility: only loaders do)."""
    from benchmark.core.motion import Motion

    ts = torch.arange(n, dtype=torch.float64) / 30 * (1000.0 if ms else 1.0)
    trans = torch.stack([torch.linspace(0, 2, n), torch.full((n,), 0.9), torch.zeros(n)], 1) * trans_scale
    g = torch.Generator().manual_seed(0)
    Motion(poses=torch.randn(n, 22, 3, generator=g) * 0.1, trans=trans, timestamps=ts, shape=shape, body=body,
           source="test", meta={"subject": "s"}).save(tmp / "data" / "a.npz")
    return tmp / "data"


def _pl_run_motions(tmp, mp, folder: Path) -> list:
    _pl_no_units(mp)
    return ["run", "inbetween", "--prior", "no-prior", "--data", str(folder), "--out", str(tmp / "o")]


def _pl_person(n: int = 300, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform([-0.22, 0.0, -0.125], [0.22, 1.7, 0.125], size=(n, 3))


def _pl_scan_root(tmp: Path, bad=None, timestamps=None, frames: int = 10) -> Path:
    """``tmp/scans/walk_01``: PLY point clouds of a person at 50 fps, with timestamps.txt
    (``timestamps=False``: none); ``bad(path)`` rewrites frame 5 (a later frame: not the first one)."""
    import trimesh

    folder = tmp / "scans" / "walk_01"
    folder.mkdir(parents=True)
    for i in range(frames):
        trimesh.PointCloud(_pl_person(seed=i)).export(folder / f"frame_{i:04d}.ply")
    if timestamps is not False:
        ts = np.arange(frames) / 50.0 if timestamps is None else timestamps
        (folder / "timestamps.txt").write_text("\n".join(f"{t:.6f}" for t in ts) + "\n")
    if bad is not None:
        bad(folder / "frame_0005.ply")
    return tmp / "scans"


def _pl_run_scans(tmp, mp, root: Path) -> list:
    _pl_no_units(mp)
    return ["run", "table1", "--prior", "no-prior", "--data", f"scans={root}", "--out", str(tmp / "o")]


@case("--data motion with millisecond timestamps", "run", "a.npz", "field 'timestamps'", "0.03 fps", "milliseconds",
      "divide them by 1000")
def _(tmp, mp):
    return _pl_run_motions(tmp, mp, _pl_motion_folder(tmp, ms=True))


@case("--data motion with translations x 1e6", "run", "a.npz", "field 'trans'", "refuses more than 1,000 m",
      "1e+06 times too large")
def _(tmp, mp):
    return _pl_run_motions(tmp, mp, _pl_motion_folder(tmp, trans_scale=1e6))


@case("--data motion with a 300-value shape", "run", "a.npz", "field 'shape' has 300 values", "body 'anny' takes 6",
      "drop the field 'shape'")
def _(tmp, mp):
    return _pl_run_motions(tmp, mp, _pl_motion_folder(tmp, shape=torch.rand(300), body="anny"))


@case("convert: 300-value shape for --body anny", "data convert", "a.npz", "field 'shape' has 300 values",
      "body 'anny' takes 6")
def _(tmp, mp):
    folder = _pl_motion_folder(tmp, shape=torch.rand(300), body="anny")
    return ["data", "convert", str(folder / "a.npz"), "--out", str(tmp / "o.npz"), "--body", "anny"]


@case("scans: an empty PLY frame", "run", "frame_0005.ply", "the file is empty")
def _(tmp, mp):
    return _pl_run_scans(tmp, mp, _pl_scan_root(tmp, bad=lambda p: p.write_bytes(b"")))


@case("scans: a garbage PLY frame", "run", "frame_0005.ply", "unreadable PLY file", "re-export")
def _(tmp, mp):
    return _pl_run_scans(tmp, mp, _pl_scan_root(tmp, bad=lambda p: p.write_text("not a ply at all\n")))


@case("scans: a truncated PLY frame", "run", "frame_0005.ply", "unreadable PLY file", "re-export")
def _(tmp, mp):
    return _pl_run_scans(tmp, mp, _pl_scan_root(tmp, bad=lambda p: p.write_bytes(p.read_bytes()[:500])))


@case("scans: a NaN point in a frame", "run", "frame_0005.ply", "NaN")
def _(tmp, mp):
    import trimesh

    def nan_point(path):
        points = _pl_person()
        points[7, 1] = np.nan
        trimesh.PointCloud(points).export(path)

    return _pl_run_scans(tmp, mp, _pl_scan_root(tmp, bad=nan_point))


@case("scans: a 1-point frame", "run", "frame_0005.ply", "1 point(s)", "at least 3")
def _(tmp, mp):
    import trimesh

    return _pl_run_scans(tmp, mp, _pl_scan_root(tmp, bad=lambda p: trimesh.PointCloud(_pl_person(1)).export(p)))


@case("scans: millisecond timestamps", "run", "timestamps.txt", "0.05 fps", "milliseconds", "divide them by 1000")
def _(tmp, mp):
    return _pl_run_scans(tmp, mp, _pl_scan_root(tmp, timestamps=np.arange(10) * 20.0))


@case("scans: no timestamps (run)", "run", "no timestamps", "walk_01/timestamps.txt", "0.00, 0.02, 0.04")
def _(tmp, mp):
    return _pl_run_scans(tmp, mp, _pl_scan_root(tmp, timestamps=False))


@case("complete: scan folder without timestamps", "complete", "no timestamps", "timestamps.txt", "--capture-fps 50")
def _(tmp, mp):
    root = _pl_scan_root(tmp, timestamps=False)
    return ["complete", str(root / "walk_01"), "--prior", "no-prior", "--out", str(tmp / "c")]


@case("complete: a truncated PLY frame", "complete", "frame_0005.ply", "unreadable PLY file")
def _(tmp, mp):
    def fit(*args, **kwargs):
        raise AssertionError("the fit started: the bad frame was not refused while loading")

    mp.setattr("benchmark.protocols.completion.fit", fit)
    root = _pl_scan_root(tmp, bad=lambda p: p.write_bytes(p.read_bytes()[:500]))
    return ["complete", str(root / "walk_01"), "--prior", "no-prior", "--out", str(tmp / "c")]


@case("convert: a BVH of binary bytes", "data convert", "x.bvh", "a binary file, not a BVH")
def _(tmp, mp):
    (tmp / "x.bvh").write_bytes(bytes(range(256)) * 8)
    return ["data", "convert", str(tmp / "x.bvh"), "--out", str(tmp / "o.npz")]


@case("convert: a 1-frame BVH", "data convert", "one.bvh", "'Frames: 1'", "repeat its first frame line",
      "add 1 to 'Frames:'")
def _(tmp, mp):
    from benchmark.loaders.bvh_format import cmu_skeleton, write_bvh

    write_bvh(tmp / "one.bvh", cmu_skeleton(), np.tile(np.eye(3), (1, 31, 1, 1)), np.array([[0.0, 17.0, 0.0]]), 1 / 120)
    return ["data", "convert", str(tmp / "one.bvh"), "--out", str(tmp / "o.npz")]


def test_missing_scan_timestamps_name_no_flag_that_run_lacks(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc, message = run_case(next(c for c in CASES if c.name == "scans: no timestamps (run)"), tmp_path, monkeypatch)
    assert rc == 2 and "--fps" not in message and "--capture-fps" not in message, message


def test_a_refused_scan_folder_leaves_no_table_and_no_unit(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc, message = run_case(next(c for c in CASES if c.name == "scans: a NaN point in a frame"), tmp_path, monkeypatch)
    assert rc == 2, message
    out = tmp_path / "o"
    written = [p.name for p in out.rglob("*") if p.is_file()] if out.exists() else []
    assert not [n for n in written if n.endswith((".json", ".md", ".csv", ".tex"))], written

# (end of section: plausibility)


# ------------------------------------------------------------------------------------------------
# numeric options, --out and what a command may delete or overwrite
# (section: options)
# Numeric options are range-checked when the command line is parsed (benchmark/core/argtypes.py): an
# argparse usage error naming the option, the value and the range, before anything loads. --out is
# checked before any work; --force replaces only what the command wrote itself; an output never
# goes into (or around) its input.


def _op_denied(mp):
    """A read-only --out (as root chmod cannot make one): the write probe is refused."""
    def denied(*a, **k):
        raise PermissionError(errno.EACCES, "Permission denied")

    mp.setattr("benchmark.core.outdir.tempfile.mkstemp", denied)


def _op_no_work(mp):
    """Loading a body or fitting would be work done before the check: an error of its own."""
    def started(*a, **k):
        raise AssertionError("work started before the arguments were checked")

    mp.setattr("benchmark.body.get_body", started)
    mp.setattr("benchmark.protocols.completion.fit", started)


def _op_run_folder(tmp: Path) -> Path:
    run = tmp / "run"
    run.mkdir()
    table_json(run, "table1.json")
    return run


@case("convert: --fps 1e9", "data convert", "argument --fps", "1e9", "1..1000")
def _(tmp, mp):
    return ["data", "convert", str(motion_file(tmp / "m.npz")), "--out", str(tmp / "y.npz"), "--fps", "1e9"]


@case("complete: --window 0", "complete", "argument --window", "0 is out of range", "> 0")
def _(tmp, mp):
    return ["complete", str(motion_file(tmp / "m.npz")), "--prior", "no-prior", "--out", str(tmp / "o"), "--window", "0"]


@case("complete: --steps 0", "complete", "argument --steps", "0 is out of range", ">= 1")
def _(tmp, mp):
    return ["complete", str(motion_file(tmp / "m.npz")), "--prior", "no-prior", "--out", str(tmp / "o"), "--steps", "0"]


@case("complete: --steps -5", "complete", "argument --steps", "-5 is out of range", ">= 1")
def _(tmp, mp):
    return ["complete", str(motion_file(tmp / "m.npz")), "--prior", "no-prior", "--out", str(tmp / "o"), "--steps", "-5"]


@case("complete: --fps 0", "complete", "argument --fps", "0 is out of range", "1..1000")
def _(tmp, mp):
    return ["complete", str(motion_file(tmp / "m.npz")), "--prior", "no-prior", "--out", str(tmp / "o"), "--fps", "0"]


@case("complete: --points 2.5", "complete", "argument --points", "'2.5' is not an integer")
def _(tmp, mp):
    return ["complete", str(motion_file(tmp / "m.npz")), "--prior", "no-prior", "--out", str(tmp / "o"), "--points", "2.5"]


@case("complete: --start -1", "complete", "argument --start", "-1 is out of range", ">= 0")
def _(tmp, mp):
    return ["complete", str(motion_file(tmp / "m.npz")), "--prior", "no-prior", "--out", str(tmp / "o"), "--start", "-1"]


@case("train: --steps 0", "train", "argument --steps", "0 is out of range", ">= 1")
def _(tmp, mp):
    return ["train", "vposer-slerp", "--steps", "0", "--out", str(tmp / "w")]


@case("train: --checkpoint-every 0", "train", "argument --checkpoint-every", "0 is out of range")
def _(tmp, mp):
    return ["train", "vposer-slerp", "--checkpoint-every", "0", "--out", str(tmp / "w")]


@case("train: --val-every -1", "train", "argument --val-every", "-1 is out of range", ">= 0")
def _(tmp, mp):
    return ["train", "vposer-slerp", "--val-every", "-1", "--out", str(tmp / "w")]


@case("make-scans: --sequences 0", "data make-scans", "argument --sequences", "0 is out of range", ">= 1")
def _(tmp, mp):
    return ["data", "make-scans", "--out", str(tmp / "s"), "--sequences", "0"]


@case("make-scans: --points 0", "data make-scans", "argument --points", "0 is out of range")
def _(tmp, mp):
    return ["data", "make-scans", "--out", str(tmp / "s"), "--points", "0"]


@case("make-scans: --holes 1", "data make-scans", "argument --holes", "1 is out of range", "[0, 1)")
def _(tmp, mp):
    return ["data", "make-scans", "--out", str(tmp / "s"), "--holes", "1"]


@case("make-scans: --noise-mm nan", "data make-scans", "argument --noise-mm", "nan is not finite")
def _(tmp, mp):
    return ["data", "make-scans", "--out", str(tmp / "s"), "--noise-mm", "nan"]


@case("export-onnx: --opset 1", "export-onnx", "argument --opset", "1 is out of range", "an integer in 11..")
def _(tmp, mp):
    return ["export-onnx", "vposer-slerp", "--out", str(tmp / "v.onnx"), "--opset", "1"]


@case("run: --jobs 0", "run", "argument --jobs", "0 is out of range")
def _(tmp, mp):
    return ["run", "table1", "--prior", "no-prior", "--jobs", "0", "--out", str(tmp / "o")]


@case("run: --cpus-per-unit 0", "run", "argument --cpus-per-unit", "0 is out of range", "> 0")
def _(tmp, mp):
    return ["run", "table1", "--prior", "no-prior", "--backend", "ray", "--cpus-per-unit", "0", "--out", str(tmp / "o")]


@case("run: --seed -1", "run", "argument --seed", "-1 is out of range", "0..4294967295")
def _(tmp, mp):
    return ["run", "table1", "--prior", "no-prior", "--seed", "-1", "--out", str(tmp / "o")]


@case("data build: --seed abc", "data build", "argument --seed", "'abc' is not an integer")
def _(tmp, mp):
    return ["data", "build", "test", "--seed", "abc"]


@case("fit-check: --fps inf", "fit-check", "argument --fps", "inf is not finite")
def _(tmp, mp):
    return ["fit-check", "--fps", "inf", "--out", str(tmp / "o")]


@case("fit-check: --around own without --multi-start", "fit-check", "--choose and --around shape several starts",
      "add --multi-start K")
def _(tmp, mp):
    return ["fit-check", "--robustness", "--prior", "frequency-guided", "--around", "own", "--out", str(tmp / "o")]


@case("fit-check: --start-probe with --robustness", "fit-check", "--start-probe runs the start search alone",
      "drop --robustness")
def _(tmp, mp):
    return ["fit-check", "--start-probe", "--robustness", "--points", "100", "--fps", "5"]


@case("report: --workers 0", "report", "argument --workers", "0 is out of range")
def _(tmp, mp):
    return ["report", str(_op_run_folder(tmp)), "--workers", "0"]


@case("report: --animation-fps 0", "report", "argument --animation-fps", "0 is out of range", "1..30")
def _(tmp, mp):
    return ["report", str(_op_run_folder(tmp)), "--animation-fps", "0"]


@case("--weights NAME given twice", "run", "--weights", "'hmvae' is given twice", "give each NAME once")
def _(tmp, mp):
    return ["run", "table1", "--prior", "hmvae", "--weights", f"hmvae={WEIGHTS / 'hmvae.pt'}", "--weights",
            f"hmvae={WEIGHTS / 'vposer.pt'}", "--out", str(tmp / "o")]


@case("complete: --out read-only", "complete", "--out", "not writable", "chmod u+w")
def _(tmp, mp):
    source = motion_file(tmp / "m.npz")
    _op_denied(mp)
    _op_no_work(mp)
    return ["complete", str(source), "--prior", "no-prior", "--out", str(tmp / "ro")]


@case("perf: --out is a file", "perf", "--out", "is a file, not a folder")
def _(tmp, mp):
    def measured(*a, **k):
        raise AssertionError("perf measured before checking --out")

    mp.setattr("benchmark.tools.perf.chamfer_compare", measured)
    return ["perf", "--only", "chamfer", "--out", str(text_file(tmp / "perf.txt"))]


@case("perf: --out holds a perf.json perf did not write", "perf", "perf.json", "not written by")
def _(tmp, mp):
    text_file(tmp / "p" / "perf.json", '{"mine": 1}')
    return ["perf", "--only", "chamfer", "--out", str(tmp / "p")]


@case("train: --out read-only", "train", "--out", "not writable")
def _(tmp, mp):
    _op_denied(mp)
    return ["train", "vposer-slerp", "--steps", "1", "--out", str(tmp / "w")]


@case("export-onnx: --force over a training record", "export-onnx", "vposer.json", "not written by export-onnx")
def _(tmp, mp):
    text_file(tmp / "vposer.json", json.dumps({"steps": 15000, "final_val": 0.1}))
    return ["export-onnx", "vposer-slerp", "--out", str(tmp / "vposer.onnx"), "--force"]


@case("make-scans: --force on a folder it did not write", "data make-scans", "not a folder",
      "data make-scans", "nothing was deleted")
def _(tmp, mp):
    text_file(tmp / "X" / "thesis.tex")
    return ["data", "make-scans", "--out", str(tmp / "X"), "--force", "--ids", "no-such-id"]


@case("complete: --out is the capture folder", "complete", "is the input scan folder itself", "outside it")
def _(tmp, mp):
    capture = tmp / "CAP" / "SEQ"
    capture.mkdir(parents=True)
    np.savez(capture / "frame_0000.npz", points=np.zeros((5, 3)))
    _op_no_work(mp)
    return ["complete", str(capture), "--prior", "no-prior", "--out", str(capture), "--force"]


@case("complete: --out contains the capture", "complete", "contains the input scan folder", "outside it")
def _(tmp, mp):
    capture = tmp / "CAP" / "SEQ"
    capture.mkdir(parents=True)
    _op_no_work(mp)
    return ["complete", str(capture), "--prior", "no-prior", "--out", str(tmp / "CAP"), "--force"]


@case("convert: --out is the input (--force)", "data convert", "would replace the input file")
def _(tmp, mp):
    source = motion_file(tmp / "m.npz")
    return ["data", "convert", str(source), "--out", str(tmp / "." / "m.npz"), "--force"]


@case("report: --out is the run folder", "report", "is the run folder itself", "outside it")
def _(tmp, mp):
    run = _op_run_folder(tmp)
    return ["report", str(run), "--out", str(run)]


@case("report: RUN/table1.json instead of RUN", "report", "table1.json is a file, not a run folder",
      "python -m benchmark report")
def _(tmp, mp):
    return ["report", str(_op_run_folder(tmp) / "table1.json")]


@case("train-report: --out is the weights folder", "train-report", "is the --weights-dir itself")
def _(tmp, mp):
    text_file(tmp / "w" / "a.json", json.dumps({"steps": 5}))
    return ["train-report", "--weights-dir", str(tmp / "w"), "--out", str(tmp / "w")]

# (end of section: options)


# ------------------------------------------------------------------------------------------------
# check-prior, report, the install
# (section: misc)

@case("describe: --weights given twice", "describe", "argument --weights: given twice", "'a.pt' and 'b.pt'")
def _(tmp, mp):
    return ["describe", "vposer-slerp", "--weights", "a.pt", "--weights", "b.pt"]


@case("check-prior: --weights given twice", "check-prior", "argument --weights: given twice")
def _(tmp, mp):
    return ["check-prior", "hmvae", "--weights", "a.pt", "--weights", "b.pt"]


@case("complete: --weights given twice", "complete", "argument --weights: given twice")
def _(tmp, mp):
    return ["complete", str(motion_file(tmp / "m.npz")), "--prior", "vposer-slerp", "--size", "paper",
            "--weights", "a.pt", "--weights", "b.pt", "--out", str(tmp / "o")]


@case("report: format_version 99", "report", "'format_version' is 99", "Make its report with the harness version")
def _(tmp, mp):  # the fix in report's words, not compare's ("Compare it with ...")
    run = tmp / "run"
    run.mkdir()
    table_json(run, "table1.json", format_version=99)
    return ["report", str(run)]


@case("--data where every motion has missing frames or a root teleport in the window", "run",
      "no usable motion is left", "gap.npz", "frames are missing between 0.967 s and 2.000 s", "jump.npz",
      "the root moves 5.00 m between 1.467 s and 1.500 s", "split the motion there")
def _(tmp, mp):
    data = tmp / "data"
    data.mkdir()
    for name in ("gap.npz", "jump.npz"):
        t, trans = np.arange(210) / 30.0, np.zeros((210, 3))
        if name == "gap.npz":
            t[30:] += 1.0  # 30 frames lost after 0.967 s
        else:
            trans[45:, 0] = 5.0  # 5 m in one frame at 1.5 s
        np.savez(data / name, poses=np.zeros((210, 22, 3)), trans=trans, timestamps=t, fps=np.float64(30.0))
    return ["run", "table1", "--prior", "no-prior", "--data", str(data), "--out", str(tmp / "o")]


@case("scans: a hole in the timestamps within the window", "run", "is usable", "1 have a hole in it",
      "walk_01/timestamps.txt", "frames are missing between 1.980 s and 2.500 s", "split the capture at the hole")
def _(tmp, mp):
    ts = np.arange(210) / 50.0
    ts[100:] += 0.5  # 25 frames lost after 1.98 s, inside the 4 s window
    return _pl_run_scans(tmp, mp, _pl_scan_root(tmp, timestamps=ts, frames=210))


# (end of section: misc)


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

    monkeypatch.setattr("benchmark.commands.list.cmd_list", boom)  # build_parser binds it when main() runs
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
        text = message.replace(d, "TMP").replace(str(ROOT), "ROOT").splitlines()
        if text and text[0].startswith("usage:"):  # argparse: usage lines, then the error line
            text = text[-1:]
        shown = text[0] if len(text) == 1 else text[0] + " ... (" + str(len(text) - 1) + " more lines: paths tried)"
        shown = shown.replace("|", "\\|")
        print(f"| {i} | {c.where} | {c.name} | `{shown}` |")
