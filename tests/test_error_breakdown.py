"""python -m benchmark error-breakdown: the MPJPE split of completion units, on motions with known errors."""

import json

import numpy as np
import pytest

from benchmark.tools.error_breakdown import FIGURES, format_rows, run_breakdown
from benchmark.data.unit_arrays import write_arrays


def _unit(tmp_path, name, fit_trans_offset, offset_frames, arm_bend=0.0, spec_hash="h0"):
    """One unit of 2 sequences x 6 output frames at 30 fps, observed at frames 0 and 3: the fit is the
    ground truth moved by ``fit_trans_offset`` (m, along x) at ``offset_frames`` and with the left
    elbow bent by ``arm_bend`` (rad) everywhere."""
    B, T = 2, 6
    ident = np.zeros((B, T, 22, 4), dtype=np.float32)
    ident[..., 3] = 1.0
    fit = ident.copy()
    if arm_bend:
        fit[:, :, 18] = [0.0, np.sin(arm_bend / 2), 0.0, np.cos(arm_bend / 2)]
    gt_trans = np.zeros((B, T, 3), dtype=np.float32)
    gt_trans[..., 1] = 1.0
    fit_trans = gt_trans.copy()
    fit_trans[:, offset_frames, 0] += fit_trans_offset
    t = np.broadcast_to(np.arange(T, dtype=np.float32) / 30.0, (B, T)).copy()
    arrays = {"format": np.array(1), "spec_hash": np.array(spec_hash), "sequence_ids": np.array(["a", "b"]),
              "t": t, "fit_quat": fit, "fit_trans": fit_trans, "fit_shape": np.full((B, 6), 0.5, np.float32),
              "gt_quat": ident, "gt_trans": gt_trans, "gt_shape": np.full((B, 6), 0.5, np.float32),
              "obs_t": np.broadcast_to(np.array([0.0, 0.1], np.float32), (B, 2)).copy()}
    units = tmp_path / "units"
    units.mkdir(exist_ok=True)
    write_arrays(units / f"{name}.npz", arrays)
    (units / f"{name}.json").write_text(json.dumps({"unit_id": name, "spec_hash": "h0", "prior": name.split("__")[0],
                                                    "cell": {"points": 100, "fps": 10}, "sequence_ids": ["a", "b"]}))


def test_error_breakdown_splits_position_frames_and_parts(tmp_path, anny_body):
    # moved by 10 cm between the observed frames only (frames 1, 2, 4, 5): 10 cm there, 0 at frames 0 and 3
    _unit(tmp_path, "moved__c", 0.1, [1, 2, 4, 5])
    # right pose and place everywhere but a bent left elbow: only the left wrist (and hand) err
    _unit(tmp_path, "bent__c", 0.0, [], arm_bend=1.0)
    rows = {r["prior"]: r for r in run_breakdown(tmp_path, anny_body)}
    moved, bent = rows["moved"], rows["bent"]
    assert moved["sequences"] == 2 and set(FIGURES) <= set(moved)
    assert moved["observed_mm"] == pytest.approx(0.0, abs=1e-3)
    assert moved["between_mm"] == pytest.approx(100.0, abs=1e-2)
    assert moved["mpjpe_mm"] == pytest.approx(100.0 * 4 / 6, abs=1e-2)
    assert moved["pelvis_mm"] == pytest.approx(100.0 * 4 / 6, abs=1e-2)
    assert moved["aligned_mm"] == pytest.approx(0.0, abs=1e-3)
    assert bent["pelvis_mm"] == pytest.approx(0.0, abs=1e-4)
    assert bent["arms_mm"] > 5.0 and bent["legs_mm"] == pytest.approx(0.0, abs=1e-4)
    assert bent["torso_mm"] == pytest.approx(0.0, abs=1e-4)
    assert bent["aligned_mm"] == pytest.approx(bent["mpjpe_mm"], abs=1e-4)
    assert "moved" in format_rows(list(rows.values()))
    assert [r["prior"] for r in run_breakdown(tmp_path, anny_body, priors=["bent"])] == ["bent"]


def test_error_breakdown_refuses_what_it_cannot_read(tmp_path, anny_body):
    with pytest.raises(FileNotFoundError, match="no units/ folder"):
        run_breakdown(tmp_path, anny_body)
    _unit(tmp_path, "stale__c", 0.1, [1], spec_hash="other")
    with pytest.raises(ValueError, match="another specification"):
        run_breakdown(tmp_path, anny_body)
    with pytest.raises(ValueError, match="no completion unit"):
        run_breakdown(tmp_path, anny_body, priors=["absent"])


def test_units_left_out_are_said_never_silent(tmp_path, anny_body):
    """A unit without its arrays is not summed silently away: its cell's row says it was left out
    (a cell with none left gets a row of its own), and a damaged unit file is named."""
    _unit(tmp_path, "moved__b000", 0.1, [1, 2, 4, 5])
    _unit(tmp_path, "moved__b001", 0.1, [1, 2, 4, 5])
    _unit(tmp_path, "gone__b000", 0.1, [1])
    (tmp_path / "units" / "moved__b001.npz").unlink()
    (tmp_path / "units" / "gone__b000.npz").unlink()
    rows = {r["prior"]: r for r in run_breakdown(tmp_path, anny_body)}
    assert rows["moved"]["sequences"] == 2 and rows["moved"]["left_out"] == [("moved__b001.json", "no moved__b001.npz")]
    assert rows["gone"]["sequences"] == 0 and np.isnan(rows["gone"]["mpjpe_mm"])
    text = format_rows(list(rows.values()))
    assert "2 *" in text and "left out: moved__b001.json (no moved__b001.npz); gone__b000.json (no gone__b000.npz)" in text
    (tmp_path / "units" / "moved__b000.json").write_text('{"unit_id": "moved__b0')
    with pytest.raises(ValueError, match=r"moved__b000\.json: not a readable unit result"):
        run_breakdown(tmp_path, anny_body)


def test_a_folder_without_units_is_named_before_the_body_loads(tmp_path, monkeypatch, capsys):
    """error-breakdown used to load the body model (seconds) before finding that the folder has no
    units/; the folder is checked first now, and a missing or file run folder is named as such."""
    import benchmark.body
    from benchmark.cli import main

    def no_body(*a, **k):
        raise AssertionError("the body model loaded before the folder was checked")

    monkeypatch.setattr(benchmark.body, "get_body", no_body)
    for run_dir, message in ((tmp_path, "no units/ folder in"), (tmp_path / "absent", "absent does not exist"),
                             (tmp_path / "t.json", "t.json is a file, not a run folder")):
        if run_dir.suffix == ".json":
            run_dir.write_text("{}")
        assert main(["error-breakdown", str(run_dir)]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: error-breakdown: ") and message in err, err
        assert "AssertionError" not in err and "Traceback" not in err
