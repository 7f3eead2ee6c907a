"""``python -m benchmark train-report``: curves from the training records."""

import json
import subprocess
import sys

from benchmark.tools.train_report import build_train_report, final_values, histories


def test_histories_and_final_values_are_found_at_any_depth():
    record = {"history": [{"step": 10, "loss": 2.0}], "final_val": {"loss": 1.5},
              "phase2": {"history": [{"step": 5, "loss": 3.0, "val_loss": 3.5}], "final_val": {"loss": 3.1}},
              "vposer_history": [{"step": 1, "loss": 9.0}], "other": [1, 2]}
    assert [p for p, _ in histories(record)] == ["history", "phase2/history", "vposer_history"]
    assert final_values(record, "history") == {"loss": 1.5}
    assert final_values(record, "phase2/history") == {"loss": 3.1}
    assert final_values(record, "vposer_history") == {}


def test_report_of_records(tmp_path):
    w = tmp_path / "weights"
    w.mkdir()
    hist = [{"step": s, "loss": 10.0 / s, "kl": 1.0, "wall_s": s * 0.1, **({"val_loss": 11.0 / s} if s % 20 == 0 else {})}
            for s in range(10, 101, 10)]
    (w / "a.json").write_text(json.dumps({"history": hist, "final_val": {"loss": 0.12}, "steps": 100,
                                          "train_wall_s": 10.0, "checkpoint_bytes": 2_000_000}))
    (w / "b.json").write_text(json.dumps({"steps": 5}))
    page = build_train_report(w, tmp_path / "out")
    text = page.read_text()
    assert (tmp_path / "out" / "img" / "a.png").stat().st_size > 1000
    assert "<td>a</td><td>100</td><td>10</td><td>0.1</td><td>0.12</td><td>2.0</td>" in text
    assert "no loss history in the record" in text


def test_cli_names_a_folder_without_records(tmp_path):
    r = subprocess.run([sys.executable, "-m", "benchmark", "train-report", "--weights-dir", str(tmp_path), "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "no training record" in r.stderr and str(tmp_path) in r.stderr
