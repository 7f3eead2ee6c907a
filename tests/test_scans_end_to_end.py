"""Captured scans end to end: ``run table1 --data scans=DIR``, ``complete``, ``data make-scans``,
and the errors / warnings for bad scan input (issue 18)."""

from __future__ import annotations

import copy
import json
import logging

import numpy as np
import pytest

from benchmark.loaders.scans import (ScanSequence, find_scan_sequences, parse_scan_data, scan_data_spec,
                                     to_harness_frame)
from benchmark.protocols.scan_completion import ScanCompletionData, load_scan_sequences

RNG = np.random.default_rng(0)


def person(height=1.7, n=400, rng=RNG):
    """A person-sized box of points (metres, y up): 0.45 wide, ``height`` tall, 0.25 deep."""
    return rng.uniform([-0.22, 0.0, -0.125], [0.22, height, 0.125], size=(n, 3))


def write_folder(folder, clouds, timestamps=None, fps=50.0):
    folder.mkdir(parents=True, exist_ok=True)
    for i, c in enumerate(clouds):
        np.savez(folder / f"frame_{i:04d}.npz", points=c)
    ts = np.arange(len(clouds)) / fps if timestamps is None else timestamps
    (folder / "timestamps.txt").write_text("\n".join(f"{t:.6f}" for t in ts) + "\n")
    return folder


def table1_spec(window_s=4.0):
    from benchmark.run.catalog import load_table_spec

    spec = copy.deepcopy(load_table_spec("table1"))
    spec["data"]["window_s"] = window_s
    return spec


# -- bad input: errors and warnings naming the file -----------------------------------------------
def test_millimetres_read_as_metres_is_an_error_naming_the_file_and_the_fix(tmp_path):
    folder = write_folder(tmp_path / "seq", [person() * 1000.0 for _ in range(3)])
    with pytest.raises(ValueError, match=r"frame_0000\.npz.*1,[67]\d\d units tall.*--units mm"):
        ScanSequence(folder)
    seq = ScanSequence(folder, units="mm")
    (pts,) = seq.read_frames([1])
    assert np.ptp(pts[:, 1]) == pytest.approx(1.7, abs=0.01)


def test_a_bad_later_frame_is_an_error_naming_it(tmp_path):
    clouds = [person() for _ in range(3)]
    clouds[2] = np.full((5, 3), np.nan)
    folder = write_folder(tmp_path / "nan", clouds)
    with pytest.raises(ValueError, match=r"frame_0002\.npz.*NaN"):  # every frame is checked at once (issue 33)
        ScanSequence(folder)
    seq = ScanSequence(folder, check=False)  # unchecked: the bad frame is an error on reading
    with pytest.raises(ValueError, match=r"frame_0002\.npz.*NaN"):
        seq.read_frames([0, 1, 2])
    clouds[2] = np.zeros((0, 3))
    with pytest.raises(ValueError, match=r"frame_0002\.npz: the frame has no points"):
        ScanSequence(write_folder(tmp_path / "empty", clouds), check=False).read_frames([2])


def test_mismatched_or_unordered_timestamps_are_errors_naming_the_file(tmp_path):
    clouds = [person() for _ in range(3)]
    with pytest.raises(ValueError, match=r"timestamps\.txt: 2 timestamps for 3 frame files"):
        ScanSequence(write_folder(tmp_path / "a", clouds, timestamps=[0.0, 0.02]))
    with pytest.raises(ValueError, match=r"timestamps\.txt: timestamps must be finite and strictly increasing.*frame_0002"):
        ScanSequence(write_folder(tmp_path / "b", clouds, timestamps=[0.0, 0.02, 0.01]))
    d = write_folder(tmp_path / "d", clouds)
    np.save(d / "frame_0003.npy", clouds[0])  # not a frame format: named when the counts disagree
    (d / "._frame_0001.npz").write_bytes(b"\0\5\26\7")  # macOS metadata twin: never a frame
    (d / "timestamps.txt").write_text("0.0\n0.02\n0.04\n0.06\n")
    with pytest.raises(ValueError, match=r"4 timestamps for 3 frame files.*not frames .*: frame_0003\.npy$"):
        ScanSequence(d)
    c = write_folder(tmp_path / "c", clouds)
    (c / "timestamps.txt").unlink()
    np.save(c / "timestamps.npy", np.array(["0.00s", "0.02s", "0.04s"]))
    with pytest.raises(ValueError, match=r"timestamps\.npy: unreadable timestamps \(could not convert string to float"):
        ScanSequence(c)


