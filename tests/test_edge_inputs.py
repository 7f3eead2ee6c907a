"""Edge inputs of the commands other than ``run`` (an audit as a user makes them): each fails with
exit code 2 and one line naming the file, the field and the fix, or works where the docs say it does.
"""

from __future__ import annotations

import io
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmark.cli import main

ROOT = Path(__file__).resolve().parents[1]


def cli(argv) -> tuple[int, str]:
    """(exit code, stderr) of ``python -m benchmark ARGV``, in this process."""
    err, buf = sys.stderr, io.StringIO()
    sys.stderr = buf
    try:
        try:
            rc = main([str(a) for a in argv])
        except SystemExit as exc:  # argparse's own usage errors
            rc = exc.code
    finally:
        sys.stderr = err
    return rc, buf.getvalue().strip()


def one_error_line(message: str) -> str:
    lines = [line for line in message.splitlines() if not line.startswith(("INFO ", "WARNING "))]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in message, message
    return lines[0]


# ----------------------------------------------------------------------------------------- report
def _run_folder(tmp: Path, edit) -> Path:
    """A run folder holding the committed smoke table1 JSON, edited by ``edit(table)``."""
    table = json.loads((ROOT / "results" / "table1.smoke.json").read_text())
    edit(table)
    run = tmp / "run"
    run.mkdir()
    (run / "table1.json").write_text(json.dumps(table))
    return run


def _set_metric(t, value):
    t["rows"][0]["cells"][0]["mpjpe_mm"] = value


@pytest.mark.parametrize("edit, expect", [
    (lambda t: t.update(rows="x"), "field 'rows' must be a list"),
    (lambda t: t["rows"][0].pop("cells"), "rows[0] must be an object with 'prior' (a string) and 'cells' (a list)"),
    (lambda t: _set_metric(t, "abc"), "prior 'no-prior', cell 5 fps / 100 pts: metric 'mpjpe_mm' is 'abc', not a finite number"),
    (lambda t: t.update(metrics=[]), "field 'metrics' is empty"),
    (lambda t: t.update(format_version=99), "field 'format_version' is 99"),
    (lambda t: t["rows"][0]["cells"][0].update(mpjpe_mm_ci95="wide"), "mpjpe_mm_ci95 is 'wide', not [low, high]"),
], ids=["rows-not-a-list", "row-without-cells", "metric-a-string", "no-metrics", "future-format", "bad-interval"])
def test_report_names_the_damaged_table_file_and_field(tmp_path, edit, expect):
    """A table JSON edited by hand or written by another tool: the report said ``error: 'cells'``,
    ``TypeError: string indices ...``, ``Unknown format code 'f' ...`` or ``IndexError`` (no file, no
    field), or rendered a future format version without a word; now the file, the field and the fix."""
    run = _run_folder(tmp_path, edit)
    rc, message = cli(["report", run, "--sequences", "0", "--workers", "1"])
    line = one_error_line(message)
    assert rc == 2
    assert str(run / "table1.json") in line and expect in line, line
    assert not (run / "report" / "index.html").exists()


def test_report_of_an_intact_table_still_works(tmp_path):
    run = _run_folder(tmp_path, lambda t: None)
    rc, message = cli(["report", run, "--sequences", "0", "--workers", "1"])
    assert rc == 0, message
    assert (run / "report" / "index.html").is_file()


# ----------------------------------------------------------------------------------- data convert
def _amass(path: Path, **change) -> Path:
    arrays = dict(poses=np.zeros((120, 156)), trans=np.zeros((120, 3)), mocap_framerate=np.array(60.0))
    arrays.update(change)
    arrays = {k: v for k, v in arrays.items() if v is not None}
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize("change, key", [
    (dict(poses=np.full((120, 156), "a")), "poses"),
    (dict(trans=np.full((120, 3), "a")), "trans"),
    (dict(poses=None, root_orient=np.zeros((120, 3)), pose_body=np.full((120, 63), "x")), "pose_body"),
    (dict(poses=np.zeros((120, 156), dtype=np.complex64)), "poses"),
], ids=["poses-strings", "trans-strings", "pose_body-strings", "poses-complex"])
def test_convert_amass_arrays_that_are_not_numbers(tmp_path, change, key):
    """AMASS arrays of strings failed as ``error: could not convert string to float: np.str_('a')``
    (no file, no key); complex poses lost their imaginary part with only numpy's ComplexWarning."""
    src = _amass(tmp_path / "seq_poses.npz", **change)
    rc, message = cli(["data", "convert", src, "--out", tmp_path / "out.npz"])
    line = one_error_line(message)
    assert rc == 2 and f"{src}: key {key!r} holds" in line and "not real numbers" in line, line
    assert not (tmp_path / "out.npz").exists()


# --------------------------------------------------------------------------------------- complete
def _motion(path: Path, frames: int = 120, fps: float = 30.0) -> Path:
    t = np.arange(frames) / fps
    poses = np.zeros((frames, 22, 3), np.float32)
    poses[:, 16, 2] = 0.5 * np.sin(3 * t)
    trans = np.zeros((frames, 3), np.float32)
    trans[:, 0] = 0.5 * t
    np.savez(path, poses=poses, trans=trans, timestamps=t, fps=np.array(fps))
    return path


