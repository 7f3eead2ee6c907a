"""Metrics judged by their distance to a reference (``better: closest``), reference figures that are
never ranked (``better: none``), a table's own compare tolerance and measured timings (the motion
tables from denoise / inbetween v2, reconstruction v3)."""

import copy
import csv
import io

import pytest

from benchmark.core.work_units import metric_specs
from benchmark.run.table_derive import add_paired
from benchmark.run.writers import direction_text, format_markdown, metric_label
from benchmark.tools.compare import compare_tables

METRICS = [
    {"name": "mpjpe_mm", "better": "lower", "description": ""},
    {"name": "accel_mps2", "better": "closest", "reference": "gt_accel_mps2", "description": ""},
    {"name": "gt_accel_mps2", "better": "none", "description": ""},
]
IDS = ["s0", "s1", "s2", "s3"]


def _cell(mpjpe, accel, gt=(5.0, 6.0, 7.0, 8.0)):
    per = {"id": IDS, "frames": [10] * 4, "mpjpe_mm": list(mpjpe), "accel_mps2": list(accel), "gt_accel_mps2": list(gt)}
    mean = lambda xs: sum(xs) / len(xs)  # noqa: E731
    return {"mpjpe_mm": mean(mpjpe), "accel_mps2": mean(accel), "gt_accel_mps2": mean(gt), "per_sequence": per}


def _rows():
    return [
        {"prior": "no-prior", "cells": [_cell([50, 52, 54, 56], [2.0, 2.5, 3.0, 3.5])]},  # far too smooth
        {"prior": "smooth", "cells": [_cell([40, 41, 42, 43], [1.0, 1.2, 1.4, 1.6])]},  # smoother still
        {"prior": "lively", "cells": [_cell([45, 46, 47, 48], [5.1, 6.2, 6.9, 8.1])]},  # as the ground truth
    ]


def test_closest_is_ranked_by_the_distance_to_its_reference_and_none_is_never_ranked():
    rows = _rows()
    add_paired(rows, [{"gap": 5}], METRICS, table_seed=0)
    cells = {r["prior"]: r["cells"][0] for r in rows}
    # the lowest acceleration is not the best one: the one nearest the ground truth's is
    assert cells["smooth"]["paired"]["accel_mps2"]["best"]["vs"] == "lively"
    assert "best" not in cells["lively"]["paired"]["accel_mps2"]
    lively = cells["lively"]["paired"]["accel_mps2"]["no_prior"]
    assert lively["better"] is True and lively["diff"] < 0  # distance minus distance
    assert lively["ci95"][1] < 0 and lively["significant"] is None  # 4 sequences: too few to claim it
    assert cells["smooth"]["paired"]["accel_mps2"]["no_prior"]["better"] is False
    # plain "lower" metrics are unchanged; the reference column gets no comparison at all
    assert cells["smooth"]["paired"]["mpjpe_mm"]["no_prior"]["better"] is True
    assert all("gt_accel_mps2" not in c.get("paired", {}) for c in cells.values())


def test_metric_specs_check_the_new_fields():
    spec = {"name": "t", "metrics": copy.deepcopy(METRICS) + [{"name": "time_per_frame_s", "timing": True},
                                                             {"name": "quat_loss", "tolerance": 0.005}]}
    specs = {m["name"]: m for m in metric_specs(spec)}
    assert specs["accel_mps2"]["reference"] == "gt_accel_mps2" and specs["time_per_frame_s"]["timing"] is True
    assert specs["quat_loss"]["tolerance"] == 0.005 and "tolerance" not in specs["mpjpe_mm"]
    bad = [({"name": "a", "better": "closest"}, "needs 'reference'"),
           ({"name": "a", "better": "closest", "reference": "a"}, "needs 'reference'"),
           ({"name": "a", "better": "smaller"}, "must be one of lower, higher, closest, none"),
           ({"name": "a", "tolerance": -1}, "'tolerance' must be a number >= 0"),
           ({"name": "a", "timing": "yes"}, "'timing' must be true or false")]
    for entry, message in bad:
        with pytest.raises(ValueError, match=message):
            metric_specs({"name": "t", "metrics": [entry, {"name": "b"}]})


def test_headings_say_how_a_metric_is_judged_and_units_read_as_units():
    assert metric_label("accel_mps2") == "Acceleration (m/s²)"
    assert direction_text(METRICS[0]) == "↓"
    assert direction_text(METRICS[1]) == "(closest to Ground-truth acceleration (m/s²) is best)"
    assert direction_text(METRICS[2]) == "(reference, not ranked)"


def _table(rows, metrics):
    return {"table": "inbetween", "protocol_version": 2, "profile": "smoke", "seed": 0, "device": "cpu",
            "grid": {"gap": [5]}, "metrics": metrics, "rows": rows, "title": "t", "headline_metric": "mpjpe_mm"}