def test_gap_in_timestamps_is_a_warning_naming_the_file(tmp_path, caplog):
    clouds = [person() for _ in range(5)]
    with caplog.at_level(logging.WARNING):
        ScanSequence(write_folder(tmp_path / "gap", clouds, timestamps=[0.0, 0.02, 0.04, 0.20, 0.22]))
    assert "timestamps.txt: 1 gap(s)" in caplog.text


def test_z_up_converts_and_a_lying_body_warns_about_the_up_axis(tmp_path, caplog):
    y_up = person()
    z_up = y_up[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])  # (x, -z, y): y-up -> z-up
    assert np.allclose(to_harness_frame(z_up, up="z"), y_up)
    folder = write_folder(tmp_path / "z", [z_up, z_up])
    with caplog.at_level(logging.WARNING):
        with pytest.raises(ValueError, match=r"frame_0000.npz.*--up y\|z"):  # 0.25 m tall along y: not a person
            ScanSequence(folder)
        ScanSequence(folder, up="z")
    lying = y_up[:, [1, 0, 2]] * np.array([0.75, 1.5, 1.0])  # 1.3 m along x, 0.66 m along y
    with caplog.at_level(logging.WARNING):
        ScanSequence(write_folder(tmp_path / "lying", [lying, lying]))
    assert "is the capture z-up? (pass --up z" in caplog.text


def test_short_sequences_are_skipped_with_a_warning_and_none_left_is_an_error(tmp_path, caplog):
    root = tmp_path / "root"
    write_folder(root / "long", [person() for _ in range(31)], fps=50.0)  # 0.6 s of frames
    write_folder(root / "short", [person() for _ in range(10)], fps=50.0)
    spec = table1_spec(window_s=0.6)
    with caplog.at_level(logging.WARNING):
        found = load_scan_sequences(spec, f"scans={root}")
    assert list(found) == ["long"] and "short" in caplog.text and "shorter than the 0.6 s window" in caplog.text
    with pytest.raises(ValueError, match="none of the 2 sequence folder"):
        load_scan_sequences(table1_spec(window_s=4.0), f"scans={root}")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no sequence folders"):
        find_scan_sequences(tmp_path / "empty")


def test_a_sequence_with_a_hole_in_its_window_is_skipped_naming_the_times(tmp_path, caplog):
    """A hole in the timestamps inside the window is not interpolated into ground truth: the sequence
    is left out with a warning naming its timestamps file, the times and the fix (as a motion's hole);
    a hole after the window costs nothing; no usable sequence left is an error saying why."""
    root = tmp_path / "root"
    ts = np.arange(31) / 50.0
    ts[15:] += 0.2  # 0.22 s between frames 14 and 15: 11 x the median 0.02 s
    write_folder(root / "hole", [person() for _ in range(31)], timestamps=ts)
    late = np.arange(41) / 50.0
    late[35:] += 0.2  # after the window's last instant (0.6 - 1/30 s): not read
    write_folder(root / "late", [person() for _ in range(41)], timestamps=late)
    spec = table1_spec(window_s=0.6)
    with caplog.at_level(logging.WARNING):
        found = load_scan_sequences(spec, f"scans={root}")
    assert list(found) == ["late"]
    assert "hole" in caplog.text and "timestamps.txt: frames are missing between 0.280 s and 0.500 s" in caplog.text
    assert "split the capture at the hole" in caplog.text
    import shutil

    shutil.rmtree(root / "late")
    with pytest.raises(ValueError, match=r"none of the 1 sequence folder.*is usable: 0 do not cover.*1 have a hole in it: .*timestamps.txt: frames are missing.*split the capture"):
        load_scan_sequences(spec, f"scans={root}")


def test_data_option_strings():
    assert scan_data_spec("scans=/d", None, None) == "scans=/d"
    spec = scan_data_spec("scans=/d", "z", "mm")
    assert spec == "scans=/d?up=z&units=mm" and parse_scan_data(spec) == (parse_scan_data("scans=/d")[0], {"up": "z", "units": "mm"})
    with pytest.raises(ValueError, match="--up and --units apply to captured scans only"):
        scan_data_spec(None, "z", None)
    with pytest.raises(ValueError, match="unknown option 'colour=red'"):
        parse_scan_data("scans=/d?colour=red")
    from benchmark.data.table_data import load_motions

    with pytest.raises(ValueError, match="completion protocol"):
        load_motions("scans=/d", 4.0)


