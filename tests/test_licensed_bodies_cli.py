"""``--body smpl|smplh|smplx`` through the CLI (run, describe, data convert) on tiny random model
files written in each official layout: SMPL as an original-style ``.pkl`` (chumpy arrays and a
sparse regressor, read without chumpy), SMPL-H as AMASS's ``smplh/neutral/model.npz``, SMPL-X as
``smplx/SMPLX_NEUTRAL.npz``. The run is the real table1 protocol, shrunk (``tiny_run``)."""

from __future__ import annotations

import json
import sys

import pytest

from benchmark.cli import main
from benchmark.core.motion import Motion
from test_smpl_body import make_model, write_chumpy_pkl, write_npz
from tiny_run import amass_file, tiny_table1, write_motion

# kind -> (layout under the root, shape parameters the body uses, joints in the file)
LAYOUTS = {
    "smpl": ("smpl/SMPL_NEUTRAL.pkl", 10, 24),
    "smplh": ("smplh/neutral/model.npz", 10, 52),
    "smplx": ("smplx/SMPLX_NEUTRAL.npz", 10, 55),
}


def write_official(root, kind, monkeypatch):
    layout = LAYOUTS[kind][0]
    model = make_model(kind, num_betas=16 if kind == "smplh" else 12, per_joint=6, seed=3)
    if layout.endswith(".pkl"):
        write_chumpy_pkl(root / layout, model, monkeypatch)
        assert "chumpy" not in sys.modules
    else:
        write_npz(root / layout, model)
    return root / layout


@pytest.fixture(params=sorted(LAYOUTS))
def licensed(request, tmp_path, monkeypatch):
    """(kind, root) with the model found through $BENCHMARK_BODY_MODELS, as a user would set it up."""
    kind = request.param
    root = tmp_path / "body_models"
    write_official(root, kind, monkeypatch)
    monkeypatch.setenv("BENCHMARK_BODY_MODELS", str(root))
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    return kind, root


def test_describe_body(licensed, capsys):
    kind, root = licensed
    assert main(["describe", "--body", kind]) == 0
    out = capsys.readouterr().out
    file_joints = LAYOUTS[kind][2]
    assert f"body {kind}-neutral from {root / LAYOUTS[kind][0]}" in out
    assert f"vertices {file_joints * 6:,}" in out and f"(file: {file_joints})" in out and "shape parameters 10" in out


def test_data_convert_with_body(licensed, tmp_path, capsys):
    kind, root = licensed
    src = amass_file(tmp_path / "seq_poses.npz", seconds=1.0, betas=16)
    out = tmp_path / "seq.npz"
    assert main(["data", "convert", str(src), "--out", str(out), "--body", kind]) == 0
    printed = capsys.readouterr().out
    motion = Motion.load(out)
    assert motion.num_frames == 31
    if kind == "smplh":  # an AMASS SMPL-H file's betas belong to SMPL-H's shape space only
        assert f"shape for body {kind}-neutral (10 parameters)" in printed
        assert motion.shape.shape == (10,) and motion.body == f"{kind}-neutral"
    else:  # SMPL and SMPL-X have shape spaces of their own: the neutral shape, said so
        assert "no shape" in printed and motion.shape is None


def test_run_table1_with_body(licensed, tmp_path, monkeypatch, capsys):
    kind, root = licensed
    tiny_table1(monkeypatch)
    write_motion(tmp_path / "data" / "a.npz")
    out = tmp_path / "out"
    rc = main(["run", "table1", "--prior", "no-prior", "--body", f"{kind}={root}", "--data", str(tmp_path / "data"),
               "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    table = json.loads((out / "table1.json").read_text())
    assert table["body"] == f"{kind}-neutral"
    cell = table["rows"][0]["cells"][0]
    assert cell.get("na_reason") is None and cell["chamfer_mm"] > 0 and cell["mpjpe_mm"] > 0


def test_missing_model_lists_every_path_tried(tmp_path, monkeypatch, capsys):
    env_root = tmp_path / "env_root"
    env_root.mkdir()
    monkeypatch.setenv("BENCHMARK_BODY_MODELS", str(env_root))
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    write_motion(tmp_path / "data" / "a.npz")
    for argv in (["describe", "--body", "smplx"],
                 ["run", "table1", "--prior", "no-prior", "--body", "smplx", "--data", str(tmp_path / "data"),
                  "--out", str(tmp_path / "out")],
                 ["data", "convert", str(tmp_path / "data" / "a.npz"), "--out", str(tmp_path / "o.npz"), "--body", "smplx"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: no SMPLX model file for gender 'neutral' was found") and "Traceback" not in err
        for tried in (env_root / "smplx" / "SMPLX_NEUTRAL.npz", env_root / "smplx" / "SMPLX_NEUTRAL.pkl",
                      env_root / "smplx" / "neutral" / "model.npz", env_root / "SMPLX_NEUTRAL.npz",
                      tmp_path / "xdg" / "motion-benchmark" / "body_models" / "smplx" / "SMPLX_NEUTRAL.npz"):
            assert str(tried) in err
        assert "<root>/smplh/neutral/model.npz" in err and "smpl-x.is.tue.mpg.de" in err
    assert not (tmp_path / "out" / "units").exists() and not (tmp_path / "o.npz").exists()


def test_data_convert_says_when_the_shape_does_not_fit_the_body(tmp_path, capsys):
    """SMPL-H betas converted for the Anny body are not Anny's shape: the file stores none, and the
    message says so (it claimed a shape for the body)."""
    src = amass_file(tmp_path / "seq_poses.npz", seconds=1.0, betas=16)
    out = tmp_path / "seq.npz"
    assert main(["data", "convert", str(src), "--out", str(out), "--body", "anny"]) == 0
    assert "no shape stored (the input's shape is not body anny's" in capsys.readouterr().out
    assert Motion.load(out).shape is None
