"""The plausibility checks (benchmark/core/plausibility.py, issue 33): every refused case, every warned
case, and normal data (the synthetic test split, the loaders' own test inputs) passing silently."""

from __future__ import annotations

import logging
import re
import types

import numpy as np
import pytest
import torch

from benchmark.core import plausibility as P
from benchmark.core.motion import Motion


def seconds(n=121, fps=30.0):
    return np.arange(n, dtype=np.float64) / fps


def walk(n=121, metres=2.0):
    """A body walking ``metres`` along +x at pelvis height 0.9 m (metres, y up)."""
    return np.stack([np.linspace(0.0, metres, n), np.full(n, 0.9), np.zeros(n)], 1)


def motion(n=121, fps=30.0, ts=None, trans=None, shape=None, body=None):
    g = torch.Generator().manual_seed(0)
    return Motion(poses=torch.randn(n, 22, 3, generator=g) * 0.1,
                  trans=torch.as_tensor(walk(n) if trans is None else trans, dtype=torch.float32),
                  timestamps=torch.as_tensor(seconds(n, fps) if ts is None else ts), shape=shape, body=body,
                  source="test")


def plausibility_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


# ------------------------------------------------------------------------------------------------ time
@pytest.mark.parametrize("fps", [1.0, 24.0, 30.0, 50.0, 120.0, 1000.0])
def test_ordinary_rates_pass_silently(fps, caplog):
    with caplog.at_level(logging.WARNING):
        assert P.check_timestamps(seconds(int(4 * fps) + 1, fps), "f.npz") == []
    assert plausibility_warnings(caplog) == []


@pytest.mark.parametrize("factor, unit, fix", [(1e3, "milliseconds", "divide them by 1000"),
                                               (1e6, "microseconds", "divide them by 10^6"),
                                               (1 / 60, "minutes", "multiply them by 60")])
def test_wrong_time_units_are_refused_naming_the_unit_and_the_fix(factor, unit, fix):
    with pytest.raises(ValueError, match=rf"f\.npz: field 'timestamps' gives a frame rate .*{unit}.*{re.escape(fix)}"):
        P.check_timestamps(seconds() * factor, "f.npz")


@pytest.mark.parametrize("fps", [0.5, 1500.0])
def test_a_rate_outside_1_to_1000_fps_is_refused(fps):
    with pytest.raises(ValueError, match=r"1-1,000 fps"):
        P.check_timestamps(seconds(20, fps), "f.npz")


def test_a_capture_longer_than_an_hour_is_refused():
    # 4 s at 1,000 fps written in milliseconds: a 1 fps rate (in range) over 4,000 s
    with pytest.raises(ValueError, match=r"f\.npz: field 'timestamps' spans 4,000 s.*at most 3,600 s.*by 1000"):
        P.check_timestamps(np.arange(4001, dtype=np.float64), "f.npz")


def test_the_callers_fix_replaces_the_guess():
    with pytest.raises(ValueError, match=r"field 'Frame Time' .*Fix: seconds per frame$"):
        P.check_timestamps(seconds() * 1000, "x.bvh", field="Frame Time", fix="seconds per frame")


def test_a_very_short_capture_is_a_warning(caplog):
    with caplog.at_level(logging.WARNING):
        warnings = P.check_timestamps(seconds(3, 120.0), "f.npz")
    assert len(warnings) == 1 and "lasts only 0.025 s" in warnings[0]
    assert plausibility_warnings(caplog) == warnings
    assert P.check_timestamps(seconds(3, 120.0), "f.npz", warn=False) == warnings
    assert P.check_timestamps([0.0], "f.npz") == []  # one timestamp: nothing to check


# ------------------------------------------------------------------------------------------------ space
def test_ordinary_translations_pass_silently(caplog):
    with caplog.at_level(logging.WARNING):
        assert P.check_translation(walk(metres=20.0), "f.npz") == []
    assert plausibility_warnings(caplog) == []


def test_translations_times_a_million_are_refused():
    with pytest.raises(ValueError, match=r"f\.npz: field 'trans' puts the body 2\.19.e\+06 m from the origin.*"
                                         r"refuses more than 1,000 m.*1e\+06 times too large"):
        P.check_translation(walk() * 1e6, "f.npz")