def test_ground_truth_between_capture_frames_is_the_interpolated_nearest_frame(tmp_path):
    """A plane moving along its normal at 1 m/s, captured at 50 fps (not a multiple of 30): the
    ground truth at each 30 fps instant lies on the plane's position at that instant."""
    g = np.random.default_rng(1)
    ts = np.arange(40) / 50.0
    clouds = []
    for t in ts:
        xy = g.uniform(-0.3, 0.3, size=(500, 2))
        clouds.append(np.column_stack([xy[:, 0], np.full(500, 1.0 + t), xy[:, 1]]))  # y = 1 + t
    clouds = [np.vstack([c, [[0, 0.2, 0], [0, 1.9, 0]]]) for c in clouds]  # two markers make it person-tall
    seq = ScanSequence(write_folder(tmp_path / "plane", clouds, timestamps=ts), check=False)
    spec = table1_spec(window_s=0.7)
    data = ScanCompletionData(spec, None, {"plane": seq}, seed=0).unit_data(["plane"])
    assert data.gt_joints is None and data.gt_points.shape[:2] == (1, 21)
    assert data.row_extra[0]["gt_time_offset_max_s"] == pytest.approx(1 / 150, abs=1e-9)
    t_out = np.arange(21) / 30.0
    plane = data.gt_points[0].numpy()
    on_plane = np.abs(plane[..., 0]) <= 0.3  # the plane points (the markers are at x = 0 too: keep by y)
    y = plane[..., 1]
    for k in range(21):
        yk = y[k][(y[k] > 0.5) & (y[k] < 1.8) & on_plane[k]]
        assert np.allclose(yk, 1.0 + t_out[k], atol=1e-5), k


# -- the scan path against the synthetic one --------------------------------------------------------
def run_both(tmp_path, anny_body, spec, steps, prior="no-prior", surface_points=None):
    from benchmark.run.catalog import get_profile
    from benchmark.run.table_run import run_table
    from benchmark.synthetic.scan_set import make_scan_set

    profile = dict(get_profile("smoke", "table1"))
    profile["steps"] = steps
    if surface_points is not None:
        profile["surface_points"] = surface_points
    make_scan_set(tmp_path / "scans", sequences=1, body=anny_body, table_capture=0, table_spec=spec)
    syn = run_table(spec, profile, [prior], anny_body, "cpu", 0, tmp_path / "syn", resume="never")
    scan = run_table(spec, profile, [prior], anny_body, "cpu", 0, tmp_path / "scan", resume="never",
                     data=f"scans={tmp_path / 'scans'}")
    return syn["table"]["rows"][0]["cells"], scan["table"]["rows"][0]["cells"]


def check_same_chamfer(syn_cells, scan_cells):
    for a, b in zip(syn_cells, scan_cells):
        assert (a["points"], a["fps"]) == (b["points"], b["fps"])
        assert a["fingerprint"] == b["fingerprint"], "the scan path must see the very observation of the synthetic run"
        assert abs(a["chamfer_mm"] - b["chamfer_mm"]) <= 0.5, (a, b)
        assert abs(a["chamfer_surface_mm"] - b["chamfer_surface_mm"]) <= 0.5, (a, b)
        assert a["mpjpe_mm"] is not None
        assert b["mpjpe_mm"] is None and b["metric_na"]["mpjpe_mm"] == "no ground-truth joints"


@pytest.fixture
def one_torch_thread():
    """Both paths on one torch thread. On two threads this test failed on this project's 2-core
    machine on 2026-12-02, at the commit before that day's changes too (0ca3681), while it passed in
    CI; the observation itself came out bit-identical on 1 and 2 threads when built outside the test
    (the cause of the different cell fingerprint is not found yet)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_scans_and_synthetic_give_the_same_chamfer_short_window(tmp_path, anny_body, one_torch_thread):
    spec = table1_spec(window_s=0.6)
    spec["data"]["points_per_frame"] = 3000  # a lighter capture and ground truth: seconds, not minutes
    spec["grid"] = {"points": [1000], "fps": [5]}
    # every ground-truth point in the surface column: its 500-point subset over 18 frames would
    # differ between the two paths' (equally valid) ground-truth samples by about 1 mm
    check_same_chamfer(*run_both(tmp_path, anny_body, spec, steps=10, surface_points="all"))


@pytest.mark.slow
def test_scans_and_synthetic_give_the_same_chamfer_smoke_table(tmp_path, anny_body):
    """The issue's target at the smoke profile: six cells, 20 steps, the 4 s window (minutes)."""
    check_same_chamfer(*run_both(tmp_path, anny_body, table1_spec(), steps=20))