@pytest.mark.parametrize("device, expect", [
    ("gpu", "--device 'gpu': not a device name; use cpu, cuda or cuda:N"),
    ("tpu:0", "--device 'tpu:0': not a device name"),
    ("cuda", "--device cuda: no CUDA device is available on this machine"),
])
def test_complete_checks_device_first(tmp_path, device, expect):
    """complete's --device went to torch unchecked, after the body and the input had loaded:
    ``RuntimeError: Expected one of cpu, cuda, ipu, ...`` or ``AssertionError: Torch not compiled
    with CUDA enabled``."""
    import torch

    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("CUDA is available here")
    rc, message = cli(["complete", _motion(tmp_path / "m.npz"), "--prior", "no-prior", "--out", tmp_path / "o",
                       "--device", device, "--steps", "1"])
    line = one_error_line(message)
    assert rc == 2 and expect in line, line
    assert not (tmp_path / "o").exists()


def test_complete_a_four_second_30fps_motion(tmp_path, brief_searches):
    """A 120-frame 30 fps motion lasts 4.0 s (Motion.duration), so complete's default window was 4 s,
    but its 50 fps capture needs frames up to 3.98 s and the motion ends at 3.967 s: it failed with
    'motion 0 spans 3.9667 s ... pass a shorter duration or a longer motion' (no file, no option).
    The window is now what the capture can sample: 199 frames at 50 fps, 3.98 s."""
    out = tmp_path / "o"
    rc, message = cli(["complete", _motion(tmp_path / "m.npz"), "--prior", "no-prior", "--out", out, "--steps", "1",
                       "--no-preview", "--device", "cpu"])
    assert rc == 0, message
    motion = np.load(out / "motion.npz")
    assert motion["poses"].shape == (119, 22, 3)  # round(3.98 s x 30 fps)


def test_run_data_skips_a_motion_its_capture_cannot_sample(tmp_path, caplog):
    """``run table1 --data``: a 120-frame 30 fps motion (4.0 s) passed the 'shorter than the window'
    check, then every work unit failed on it in the 50 fps capture; it is skipped with the warning
    (and a folder of only such motions is an error naming the rate and the fix)."""
    from benchmark.protocols.completion_unit import load_motions
    from benchmark.run.catalog import load_table_spec

    spec = load_table_spec("table1")
    data = tmp_path / "data"
    data.mkdir()
    _motion(data / "exactly4s.npz", frames=120)
    with pytest.raises(ValueError, match=r"every motion is shorter than the 4\.0 s window this table needs at 50 fps "
                                         r".*exactly4s\.npz, lasts 4\.00 s: 120 frames over 3\.967 s\).*up to 3\.980 s"):
        load_motions(spec, str(data), None)
    _motion(data / "long.npz", frames=121)
    assert list(load_motions(spec, str(data), None)) == ["long.npz"]
    assert "exactly4s.npz" in caplog.text


def test_data_without_its_subcommand_says_what_it_takes(tmp_path):
    """``python -m benchmark data`` printed the top-level help, which does not list data's commands,
    and exited 2 without a word on what was wrong."""
    rc, message = cli(["data"])
    line = one_error_line(message)
    assert rc == 2 and "data: give a DATA_COMMAND: convert, build, make-scans" in line, line
    rc, message = cli(["data", "convert", tmp_path / "none.npz", "--out", tmp_path / "o.npz"])  # still dispatched
    assert rc == 2 and "none.npz: no such file" in message, message


# ------------------------------------------------------------------------------------------ priors
@pytest.mark.parametrize("prior", ["hmvae", "hmvae-trajectory"])
def test_a_mistyped_hmvae_weights_path_is_named_as_such(tmp_path, prior):
    """``--weights`` naming no file: HM-VAE said 'embedded HM-VAE weights not found: [...]. Train them
    with ...' (the fix for missing embedded weights, not for a mistyped path), unlike the other priors."""
    given = tmp_path / "hmvea.pt"
    rc, message = cli(["describe", prior, "--weights", given])
    line = one_error_line(message)
    assert rc == 2 and f"{prior} weights {given}: no such file; check the path given with --weights" in line, line


def test_convert_a_bvh_of_another_skeleton_names_a_fix_the_command_line_has(tmp_path):
    """A BVH whose joints are not the CMU skeleton's: the error ended 'pass a joint_map for this
    skeleton', which no command takes; it now says which names the commands read and the Python way."""
    from benchmark.loaders.bvh_format import cmu_skeleton, write_bvh

    sk = cmu_skeleton()
    frames = 10
    rot = np.tile(np.eye(3), (frames, len(sk.names), 1, 1))
    src = write_bvh(tmp_path / "take.bvh", sk, rot, np.tile([0.0, 17.0, 0.0], (frames, 1)), frame_time=1 / 120)
    src.write_text(src.read_text().replace("LeftUpLeg", "LeftThigh"))
    rc, message = cli(["data", "convert", src, "--out", tmp_path / "take.npz"])
    line = one_error_line(message)
    assert rc == 2 and "maps to BVH joint 'LeftUpLeg', which the file lacks" in line, line
    assert "name the joints as the CMU skeleton does" in line and "data convert" in line and "joint_map=" in line
