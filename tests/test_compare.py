"""Comparing two tables: per-cell, per-metric differences against tolerances in the metric's unit."""

import copy
import io
import json

import pytest

from benchmark.tools.compare import compare_tables, default_tolerance, format_report, main_compare, parse_tolerances
from benchmark.run.table_derive import derive_table
from fake_units import FakeExecutor, meta, plan, table_spec


@pytest.fixture(scope="module")
def base():
    units = plan(priors=["p", "q"])
    ex = FakeExecutor(na=lambda u: "cannot serve" if u.prior == "q" and u.cell["points"] == 100 else None)
    return derive_table(table_spec(), [ex(u) for u in units], meta(units))


def _cell(table, prior, points, fps):
    row = next(r for r in table["rows"] if r["prior"] == prior)
    return next(c for c in row["cells"] if c["points"] == points and c["fps"] == fps)


def _failing(rows):
    return [r for r in rows if not r["ok"]]


def test_identical_tables_agree(base):
    ok, rows = compare_tables(base, copy.deepcopy(base))
    assert ok and _failing(rows) == []
    cell_rows = [r for r in rows if r["kind"] == "cell"]
    assert len(cell_rows) == 2 * 6 * 3  # std companions are not compared by default
    assert {r["status"] for r in cell_rows} == {"ok", "both n/a"}
    assert all(r["input"] == "same" for r in cell_rows)


def test_differences_against_default_and_given_tolerances(base):
    b = copy.deepcopy(base)
    _cell(b, "p", 1000, 5)["chamfer_mm"] += 0.3
    _cell(b, "p", 1000, 10)["mpjpe_mm"] -= 0.7
    ok, rows = compare_tables(base, b)
    bad = _failing(rows)
    assert not ok and len(bad) == 1
    assert (bad[0]["prior"], bad[0]["cell"], bad[0]["metric"], bad[0]["status"]) == ("p", {"points": 1000, "fps": 10}, "mpjpe_mm", "out of tolerance")
    assert bad[0]["diff"] == pytest.approx(-0.7) and bad[0]["tol"] == 0.5
    within = next(r for r in rows if r.get("metric") == "chamfer_mm" and r.get("cell") == {"points": 1000, "fps": 5} and r["prior"] == "p")
    assert within["status"] == "ok" and within["diff"] == pytest.approx(0.3)
    ok, _ = compare_tables(base, b, {"mpjpe_mm": 1.0})
    assert ok
    ok, rows = compare_tables(base, b, {"chamfer_mm": 0.1, "mpjpe_mm": 1.0})
    assert not ok and [r["metric"] for r in _failing(rows)] == ["chamfer_mm"]


def test_a_difference_equal_to_the_tolerance_passes(base):
    b = copy.deepcopy(base)
    _cell(b, "p", 100, 5)["chamfer_mm"] += 0.5
    assert compare_tables(base, b)[0]


def test_std_is_compared_only_when_asked(base):
    b = copy.deepcopy(base)
    _cell(b, "p", 100, 5)["chamfer_mm_std"] += 5.0
    assert compare_tables(base, b)[0]
    ok, rows = compare_tables(base, b, {"chamfer_mm_std": 1.0})
    assert not ok and [r["metric"] for r in _failing(rows)] == ["chamfer_mm_std"]


def test_missing_cells_and_na_mismatches(base):
    b = copy.deepcopy(base)
    b["rows"] = [r for r in b["rows"] if r["prior"] != "q"]
    ok, rows = compare_tables(base, b)
    assert not ok and {r["status"] for r in _failing(rows)} == {"missing in B"}
    assert len(_failing(rows)) == 6 * 3
    ok, rows = compare_tables(b, base)
    assert {r["status"] for r in _failing(rows)} == {"missing in A"}

    c = copy.deepcopy(base)
    cell = _cell(c, "p", 100, 10)
    for k in [k for k in cell if k.startswith(("chamfer", "mpjpe"))]:
        del cell[k]
    cell["na_reason"] = "incomplete: 1 of 2 units"
    ok, rows = compare_tables(base, c)
    bad = _failing(rows)
    assert not ok and {r["status"] for r in bad} == {"n/a mismatch"} and len(bad) == 3
    assert bad[0]["note"] == "B: incomplete: 1 of 2 units" and bad[0]["a"] is not None and bad[0]["b"] is None