# -- make-scans and complete ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_scan_set(tmp_path_factory, anny_body):
    from benchmark.synthetic.scan_set import make_scan_set

    out = tmp_path_factory.mktemp("scanset")
    (folder,) = make_scan_set(out, sequences=["synthetic:test:0000"], fps=60.0, points=2000, duration=0.5,
                              body=anny_body, units="mm", up="z")
    return folder


def test_make_scans_writes_the_layout_with_holes_noise_and_ground_truth(small_scan_set):
    from benchmark.core.motion import Motion

    seq = ScanSequence(small_scan_set, up="z", units="mm")
    assert len(seq.frames) == 30 and seq.capture_fps == pytest.approx(60.0, rel=1e-4)
    pts = seq.read_frames([0, 29])
    assert [p.shape[0] for p in pts] == [2000, 2000]  # 2,222 sampled, the 10 % nearest one point cut away
    assert 1.4 < np.ptp(pts[0][:, 1]) < 2.1
    truth = Motion.load(small_scan_set / "ground_truth" / "motion.npz")
    assert float(truth.timestamps[0]) == 0.0 and truth.duration == pytest.approx(0.5, abs=0.03)
    assert not any(p.name.startswith("ground_truth") for p in seq.frames)


def test_make_scans_cli_refuses_a_non_empty_folder(tmp_path, capsys):
    from benchmark.cli import main

    (tmp_path / "x").write_text("keep me")
    assert main(["data", "make-scans", "--out", str(tmp_path), "--sequences", "1"]) == 2
    assert "exists and is not empty; pass --force" in capsys.readouterr().err


def test_complete_writes_a_motion_that_data_convert_reads_back_and_meshes(small_scan_set, tmp_path, capsys):
    import trimesh

    from benchmark.cli import main
    from benchmark.loaders.convert import load_motion

    out = tmp_path / "out"
    rc = main(["complete", str(small_scan_set), "--prior", "no-prior", "--out", str(out), "--steps", "2",
               "--profile", "smoke", "--up", "z", "--units", "mm", "--meshes", "--points", "500"])
    text = capsys.readouterr().out
    assert rc == 0, text
    motion = load_motion(out / "motion.npz")
    assert motion.num_frames == 15 and motion.fps == pytest.approx(30.0) and motion.body == "anny"
    assert motion.shape is not None and motion.poses.shape == (15, 22, 3)
    meshes = sorted((out / "meshes").glob("*.ply"))
    assert len(meshes) == 15
    mesh = trimesh.load(meshes[0], process=False)
    assert len(mesh.faces) > 1000 and 1.0 < np.ptp(np.asarray(mesh.vertices)[:, 1]) < 2.2
    diag = json.loads((out / "diagnostics.json").read_text())
    assert [h["step"] for h in diag["history"]] == [0, 1] and "converged" in diag["convergence"]
    assert diag["truth"]["mpjpe_mm"] > 0 and 0 <= diag["truth"]["facing_err_deg_mean"] <= 180
    assert "data term (Chamfer, mm" in text and "facing error" in text and "preview" in text


def test_complete_on_a_motion_file_and_a_bad_input(tmp_path, capsys):
    from benchmark.cli import main
    from benchmark.synthetic.splits import build_split

    motion = build_split("test")[0]
    motion.window(float(motion.timestamps[0]), 0.4).save(tmp_path / "m.npz")
    rc = main(["complete", str(tmp_path / "m.npz"), "--prior", "no-prior", "--out", str(tmp_path / "o"),
               "--steps", "1", "--profile", "smoke", "--points", "200", "--no-preview"])
    text = capsys.readouterr().out
    assert rc == 0 and "MPJPE" in text and (tmp_path / "o" / "motion.npz").is_file()
    assert main(["complete", str(tmp_path / "missing"), "--prior", "no-prior", "--out", str(tmp_path / "p")]) == 2
    assert "no such scan folder or motion file" in capsys.readouterr().err