def test_millimetres_are_refused_naming_the_unit():
    with pytest.raises(ValueError, match=r"millimetres: divide them by 1,000"):
        P.check_translation(walk() * 1000, "f.npz", field="trans")


def test_travelling_kilometres_is_refused_even_near_the_origin():
    tr = walk(metres=1200.0)
    tr[:, 0] -= 600.0  # from -600 m to +600 m: never 1 km from the origin, 1.2 km travelled
    with pytest.raises(ValueError, match=r"moves it over 1,200 m"):
        P.check_translation(tr, "f.npz")


def test_a_few_hundred_metres_is_a_warning(caplog):
    with caplog.at_level(logging.WARNING):
        warnings = P.check_translation(walk(metres=300.0), "f.npz")
    assert len(warnings) == 1 and "more than 100 m" in warnings[0] and "metres" in warnings[0]
    assert plausibility_warnings(caplog) == warnings


def test_check_motion_needs_two_frames_and_runs_both_checks(caplog):
    with pytest.raises(ValueError, match=r"f\.npz: field 'poses' holds 1 frame; a motion needs at least 2"):
        P.check_motion(motion(n=1), "f.npz")
    with pytest.raises(ValueError, match=r"'timestamps'.*milliseconds"):
        P.check_motion(motion(ts=seconds() * 1000), "f.npz")
    with pytest.raises(ValueError, match=r"'trans'.*times too large"):
        P.check_motion(motion(trans=walk() * 1e6), "f.npz")
    with caplog.at_level(logging.WARNING):
        assert P.check_motion(motion(), "f.npz") == []
    assert plausibility_warnings(caplog) == []


# ------------------------------------------------------------------------------------------------ loaders
def test_motion_load_refuses_millisecond_timestamps_and_a_milli_fps(tmp_path):
    path = motion(ts=seconds() * 1000).save(tmp_path / "ms.npz")
    with pytest.raises(ValueError, match=r"ms\.npz: field 'timestamps' gives a frame rate of 0\.03 fps.*milliseconds"):
        Motion.load(path)
    np.savez(tmp_path / "fps.npz", poses=np.zeros((50, 22, 3)), trans=walk(50), fps=0.03)
    with pytest.raises(ValueError, match=r"fps\.npz: field 'fps' gives a frame rate of 0\.03 fps"):
        Motion.load(tmp_path / "fps.npz")
    with pytest.raises(ValueError, match=r"one\.npz: field 'poses' holds 1 frame"):
        Motion.load(motion(n=1).save(tmp_path / "one.npz"))


def test_amass_loader_refuses_a_rate_in_the_wrong_unit_and_huge_translations(tmp_path):
    from benchmark.loaders.amass import load_amass

    def write(name, rate=120.0, scale=1.0):
        np.savez(tmp_path / name, poses=np.zeros((60, 156)), trans=walk(60) * scale, betas=np.zeros(16),
                 mocap_framerate=np.array(rate))
        return tmp_path / name

    with pytest.raises(ValueError, match=r"slow_poses\.npz: field 'mocap_framerate' gives a frame rate of 0\.12 fps.*"
                                         r"frames per second"):
        load_amass(write("slow_poses.npz", rate=0.12))
    with pytest.raises(ValueError, match=r"big_poses\.npz: field 'trans' puts the body"):
        load_amass(write("big_poses.npz", scale=1e6))
    assert load_amass(write("ok_poses.npz")).num_frames == 60


