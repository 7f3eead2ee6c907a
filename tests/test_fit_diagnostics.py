"""Fit diagnostics (benchmark.core.fit_diagnostics): per-sequence figures, cell counts, the Markdown
section and flags, and fit-check's verdicts."""

import math

import numpy as np
import pytest
import torch

from benchmark.tools.fit_check import TARGETS, check_cell
from benchmark.core.fit_diagnostics import (
    BACKWARDS_DEG,
    FLAG,
    cell_diagnostics,
    cell_flagged,
    convergence,
    root_errors,
    sequence_diagnostics,
)


def _yaw(deg):
    a = math.radians(deg)
    return torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]],
                        dtype=torch.float64)


def test_convergence_is_the_relative_decrease_over_the_last_tenth():
    trace = [100.0 - i for i in range(100)]  # 100 -> 1, falling by 1 per step
    # window 10 steps, 2-step means: d0 = mean(d[88:90]) = 11.5, d1 = mean(d[98:100]) = 1.5
    assert convergence(trace) == pytest.approx((11.5 - 1.5) / 11.5)
    assert convergence([5.0] * 50) == 0.0
    assert convergence([10.0, 9.0]) == pytest.approx(0.1)
    assert math.isnan(convergence([3.0]))


def test_sequence_diagnostics_flags_a_backwards_fit_and_an_unconverged_one():
    T = 12
    gt = torch.stack([_yaw(20.0)] * T)[None].repeat(2, 1, 1, 1)  # (2, T, 3, 3)
    fit = torch.stack([torch.stack([_yaw(25.0)] * T), torch.stack([_yaw(20.0 + 170.0)] * T)])
    steps = 50
    flat = torch.full((steps, 1), 12.0)
    falling = torch.linspace(30.0, 15.0, steps)[:, None]
    d = sequence_diagnostics(torch.cat([flat, falling], 1), fit, gt)
    assert d[0]["root_err_deg"] == pytest.approx(5.0, abs=1e-3)
    assert d[0]["facing_err_deg"] == pytest.approx(5.0, abs=1e-3)
    assert not d[0]["backwards"] and d[0]["converged"] and d[0]["final_data_mm"] == 12.0
    assert d[1]["facing_err_deg"] == pytest.approx(170.0, abs=1e-3) and d[1]["backwards"]
    assert not d[1]["converged"] and d[1]["data_decrease_last10"] > 0.01
    # no ground truth (captured scans): the data-term figures only
    d = sequence_diagnostics(flat, None, None)
    assert "backwards" not in d[0] and d[0]["converged"]


def test_root_errors_separate_tilt_from_facing():
    gt = np.eye(3)[None]
    tilt = np.array([[[1.0, 0.0, 0.0], [0.0, math.cos(0.3), -math.sin(0.3)], [0.0, math.sin(0.3), math.cos(0.3)]]])
    root, facing = root_errors(tilt, gt)
    assert root[0] == pytest.approx(math.degrees(0.3)) and facing[0] == pytest.approx(0.0, abs=1e-6)
    root, facing = root_errors(_yaw(180.0).numpy()[None], gt)
    assert facing[0] == pytest.approx(180.0) and facing[0] > BACKWARDS_DEG


def _row(backwards=False, converged=True, root=5.0):
    return {"id": "s", "frames": 3, "sums": {"x_m": 1.0},
            "diagnostics": {"root_err_deg": root, "facing_err_deg": 170.0 if backwards else root, "backwards": backwards,
                            "final_data_mm": 10.0, "data_decrease_last10": 0.0 if converged else 0.2,
                            "converged": converged}}


def test_cell_diagnostics_count_and_flag():
    d = cell_diagnostics([_row(), _row(backwards=True, root=170.0), _row(converged=False)])
    assert d["sequences"] == 3 and d["backwards"] == 1 and d["not_converged"] == 1 and d["misoriented"] == 1
    assert d["root_err_deg_max"] == 170.0 and d["root_err_deg"] == pytest.approx((5 + 170 + 5) / 3)
    assert cell_flagged(d)
    assert not cell_flagged(cell_diagnostics([_row(), _row()]))
    assert cell_diagnostics([{"id": "s", "frames": 1, "sums": {}}]) is None
    upside_down = _row(root=176.0)  # facing the right way, root turned over: misoriented, not backwards
    d = cell_diagnostics([upside_down])
    assert d["backwards"] == 0 and d["misoriented"] == 1 and cell_flagged(d)


def test_markdown_marks_flagged_cells_and_lists_diagnostics():
    from benchmark.run.writers import format_markdown

    good, bad = cell_diagnostics([_row()]), cell_diagnostics([_row(backwards=True, root=170.0)])
    cells = [{"points": 100, "chamfer_mm": 20.0, "chamfer_mm_std": 0.0, "diagnostics": good},
             {"points": 1000, "chamfer_mm": 90.0, "chamfer_mm_std": 0.0, "diagnostics": bad}]
    table = {"table": "t", "title": "T", "grid": {"points": [100, 1000]}, "rows": [{"prior": "p", "cells": cells}],
             "metrics": [{"name": "chamfer_mm", "better": "lower"}], "profile": "quick", "protocol_version": 2,
             "device": "cpu", "seed": 0, "provenance": {}}
    md = format_markdown(table)
    assert f"| p | 20.0 ± 0.0 | 90.0 ± 0.0 {FLAG} |" in md
    assert "## Fit diagnostics" in md
    assert "| p | 0/0/1, 5° | **1/0/1, 170°, 1 misoriented** ⚠ |" in md


def test_fit_check_verdicts():
    cell = {"mpjpe_mm": 35.0, "chamfer_mm": 11.0,
            "diagnostics": {"root_err_deg_max": 4.0, "backwards": 0, "not_converged": 0}}
    assert all(ok for *_, ok in check_cell(cell))
    cell["mpjpe_mm"] = 60.0
    failed = [name for name, _, _, ok in check_cell(cell) if not ok]
    assert failed == ["mpjpe_mm"]
    assert set(TARGETS) == {name for name, *_ in check_cell(cell)}
    assert [ok for name, _, _, ok in check_cell({"mpjpe_mm": 1.0}) if name == "backwards"] == [False]  # no diagnostics: fails


def test_a_one_step_fit_has_no_decrease_and_is_not_converged():
    """One step: nothing to judge a decrease by; stored as None (a unit's JSON holds no NaN)."""
    import json

    d = sequence_diagnostics(torch.ones(1, 2))
    assert [x["data_decrease_last10"] for x in d] == [None, None] and not any(x["converged"] for x in d)
    json.dumps(d, allow_nan=False)
    cell = cell_diagnostics([{"diagnostics": x} for x in d])
    assert cell["data_decrease_last10_max"] is None and cell["not_converged"] == 2