def test_complete_names_the_option_a_capture_cannot_serve_and_leaves_no_folder(tmp_path, capsys):
    from benchmark.cli import main

    seq = write_folder(tmp_path / "cap", [person() for _ in range(30)], fps=10.0)  # 400 points, 10 fps
    for extra, says in ((["--points", "1000", "--fps", "5"], "--points 1000: the capture holds 400 points"),
                        (["--points", "100", "--fps", "30"], "--fps 30: scan folder")):
        out = tmp_path / "out"
        assert main(["complete", str(seq), "--prior", "no-prior", "--out", str(out), "--steps", "1", "--no-preview",
                     *extra]) == 2
        assert says in capsys.readouterr().err
        assert not out.exists()  # created for the run, which failed before writing: removed


# Issue 11's target for a converged no-prior fit (MPJPE <= 40 mm at 10,000 points / 10 fps). The
# facing search (benchmark.protocols.facing.facing_search, what `complete` uses) turns the
# capture the right way; the schedule that converges the limbs is issue 11's open part, so the
# MPJPE check is an expected failure until it lands (measured: 38-72 mm per sequence at 60 steps).
FITS_MPJPE_TARGET_MM = 40.0


def _complete_no_prior(tmp_path, anny_body):
    """``complete`` with ``no-prior`` on a 4 s, 60 fps make-scans capture (3 mm noise, 10 % holes)
    against its generating motion, at the default (quick) profile."""
    import argparse

    from benchmark.tools.complete import run_complete
    from benchmark.synthetic.scan_set import make_scan_set

    (folder,) = make_scan_set(tmp_path / "scans", sequences=1, body=anny_body)
    args = argparse.Namespace(input=str(folder), prior="no-prior", out=str(tmp_path / "out"), points=None, fps=10.0,
                              window=None, start=0.0, meshes=False, no_preview=True, profile="quick", steps=None,
                              device="cpu", seed=0, size="embedded", weights=None, body="anny", up="y", units="m",
                              capture_fps=None, force=False, facing="search")
    return run_complete(args)


@pytest.mark.slow
def test_complete_faces_the_capture_the_right_way(tmp_path, anny_body):
    diag = _complete_no_prior(tmp_path, anny_body)
    assert diag["truth"]["frames_facing_backwards"] == 0
    assert diag["truth"]["root_orientation_err_deg_mean"] <= 10.0


@pytest.mark.slow
@pytest.mark.xfail(reason="issue 11: the limbs of a 60-step fit from the T-pose stop in local minima (MPJPE 38-72 mm "
                   "per quick sequence at 10,000 points / 10 fps with the facing search)")
def test_complete_no_prior_recovers_the_generating_motion(tmp_path, anny_body):
    diag = _complete_no_prior(tmp_path, anny_body)
    assert diag["truth"]["mpjpe_mm"] <= FITS_MPJPE_TARGET_MM


def test_a_sparse_ground_truth_frame_is_an_error_naming_it_not_a_cut_of_every_frame(tmp_path):
    """Every ground-truth frame of a unit is cut to one size: one frame of 3 points among frames of
    400 cut them all to 3 (Chamfer 33 -> 187 mm on a real capture, with a log line). It is refused,
    naming the sequence and the capture frame."""
    g = np.random.default_rng(2)
    clouds = [person(rng=g) for _ in range(40)]
    clouds[5] = np.array([[0.0, 0.0, 0.0], [0.0, 1.7, 0.0], [0.1, 0.9, 0.0]])
    seq = ScanSequence(write_folder(tmp_path / "sparse", clouds), check=False)
    source = ScanCompletionData(table1_spec(window_s=0.7), None, {"sparse": seq}, seed=0)
    with pytest.raises(ValueError, match=r"scans sparse: capture frame 5 \(t = 0\.100 s\) holds 3 points, under half"):
        source.unit_data(["sparse"])