def test_bvh_loader_refuses_frame_time_in_ms_and_names_a_cli_fix_for_one_frame(tmp_path):
    from benchmark.loaders.bvh import load_bvh
    from benchmark.loaders.bvh_format import cmu_skeleton, write_bvh

    def write(name, frames, frame_time=1 / 120, height=17.0):
        return write_bvh(tmp_path / name, cmu_skeleton(), np.tile(np.eye(3), (frames, 31, 1, 1)),
                         np.tile([0.0, height, 0.0], (frames, 1)), frame_time)

    with pytest.raises(ValueError, match=r"ms\.bvh: field 'Frame Time' gives a frame rate of 0\.12 fps.*seconds per"):
        load_bvh(write("ms.bvh", 30, frame_time=1000 / 120))
    with pytest.raises(ValueError, match=r"far\.bvh: field 'root position channels' puts the body.*CMU units"):
        load_bvh(write("far.bvh", 30, height=1e6))
    with pytest.raises(ValueError, match=r"one\.bvh: 'Frames: 1'.*repeat its first frame line.*add 1 to 'Frames:'"):
        load_bvh(write("one.bvh", 1))
    (tmp_path / "bin.bvh").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(ValueError, match=r"bin\.bvh: a binary file, not a BVH"):
        load_bvh(tmp_path / "bin.bvh")
    (tmp_path / "latin.bvh").write_bytes(b"\xff\xfe not utf-8 \xe9")
    with pytest.raises(ValueError, match=r"latin\.bvh: no MOTION section"):
        load_bvh(tmp_path / "latin.bvh")
    (tmp_path / "empty.bvh").write_bytes(b"")
    with pytest.raises(ValueError, match=r"empty\.bvh: the file is empty"):
        load_bvh(tmp_path / "empty.bvh")


# ------------------------------------------------------------------------------------------------ scans
def person(n=300, seed=0):
    return np.random.default_rng(seed).uniform([-0.22, 0.0, -0.125], [0.22, 1.7, 0.125], size=(n, 3))


@pytest.mark.parametrize("n", [0, 1, 2])
def test_a_scan_frame_with_fewer_than_three_points_is_refused(n):
    with pytest.raises(ValueError, match=rf"frame\.ply: the frame has {n} point\(s\); a frame needs at least 3"):
        P.check_scan_frame_size(person(n), "frame.ply")
    P.check_scan_frame_size(person(3), "frame.ply")


def test_a_nan_scan_point_is_refused_naming_it():
    pts = person()
    pts[7, 1] = np.nan
    with pytest.raises(ValueError, match=r"frame\.ply: point 7 is not finite"):
        P.check_scan_points(pts, "frame.ply")


def test_scan_coordinates_far_away_are_refused_and_unusual_ones_warned(caplog):
    with pytest.raises(ValueError, match=r"frame\.ply: point \d+ lies 2,00\d m from the origin.*--units"):
        P.check_scan_coordinates(person() + [2000.0, 0.0, 0.0], "frame.ply")
    with caplog.at_level(logging.WARNING):
        assert P.check_scan_coordinates(person(), "frame.ply") == []
        warnings = P.check_scan_coordinates(person() + [150.0, 0.0, 0.0], "frame.ply")
    assert len(warnings) == 1 and "more than 100 m" in warnings[0]
    assert plausibility_warnings(caplog) == warnings


def write_scan_folder(folder, n=10, ts=None, frames=None):
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        np.savez(folder / f"frame_{i:04d}.npz", points=person(seed=i) if frames is None else frames(i))
    ts = np.arange(n) / 50.0 if ts is None else ts
    (folder / "timestamps.txt").write_text("\n".join(f"{t:.6f}" for t in ts) + "\n")
    return folder


def test_scan_sequences_check_every_frame_when_built(tmp_path):
    from benchmark.loaders.scans import ScanSequence

    bad = write_scan_folder(tmp_path / "bad", frames=lambda i: person(1) if i == 7 else person(seed=i))
    with pytest.raises(ValueError, match=r"frame_0007\.npz: the frame has 1 point"):
        ScanSequence(bad)
    ScanSequence(bad, check=False)  # unchecked: frames are read (and checked) on demand
    ms = write_scan_folder(tmp_path / "ms", ts=np.arange(10) * 20.0)
    with pytest.raises(ValueError, match=r"timestamps\.txt: field 'timestamps' gives a frame rate of 0\.05 fps.*"
                                         r"milliseconds.*divide them by 1000"):
        ScanSequence(ms, check=False)


def test_scan_warnings_are_logged_once_per_sequence(tmp_path, caplog):
    from benchmark.loaders.scans import ScanSequence

    lying = write_scan_folder(tmp_path / "lying", frames=lambda i: person(seed=i)[:, [1, 0, 2]])
    with caplog.at_level(logging.WARNING):
        seq = ScanSequence(lying)
        seq.read_frames([0, 1, 2])  # validated: reading does not repeat the warnings
    warnings = plausibility_warnings(caplog)
    assert len(warnings) == 1 and "is the capture z-up?" in warnings[0] and "warnings on 10 frame(s)" in warnings[0]


