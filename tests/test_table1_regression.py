"""Regression: re-run the smoke table1 and compare it with the committed golden.

The golden (results/table1.smoke.json and .md) changes only through
``python -m pytest tests/test_table1_regression.py --update-goldens`` (refused under CI).
Tolerances are in the metrics' units (mm): the smoke fit is short, so small floating-point
differences between machines move it a little; a real change of the protocol, a prior or the
data moves it far more (and changes the fingerprints, which are compared exactly).
"""

import json
import shutil
from pathlib import Path

import pytest

from benchmark.catalog import get_profile, load_table_spec
from benchmark.cli_run import default_priors
from benchmark.compare import compare_tables
from benchmark.protocols.table_run import run_table
from benchmark.writers import write_table

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = ROOT / "results" / "table1.smoke.json"
TOLERANCES = {"chamfer_mm": 1.0, "chamfer_surface_mm": 1.0, "mpjpe_mm": 3.0}
PRIORS = default_priors(load_table_spec("table1"))  # every prior of the table spec


@pytest.fixture(scope="module")
def smoke_table(tmp_path_factory, anny_body):
    out = tmp_path_factory.mktemp("table1_smoke")
    result = run_table(load_table_spec("table1"), get_profile("smoke", table="table1"), priors=PRIORS,
                       body=anny_body, device="cpu", seed=0, out_dir=out)
    assert not result["failures"]
    return result["table"], out


def test_smoke_table_is_complete(smoke_table):
    table, _ = smoke_table
    rows = [r["prior"] for r in table["rows"]]
    assert {"no-prior", "vposer-slerp"} <= set(rows) and set(rows) <= set(PRIORS), rows
    for row in table["rows"]:
        assert len(row["cells"]) == 6
        for cell in row["cells"]:
            assert cell.get("na_reason") is None
            for metric in ("chamfer_mm", "chamfer_surface_mm", "mpjpe_mm"):
                assert 0 < cell[metric] < 1000
            assert cell["chamfer_surface_mm"] <= cell["chamfer_mm"] + 1e-6
            assert cell["frames"] == get_profile("smoke", table="table1")["sequences"] * 120
    # every prior saw the same degraded observation in a cell
    for row in table["rows"][1:]:
        for a, b in zip(table["rows"][0]["cells"], row["cells"]):
            assert a["fingerprint"] == b["fingerprint"]


def test_resume_reuses_every_unit(smoke_table, anny_body):
    table, out = smoke_table
    again = run_table(load_table_spec("table1"), get_profile("smoke", table="table1"), priors=PRIORS,
                      body=anny_body, device="cpu", seed=0, out_dir=out)
    a = [[c["chamfer_mm"] for c in r["cells"]] for r in table["rows"]]
    b = [[c["chamfer_mm"] for c in r["cells"]] for r in again["table"]["rows"]]
    assert a == b


def test_matches_committed_golden(smoke_table, update_goldens):
    table, out = smoke_table
    if update_goldens:
        GOLDEN.parent.mkdir(exist_ok=True)
        write_table(table, GOLDEN.parent, stem="table1.smoke", formats=("json", "md"))
        pytest.skip("goldens rewritten (explicit --update-goldens)")
    if not GOLDEN.exists():
        pytest.fail(f"{GOLDEN} is missing: create it with --update-goldens")
    golden = json.loads(GOLDEN.read_text())
    ok, rows = compare_tables(golden, table, TOLERANCES)
    problems = [r for r in rows if not r.get("ok", True)]
    assert ok, f"smoke table1 differs from the golden beyond tolerance: {problems[:6]}"
    for g_row, n_row in zip(golden["rows"], table["rows"]):
        for g, n in zip(g_row["cells"], n_row["cells"]):
            assert g["fingerprint"] == n["fingerprint"], "the degraded observations changed: regenerate goldens knowingly"
    shutil.rmtree(out, ignore_errors=True)


def test_committed_quick_table_is_complete_and_consistent():
    """The default-profile reference table: every cell filled, provenance recorded, Markdown beside it."""
    path = ROOT / "results" / "table1.quick.json"
    table = json.loads(path.read_text())
    assert table["table"] == "table1" and table["profile"] == "quick"
    assert (ROOT / "results" / "table1.quick.md").exists()
    for key in ("protocol_version", "seed", "device", "provenance", "rows"):
        assert key in table
    rows = [r["prior"] for r in table["rows"]]
    assert {"no-prior", "vposer-slerp"} <= set(rows) and set(rows) <= set(PRIORS), rows
    for row in table["rows"]:
        assert len(row["cells"]) == 6
        for cell in row["cells"]:
            assert cell.get("na_reason") is None and cell["chamfer_mm"] > 0 and cell["fingerprint"]
    # the same cell saw the same observation for every prior
    by_cell = {}
    for row in table["rows"]:
        for cell in row["cells"]:
            by_cell.setdefault((cell["points"], cell["fps"]), set()).add(cell["fingerprint"])
    assert all(len(v) == 1 for v in by_cell.values())