def test_a_cell_denser_than_the_capture_is_na_not_the_sparser_cell_under_its_label(tmp_path):
    """A 400-point capture cannot give the 1,000- or 10,000-point cells: they were the 400-point cell
    under those labels (identical numbers); they are n/a, with the reason."""
    import types

    from benchmark.protocols.completion_unit import run_completion_unit
    from benchmark.protocols.scan_completion import CellNotServed

    seq = ScanSequence(write_folder(tmp_path / "p400", [person() for _ in range(40)]), check=False)
    source = ScanCompletionData(table1_spec(window_s=0.7), None, {"p400": seq}, seed=0)
    obs, _ = source.observe(["p400"], 100, 10.0, seed=0)
    assert int(obs.lengths.max()) == 100
    with pytest.raises(CellNotServed, match=r"the capture holds 400 points per observed frame .*a cell of 1000 points"):
        source.observe(["p400"], 1000, 10.0, seed=0)
    unit = types.SimpleNamespace(cell={"points": 1000, "fps": 10}, sequence_ids=["p400"], unit_id="u", spec_hash="h",
                                 prior="no-prior")
    result = run_completion_unit(unit, table1_spec(window_s=0.7), {}, None, None, source, "cpu")
    assert result["na_reason"].startswith("the capture holds 400 points") and result["per_sequence"] == []


def test_a_capture_slower_than_the_observed_rate_is_an_error_naming_the_folder(tmp_path):
    seq = ScanSequence(write_folder(tmp_path / "slow", [person() for _ in range(4)], fps=4.0))
    source = ScanCompletionData(table1_spec(window_s=0.8), None, {"slow": seq}, seed=0)
    with pytest.raises(ValueError, match=r"slow: the capture \(4 fps.*no distinct frame for every instant at 5 fps"):
        source.observe(["slow"], 100, 5.0, seed=0)
    obs, offsets = source.observe(["slow"], 100, 2.0, seed=0)  # 2 fps from 4 fps: every other frame
    assert obs.timestamps[0].tolist() == [0.0, 0.5] and offsets == [0.0] and obs.lengths.tolist() == [[100, 100]]


def test_a_sequences_ground_truth_and_score_do_not_depend_on_its_batch(tmp_path, anny_body):
    """Each captured sequence's ground truth is cut to its own smallest frame, by its own seed (scan
    rules revision 2). Before, every frame of a unit was cut to the unit's smallest, by the unit's
    seed: a 1,200-point capture batched with a 300-point one was scored against 300 of its points,
    and its output -> scan distances (nearest of fewer points) grew."""
    import dataclasses

    import torch

    from benchmark.body.base import BodyOutput
    from benchmark.protocols.completion_unit import evaluate
    from benchmark.run.table_run import motion_sha256

    g = np.random.default_rng(5)
    dense = ScanSequence(write_folder(tmp_path / "dense", [person(n=1200, rng=g) for _ in range(40)]), check=False)
    sparse = ScanSequence(write_folder(tmp_path / "sparse", [person(n=300, rng=g) for _ in range(40)]), check=False)
    spec = table1_spec(window_s=0.7)
    alone = ScanCompletionData(spec, None, {"dense": dense}, seed=0).unit_data(["dense"])
    both = ScanCompletionData(spec, None, {"dense": dense, "sparse": sparse}, seed=0).unit_data(["dense", "sparse"])
    assert isinstance(both.gt_points, list) and [tuple(x.shape) for x in both.gt_points] == [(1, 21, 1200, 3), (1, 21, 300, 3)]
    assert alone.gt_points.shape == (1, 21, 1200, 3)
    assert torch.equal(both.gt_points[0], alone.gt_points)  # the same points, in the same order (its own seed)
    rest = anny_body.prepare(anny_body.default_shape(2))
    eye = torch.eye(3).expand(2, 21, 22, 3, 3)
    out = anny_body.skin(rest, eye, torch.zeros(2, 21, 3) + torch.tensor([0.0, 0.9, 0.0]))
    zeros = torch.zeros(2, 21, 22, 3)
    rows = evaluate(anny_body, out, dataclasses.replace(both, gt_joints=zeros), "cpu", surface_points=200)
    one = evaluate(anny_body, BodyOutput(vertices=out.vertices[:1], joints=out.joints[:1]),
                   dataclasses.replace(alone, gt_joints=zeros[:1]), "cpu", surface_points=200)
    assert len(rows) == 2 and rows[0]["sums"] == one[0]["sums"]
    assert motion_sha256(dense) != dense.content_sha256()  # stored capture units of revision 1 are computed again
