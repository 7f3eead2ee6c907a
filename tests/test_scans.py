"""Captured scan folders: PLY / OBJ / NPZ frames written here, read back, and the errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from benchmark.loaders.scans import list_scan_frames, load_scan_folder, natural_key, read_scan_frame

HALF = np.array([0.2, 0.5, 0.1])


def write_mixed_folder(folder, with_timestamps=True):
    """frame_1.ply (point cloud), frame_2.obj (box mesh), frame_10.npz; returns the clouds in time order."""
    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(7, 3))
    trimesh.PointCloud(cloud).export(folder / "frame_1.ply")
    box = trimesh.creation.box(extents=2 * HALF)
    box.export(folder / "frame_2.obj")
    npz = rng.normal(size=(5, 3))
    np.savez(folder / "frame_10.npz", points=npz, colours=np.zeros((5, 3)))
    (folder / "notes.md").write_text("not a frame")
    if with_timestamps:
        (folder / "timestamps.txt").write_text("# seconds\n0.00\n0.02\n0.04\n")
    return [cloud, np.asarray(box.vertices), npz]


def test_round_trip_in_natural_order(tmp_path):
    clouds = write_mixed_folder(tmp_path)
    assert [p.name for p in list_scan_frames(tmp_path)] == ["frame_1.ply", "frame_2.obj", "frame_10.npz"]
    scans = load_scan_folder(tmp_path)
    assert scans.points.shape == (1, 3, 8, 3) and scans.points.dtype == torch.float32
    assert scans.lengths.tolist() == [[7, 8, 5]]
    assert torch.allclose(scans.timestamps[0], torch.tensor([0.0, 0.02, 0.04], dtype=torch.float64))
    for t, cloud in enumerate(clouds):
        assert np.allclose(scans.frame_points(0, t).numpy(), cloud, atol=1e-6)
    assert bool((scans.points[0, 2, 5:] == 0).all()), "padding is zeros"


def test_natural_key():
    names = ["f10.ply", "f2.ply", "F1.ply", "f2b.ply", "f02a.ply"]
    assert sorted(names, key=natural_key) == ["F1.ply", "f02a.ply", "f2.ply", "f2b.ply", "f10.ply"]


def test_timestamps_from_fps_npy_or_argument(tmp_path):
    write_mixed_folder(tmp_path, with_timestamps=False)
    scans = load_scan_folder(tmp_path, fps=50.0)
    assert torch.allclose(scans.timestamps[0], torch.tensor([0.0, 0.02, 0.04], dtype=torch.float64))
    given = load_scan_folder(tmp_path, timestamps=[1.0, 1.5, 2.0])
    assert given.timestamps[0].tolist() == [1.0, 1.5, 2.0]
    np.save(tmp_path / "timestamps.npy", np.array([3.0, 3.1, 3.2]))
    assert torch.allclose(load_scan_folder(tmp_path).timestamps[0], torch.tensor([3.0, 3.1, 3.2], dtype=torch.float64))


def test_sample_meshes_over_their_surface(tmp_path):
    trimesh.creation.box(extents=2 * HALF).export(tmp_path / "a_1.ply")
    trimesh.creation.box(extents=2 * HALF).export(tmp_path / "a_2.obj")
    scans = load_scan_folder(tmp_path, fps=10, sample=500, seed=4)
    assert scans.lengths.tolist() == [[500, 500]]
    residual = (scans.points.double().abs() / torch.from_numpy(HALF)).amax(-1) - 1
    assert residual.abs().max() < 1e-5, "sampled points lie on the box surface"
    assert not torch.allclose(scans.points[0, 0], scans.points[0, 1]), "fresh samples per frame"
    assert torch.equal(load_scan_folder(tmp_path, fps=10, sample=500, seed=4).points, scans.points)


def test_errors_name_the_file_and_the_fix(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match=r"empty: no frames found.*\.ply"):
        load_scan_folder(empty, fps=50)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_scan_folder(tmp_path / "missing", fps=50)

    folder = tmp_path / "seq"
    folder.mkdir()
    write_mixed_folder(folder, with_timestamps=False)
    with pytest.raises(ValueError, match=r"no timestamps; add timestamps.txt.*or pass fps="):
        load_scan_folder(folder)
    (folder / "timestamps.txt").write_text("0.0\n0.1\n")
    with pytest.raises(ValueError, match=r"timestamps.txt gives 2 timestamps for 3 frame files"):
        load_scan_folder(folder)
    (folder / "timestamps.txt").write_text("0.0\n0.2\n0.1\n")
    with pytest.raises(ValueError, match="strictly increasing"):
        load_scan_folder(folder)
    np.save(folder / "timestamps.npy", np.arange(3.0))
    with pytest.raises(ValueError, match="both timestamps.txt and timestamps.npy"):
        load_scan_folder(folder)
    (folder / "timestamps.txt").unlink()

    with pytest.raises(ValueError, match=r"frame_1.ply: sample=10 needs a mesh with faces.*drop sample"):
        load_scan_folder(folder, sample=10)
    with pytest.raises(ValueError, match=r"frame_10.npz: sample=10 applies to meshes.*drop sample"):
        read_scan_frame(folder / "frame_10.npz", sample=10)
    np.savez(folder / "frame_10.npz", xyz=np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"frame_10.npz: no 'points' array \(found keys \['xyz'\]\)"):
        load_scan_folder(folder)
    np.savez(folder / "frame_10.npz", points=np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"frame_10.npz: 'points' must be an \(N, 3\) array"):
        load_scan_folder(folder)
    (folder / "frame_10.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="frame_10.npz: unreadable npz file"):
        load_scan_folder(folder)
    np.savez(folder / "frame_10.npz", points=np.zeros((4, 3)))
    (folder / "frame_1.ply").write_text("garbage")
    with pytest.raises(ValueError, match="frame_1.ply: unreadable PLY file"):
        load_scan_folder(folder)
    (folder / "frame_1.ply").write_text("")
    with pytest.raises(ValueError, match="frame_1.ply: "):
        load_scan_folder(folder)


def test_capture_content_hash_follows_bytes_units_and_up(tmp_path):
    """Resume keys a capture's units on its content: the frames' bytes, the up axis and the units."""
    from benchmark.loaders.scans import ScanSequence
    from benchmark.run.table_run import motion_sha256

    write_mixed_folder(tmp_path)
    base = motion_sha256(ScanSequence(tmp_path, check=False))
    assert base == motion_sha256(ScanSequence(tmp_path, check=False))
    assert base != motion_sha256(ScanSequence(tmp_path, units="mm", check=False))
    assert base != motion_sha256(ScanSequence(tmp_path, up="z", check=False))
    np.savez(tmp_path / "frame_10.npz", points=np.ones((5, 3)))
    assert base != motion_sha256(ScanSequence(tmp_path, check=False))
