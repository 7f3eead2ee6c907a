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
