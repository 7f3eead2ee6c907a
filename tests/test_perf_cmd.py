"""`python -m benchmark perf` builds its report (tiny sizes; the timings themselves are not tested)."""

import json

from benchmark.tools.perf import chamfer_compare, format_report


def test_chamfer_compare_and_report(tmp_path):
    rows = chamfer_compare(frames=1, points=(40,), vertices=(60,), repeats=1)
    assert len(rows) == 1
    row = rows[0]
    assert row["loss_max_abs_diff_m"] == 0.0  # the project's loss is the scipy reference's, exactly
    for key in ("loss_project_ms", "loss_ckdtree_ms", "metric_project_ms", "metric_ckdtree_ms", "loss_vs_ckdtree"):
        assert row[key] > 0
    text = format_report({"machine": {"cpu": "x", "cores": 2, "torch": "t", "device": "cpu"}, "chamfer": rows})
    assert "60 x 40" in text and "ratio" in text
    json.dumps(rows)  # the report is JSON-serialisable