def test_compare_uses_the_tables_tolerance_and_never_fails_on_a_timing():
    metrics = [{"name": "quat_loss", "better": "lower", "tolerance": 0.005},
               {"name": "time_per_frame_s", "better": "lower", "timing": True}]
    row = lambda q, t: [{"prior": "hmvae", "cells": [{"gap": 5, "quat_loss": q, "time_per_frame_s": t}]}]  # noqa: E731
    ok, rows = compare_tables(_table(row(0.500, 0.01), metrics), _table(row(0.504, 0.70), metrics))
    assert ok, [r for r in rows if not r["ok"]]
    timing = next(r for r in rows if r.get("metric") == "time_per_frame_s")
    assert timing["status"] == "note" and "measured time" in timing["note"]
    ok, rows = compare_tables(_table(row(0.500, 0.01), metrics), _table(row(0.510, 0.01), metrics))
    assert not ok and next(r for r in rows if r.get("metric") == "quat_loss")["status"] == "out of tolerance"
    ok, _ = compare_tables(_table(row(0.5, 0.01), metrics), _table(row(0.5, 0.70), metrics),
                           tolerances={"time_per_frame_s": 0.1})  # named by --tol: compared
    assert not ok


def test_markdown_shows_closest_and_reference_headings():
    rows = _rows()
    for r in rows:
        r["cells"][0].update(gap=5, sequences=4, frames=40)
    add_paired(rows, [{"gap": 5}], METRICS, table_seed=0)
    md = format_markdown(_table(rows, METRICS))
    assert "## Acceleration (m/s²) (closest to Ground-truth acceleration (m/s²) is best)" in md
    assert "## Ground-truth acceleration (m/s²) (reference, not ranked)" in md


def test_cells_seen_on_different_observations_are_not_paired():
    """A row merged from a run whose observation differs (its fingerprint) is not compared sequence by
    sequence with the others: a paired difference needs the same observation."""
    rows = _rows()
    for r, fp in zip(rows, ("obs-a", "obs-a", "obs-b")):
        r["cells"][0]["fingerprint"] = fp
    add_paired(rows, [{"gap": 5}], METRICS, table_seed=0)
    cells = {r["prior"]: r["cells"][0] for r in rows}
    assert "no_prior" in cells["smooth"]["paired"]["mpjpe_mm"]
    assert "no_prior" not in cells["lively"].get("paired", {}).get("mpjpe_mm", {})


def test_headers_say_which_frames_a_number_averages():
    """inbetween scores only the missing frames: its spec's scored_frames reaches the table and its
    Markdown and LaTeX headers; a table without it averages every output frame."""
    from benchmark.run.catalog import load_table_spec
    from benchmark.run.writers import format_latex

    rows = _rows()
    for r in rows:
        r["cells"][0].update(gap=5, sequences=4, frames=40)
    table = _table(rows, METRICS)
    assert "mean over all output frames of all sequences" in format_markdown(table)
    table["scored_frames"] = load_table_spec("inbetween")["scored_frames"]
    for text in (format_markdown(table), format_latex(table)):
        assert "mean over the missing frames (the gap) of all sequences" in text
        assert "all output frames" not in text


def test_closest_ranks_by_the_mean_per_sequence_distance_not_the_distance_of_the_means():
    """``better: closest`` ranks what its paired comparisons compare: the frame-weighted mean of
    ``|accel - gt_accel|`` per sequence. A prior too smooth on two sequences and too lively on the
    other two has the ground truth's mean acceleration while being far from it on every sequence."""
    gt = (5.0, 6.0, 7.0, 8.0)
    rows = [
        {"prior": "no-prior", "cells": [_cell([50, 52, 54, 56], [2.0, 2.5, 3.0, 3.5], gt)]},
        {"prior": "swinging", "cells": [_cell([45, 46, 47, 48], [1.0, 2.0, 11.0, 12.0], gt)]},  # mean 6.5 = gt's, 4 away each
        {"prior": "close", "cells": [_cell([45, 46, 47, 48], [5.5, 6.5, 7.5, 8.5], gt)]},  # mean 7.0, 0.5 away each
    ]
    add_paired(rows, [{"gap": 5}], METRICS, table_seed=0)
    cells = {r["prior"]: r["cells"][0] for r in rows}
    assert "best" not in cells["close"]["paired"]["accel_mps2"]
    swinging = cells["swinging"]["paired"]["accel_mps2"]["best"]
    assert swinging["vs"] == "close" and swinging["diff"] == pytest.approx(4.0 - 0.5) and swinging["better"] is False


def test_csv_names_the_best_prior_even_when_no_comparison_against_it_was_made():
    """The best prior's row was merged from another observation (its fingerprint): nobody is paired
    with it, and the CSV must still name it, not whichever row happens to hold a comparison."""
    from benchmark.run.csv_format import format_csv

    rows = _rows()
    for r, fp in zip(rows, ("obs-a", "obs-a", "obs-b")):
        r["cells"][0].update(gap=5, sequences=4, frames=40, fingerprint=fp)
    add_paired(rows, [{"gap": 5}], METRICS, table_seed=0)
    out = list(csv.DictReader(io.StringIO(format_csv(_table(rows, METRICS)))))
    best = {(r["prior"], r["metric"]): r["best_prior"] for r in out}
    assert best[("smooth", "mpjpe_mm")] == "smooth"  # the lowest MPJPE
    assert best[("no-prior", "accel_mps2")] == "lively" and best[("smooth", "accel_mps2")] == "lively"
    assert best[("smooth", "gt_accel_mps2")] == ""  # a reference: never ranked