def test_each_kind_of_scan_warning_is_shown_once(tmp_path, caplog):
    """A 500 m outlier makes one frame both too wide and too far: both warnings are shown (only the
    first was, and it pointed to the up axis), and the frames are counted, not the messages."""
    from benchmark.loaders.scans import ScanSequence

    def frame(i):
        pts = person(seed=i)
        if i == 5:
            pts[0] = [0.0, 0.0, 500.0]
        return pts

    with caplog.at_level(logging.WARNING):
        ScanSequence(write_scan_folder(tmp_path / "outlier", frames=frame))
    warnings = plausibility_warnings(caplog)
    assert len(warnings) == 2 and all("frame_0005" in w for w in warnings), warnings
    assert not any("frame(s)" in w for w in warnings)  # one frame: no count


def test_missing_timestamps_name_a_fix_for_the_command_in_use(tmp_path):
    from benchmark.loaders.scans import ScanSequence

    folder = write_scan_folder(tmp_path / "s")
    (folder / "timestamps.txt").unlink()
    with pytest.raises(ValueError) as run_error:
        ScanSequence(folder)
    assert "timestamps.txt" in str(run_error.value) and "--fps" not in str(run_error.value)
    with pytest.raises(ValueError, match=r"or give the capture rate with --capture-fps \(e\.g\. --capture-fps 50\)"):
        ScanSequence(folder, rate_flag="--capture-fps")


def test_the_scan_folder_loader_checks_time_and_points(tmp_path):
    from benchmark.loaders.scans import load_scan_folder

    with pytest.raises(ValueError, match=r"milliseconds"):
        load_scan_folder(write_scan_folder(tmp_path / "ms", ts=np.arange(10) * 20.0))
    with pytest.raises(ValueError, match=r"frame_0003\.npz: the frame has 2 point"):
        load_scan_folder(write_scan_folder(tmp_path / "two", frames=lambda i: person(2 if i == 3 else 300)))


def test_a_truncated_ascii_ply_is_refused_though_trimesh_reads_it(tmp_path):
    import trimesh

    from benchmark.loaders.scans import read_scan_frame

    text = trimesh.exchange.ply.export_ply(trimesh.PointCloud(person(50)), encoding="ascii").decode()
    cut = "\n".join(text.splitlines()[:-20]) + "\n"  # 20 vertex lines fewer than the header says
    (tmp_path / "cut.ply").write_text(cut)
    with pytest.raises(ValueError, match=r"cut\.ply: the PLY header declares 50 vertices but the file holds 30"):
        read_scan_frame(tmp_path / "cut.ply")
    (tmp_path / "full.ply").write_text(text)
    assert read_scan_frame(tmp_path / "full.ply").shape == (50, 3)
    (tmp_path / "empty.ply").write_bytes(b"")
    with pytest.raises(ValueError, match=r"empty\.ply: the file is empty"):
        read_scan_frame(tmp_path / "empty.ply")


# ------------------------------------------------------------------------------------------------ shape
ANNY = dict(body_name="anny", body_family="anny", shape_dim=6)
SMPL = dict(body_name="smpl-neutral", body_family="smpl", shape_dim=10)


def test_shape_of_the_bodys_length_passes_silently(caplog):
    with caplog.at_level(logging.WARNING):
        assert P.check_shape(np.full(6, 0.5), "f.npz", **ANNY) == []
        assert P.check_shape(np.ones(10), "f.npz", **SMPL) == []
        assert P.check_shape(np.ones(5), "f.npz", **SMPL) == []  # padded with zeros: the mean shape
        assert P.check_shape(np.ones(16), "f.npz", **SMPL) == []  # AMASS's 16 betas: the documented cut
    assert plausibility_warnings(caplog) == []


@pytest.mark.parametrize("n, body", [(300, ANNY), (7, ANNY), (300, SMPL), (17, SMPL)])
def test_a_longer_shape_with_nonzero_extra_values_is_refused(n, body):
    with pytest.raises(ValueError, match=rf"f\.npz: field 'shape' has {n} values, body '{body['body_name']}' takes "
                                         rf"{body['shape_dim']}, and the {n - body['shape_dim']} .* not zero.*Fix"):
        P.check_shape(np.full(n, 0.5), "f.npz", **body)