def test_table_level_mismatch_and_notes(base):
    b = copy.deepcopy(base)
    b["profile"] = "full"
    b["seed"] = 7
    ok, rows = compare_tables(base, b)
    header = {r["field"]: r for r in rows if r["kind"] == "header"}
    assert not ok and header["profile"]["status"] == "mismatch" and header["seed"]["status"] == "note"
    assert header["seed"]["ok"]


def test_changed_input_is_reported_but_does_not_fail(base):
    b = copy.deepcopy(base)
    _cell(b, "p", 100, 5)["fingerprint"] = "f" * 64
    ok, rows = compare_tables(base, b)
    assert ok
    assert {r["input"] for r in rows if r["kind"] == "cell" and r["cell"] == {"points": 100, "fps": 5} and r["prior"] == "p"} == {"changed"}
    assert "1 cell(s) saw a different input" in format_report(ok, rows)


def test_metrics_without_a_tolerance_fail_with_a_hint(base):
    a = copy.deepcopy(base)
    a["metrics"].append({"name": "jitter", "better": "lower", "description": ""})
    for row in a["rows"]:
        for cell in row["cells"]:
            if not cell.get("na_reason"):
                cell["jitter"] = 1.0
    ok, rows = compare_tables(a, copy.deepcopy(a))
    assert not ok and _failing(rows)[0]["status"] == "no tolerance" and "--tol jitter=VALUE" in _failing(rows)[0]["note"]
    assert compare_tables(a, copy.deepcopy(a), {"jitter": 0.0})[0]
    assert default_tolerance("chamfer_mm") == 0.5 and default_tolerance("chamfer_mm_std") is None


@pytest.mark.parametrize("bad, match", [
    ("chamfer_mm", "expected METRIC=VALUE"),
    ("=0.5", "expected METRIC=VALUE"),
    ("chamfer_mm=", "expected METRIC=VALUE"),
    ("chamfer_mm=half", "'half' is not a number"),
    ("chamfer_mm=-1", ">= 0"),
    ("chamfer_mm=nan", "finite"),
])
def test_bad_tolerance_strings(bad, match):
    with pytest.raises(ValueError, match=match):
        parse_tolerances([bad])


def test_parse_tolerances_and_unknown_metric(base):
    assert parse_tolerances(["chamfer_mm=0.25", " mpjpe_mm = 2 "]) == {"chamfer_mm": 0.25, "mpjpe_mm": 2.0}
    with pytest.raises(ValueError, match="given twice"):
        parse_tolerances(["chamfer_mm=1", "chamfer_mm=2"])
    with pytest.raises(ValueError, match=r"unknown metric\(s\) \['chamfer'\]"):
        compare_tables(base, base, {"chamfer": 1.0})


def test_main_compare_exit_codes_and_report(base, tmp_path):
    pa, pb = tmp_path / "a.json", tmp_path / "b.json"
    pa.write_text(json.dumps(base))
    b = copy.deepcopy(base)
    _cell(b, "q", 10000, 10)["chamfer_mm"] += 2.0
    pb.write_text(json.dumps(b))
    out = io.StringIO()
    assert main_compare(pa, pa, [], out=out) == 0
    assert out.getvalue().rstrip().splitlines()[-1].startswith("OK: 36 cell x metric comparisons, 0 failing")
    out = io.StringIO()
    assert main_compare(pa, pb, [], out=out) == 1
    text = out.getvalue()
    fail_line = next(l for l in text.splitlines() if l.startswith("FAIL  "))
    assert "q" in fail_line and "10000 pts / 10 fps" in fail_line and "chamfer_mm" in fail_line and "out of tolerance" in fail_line
    assert "+2.000" in fail_line
    assert text.rstrip().splitlines()[-1].startswith("FAIL: 36 cell x metric comparisons, 1 failing")
    assert main_compare(pa, pb, ["chamfer_mm=2.5"], out=io.StringIO()) == 0
    with pytest.raises(ValueError, match="bad --tol"):
        main_compare(pa, pb, ["chamfer_mm:2"])
    with pytest.raises(FileNotFoundError, match="nope.json"):
        main_compare(pa, tmp_path / "nope.json", [])
    (tmp_path / "x.json").write_text("{}")
    with pytest.raises(ValueError, match="x.json: not a table JSON"):
        main_compare(pa, tmp_path / "x.json", [])


