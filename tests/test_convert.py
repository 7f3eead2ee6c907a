from pathlib import Path

import numpy as np
import pytest
import torch

from benchmark.loaders.bvh_format import cmu_skeleton, write_bvh
from benchmark.loaders.convert import convert, detect_format
from benchmark.core.motion import Motion


def test_convert_amass_and_bvh_and_refuse_overwrite(tmp_path):
    amass = tmp_path / "seq_poses.npz"
    rng = np.random.default_rng(0)
    np.savez(amass, poses=0.2 * rng.standard_normal((61, 156)), trans=rng.standard_normal((61, 3)),
             betas=np.zeros(16), gender="male", mocap_framerate=np.array(60.0))
    bvh = write_bvh(tmp_path / "01_01.bvh", cmu_skeleton(), np.tile(np.eye(3), (5, 31, 1, 1)),
                    np.zeros((5, 3)), 1 / 120)
    assert detect_format(amass) == "amass" and detect_format(bvh) == "bvh"

    out = tmp_path / "out" / "a.npz"
    m = convert(amass, out, fps=30)
    assert m.num_frames == 31 and out.is_file()
    back = Motion.load(out)
    assert torch.equal(back.poses, m.poses) and back.body == "smplh"
    assert back.meta["stored_fps"] == 60.0 and back.meta["resampled"]["to_fps"] == 30.0
    assert detect_format(out) == "harness"

    with pytest.raises(FileExistsError, match=r"a.npz already exists.*overwrite=True \(CLI: --force\)"):
        convert(bvh, out)
    m2 = convert(bvh, out, overwrite=True)
    assert m2.num_frames == 4 and Motion.load(out).source.startswith("bvh:")

    # a harness file converts to itself (resampled)
    m3 = convert(out, tmp_path / "b.npz", fps=60)
    assert abs(m3.fps - 60.0) < 1e-9

    with pytest.raises(ValueError, match="unsupported input format '.c3d'"):
        convert(tmp_path / "x.c3d", tmp_path / "c.npz")
    with pytest.raises(ValueError, match="ending in .npz"):
        convert(bvh, tmp_path / "c.pkl")


def test_convert_to_a_capitalised_npz_and_the_cause_of_an_unusable_folder(tmp_path, monkeypatch, capsys):
    """``--out X.NPZ`` used to be refused ("give a path ending in .npz"); a folder no file can be
    created in for another reason than permissions (``/proc``) was reported as "not writable (No such
    file or directory)" with a chmod fix. Now the capitalised name is written (and a ``--data`` folder
    reads it), and the message says what is wrong there."""
    import errno

    from benchmark.cli import main
    from benchmark.core import outdir
    from benchmark.data.table_data import load_motions

    src = tmp_path / "in.npz"
    Motion(poses=torch.zeros(121, 22, 3), trans=torch.zeros(121, 3),
           timestamps=torch.arange(121, dtype=torch.float64) / 30, source="test").save(src)
    data = tmp_path / "data"
    m = convert(src, data / "walk.NPZ")
    assert Motion.load(data / "walk.NPZ").num_frames == m.num_frames == 121
    assert list(load_motions(f"amass={data}", 1.0)) == ["walk.NPZ"]

    def refuse(*a, **k):  # what creating a file in /proc raises, as root too
        raise FileNotFoundError(errno.ENOENT, "No such file or directory")

    monkeypatch.setattr(outdir.tempfile, "mkstemp", refuse)
    assert main(["data", "convert", str(src), "--out", str(tmp_path / "x.npz")]) == 2
    err = capsys.readouterr().err
    assert "its filesystem does not let files be created there (creating one failed: No such file or directory, " \
           "although the folder exists)" in err and "chmod" not in err and "not writable" not in err
    monkeypatch.undo()
    if Path("/proc/self").is_dir():  # the real thing, where there is one
        assert main(["data", "convert", str(src), "--out", "/proc/x.npz"]) == 2
        err = capsys.readouterr().err
        assert "the folder of --out /proc: its filesystem does not let files be created there" in err
        assert "chmod" not in err and "Traceback" not in err