def test_a_shorter_shape_of_named_parameters_is_refused():
    with pytest.raises(ValueError, match=r"field 'shape' has 4 values, body 'anny' takes 6 named parameters"):
        P.check_shape(np.full(4, 0.5), "f.npz", **ANNY)


@pytest.mark.parametrize("body", [ANNY, SMPL])
def test_a_longer_shape_whose_extra_values_are_zero_is_a_warning(body, caplog):
    shape = np.concatenate([np.full(body["shape_dim"], 0.5), np.zeros(300 - body["shape_dim"])])
    with caplog.at_level(logging.WARNING):
        warnings = P.check_shape(shape, "f.npz", **body)
    assert len(warnings) == 1 and "are zero and are dropped" in warnings[0]
    assert plausibility_warnings(caplog) == warnings


def test_shape_for_body_checks_and_keeps_plausible_shapes_bit_for_bit():
    from benchmark.core.motion import shape_for_body

    anny = types.SimpleNamespace(name="anny", shape_dim=6)
    smpl = types.SimpleNamespace(name="smpl-neutral", model_type="smpl", shape_dim=10)
    m = motion(shape=torch.rand(6), body="anny")
    assert torch.equal(shape_for_body(m, anny).shape, m.shape)
    betas = motion(shape=torch.randn(16), body="smpl")
    assert torch.equal(shape_for_body(betas, smpl).shape, betas.shape[:10])
    short = motion(shape=torch.randn(8), body="smpl")
    assert torch.equal(shape_for_body(short, smpl).shape, torch.cat([short.shape, torch.zeros(2)]))
    # SMPL, SMPL-H and SMPL-X each have their own shape space: another kind's betas give the neutral shape
    for src in ("smplh", "smplx"):
        moved = shape_for_body(motion(shape=torch.randn(16), body=src), smpl)
        assert moved.shape is None and moved.body is None
    with pytest.raises(ValueError, match=r"data/a\.npz: field 'shape' has 300 values"):
        shape_for_body(motion(shape=torch.rand(300), body="anny"), anny, "data/a.npz")
    other = shape_for_body(motion(shape=torch.rand(300), body="anny"), smpl)  # another body's: neutral, as before
    assert other.shape is None and other.body is None


# ------------------------------------------------------------------------------------------------ normal data
def test_the_synthetic_test_split_passes_every_check_silently(tmp_path, caplog):
    from benchmark.core.motion import shape_for_body
    from benchmark.synthetic.splits import build_split

    anny = types.SimpleNamespace(name="anny", shape_dim=6)
    motions = build_split("test")
    with caplog.at_level(logging.WARNING):
        for m in motions:
            assert P.check_motion(m, m.source) == []
            assert torch.equal(shape_for_body(m, anny, m.source).shape, m.shape)
        again = Motion.load(motions[0].save(tmp_path / "m.npz"))
    assert plausibility_warnings(caplog) == []
    assert torch.equal(again.trans, motions[0].trans)


def test_the_loaders_test_fixtures_pass_silently(tmp_path, caplog):
    from test_amass import write_amass

    from benchmark.loaders.amass import load_amass
    from benchmark.loaders.bvh import load_bvh
    from benchmark.loaders.bvh_format import cmu_skeleton, write_bvh
    from benchmark.loaders.scans import ScanSequence

    write_amass(tmp_path / "seq_poses.npz")
    rng = np.random.default_rng(2)
    root = np.cumsum(rng.normal(scale=0.2, size=(25, 3)), axis=0) + [0.0, 17.0, 0.0]
    bvh = write_bvh(tmp_path / "01_01.bvh", cmu_skeleton(), np.tile(np.eye(3), (25, 31, 1, 1)), root, 1 / 120)
    with caplog.at_level(logging.WARNING):
        load_amass(tmp_path / "seq_poses.npz")
        load_bvh(bvh)
        ScanSequence(write_scan_folder(tmp_path / "scans"))
    assert plausibility_warnings(caplog) == []