def test_main_compare_only_the_given_priors(base, tmp_path):
    """``compare --prior``: a run of one prior against the whole reference table compares that row
    only; a prior missing from either table is an error naming the file and its rows."""
    pa, pb = tmp_path / "a.json", tmp_path / "b.json"
    pa.write_text(json.dumps(base))
    one = copy.deepcopy(base)
    one["rows"] = [r for r in one["rows"] if r["prior"] == "p"]
    pb.write_text(json.dumps(one))
    assert main_compare(pa, pb, [], out=io.StringIO()) == 1  # q is missing in B
    out = io.StringIO()
    assert main_compare(pa, pb, [], out=out, priors=["p"]) == 0
    assert out.getvalue().rstrip().splitlines()[-1].startswith("OK: 18 cell x metric comparisons, 0 failing")
    with pytest.raises(ValueError, match=r"b.json: no row for --prior q; its rows: p"):
        main_compare(pa, pb, [], priors=["q"])


def test_malformed_tables_are_refused_by_field_never_ok():
    """A second row of one prior (later rows overwrote earlier ones: a conflicting copy passed as OK),
    a repeated cell, a grid axis that is not a list, an unreadable metric_na or an integer no float
    holds: each refused naming the file and the field."""
    units = plan(priors=["p", "q"])
    table = derive_table(table_spec(), [FakeExecutor()(u) for u in units], meta(units))
    dup = copy.deepcopy(table)
    worse = copy.deepcopy(dup["rows"][0])
    for cell in worse["cells"]:
        cell["mpjpe_mm"] += 100.0
    dup["rows"].insert(0, worse)
    with pytest.raises(ValueError, match=r"B.json: rows\[1\]: prior 'p' has two rows"):
        compare_tables(table, dup, labels=("A.json", "B.json"))
    rep = copy.deepcopy(table)
    rep["rows"][0]["cells"][1] = copy.deepcopy(rep["rows"][0]["cells"][0])
    with pytest.raises(ValueError, match=r"cells\[1\] repeats the cell"):
        compare_tables(table, rep, labels=("A.json", "B.json"))
    with pytest.raises(ValueError, match=r"field 'grid' must be an object \(axis -> list of values\)"):
        compare_tables(table, {**table, "grid": {"points": 100}}, labels=("A.json", "B.json"))
    odd = copy.deepcopy(table)
    odd["rows"][0]["cells"][0].update(mpjpe_mm=None, metric_na="x")
    ok, _ = compare_tables(table, odd)
    assert not ok
    big = copy.deepcopy(table)
    big["rows"][0]["cells"][0]["mpjpe_mm"] = 10 ** 400
    with pytest.raises(ValueError, match="not a finite number"):
        compare_tables(table, big)


def test_other_test_sequences_are_reported(base):
    """A run on other sequences averages another test set: within tolerance or not, the report says so."""
    a, b = copy.deepcopy(base), copy.deepcopy(base)
    a["sequences"], b["sequences"] = ["s0", "s1", "s2"], ["s0", "s1", "s9"]
    ok, rows = compare_tables(a, b)
    header = {r["field"]: r for r in rows if r["kind"] == "header"}
    assert ok and header["sequences"]["status"] == "note"
    assert header["sequences"]["a"] == "3 sequences, 1 not in B (s2)" and header["sequences"]["b"] == "3 sequences, 1 not in A (s9)"
    assert "note  sequences differs" in format_report(ok, rows)
    _, rows = compare_tables(a, copy.deepcopy(a))
    assert not [r for r in rows if r["kind"] == "header"]
