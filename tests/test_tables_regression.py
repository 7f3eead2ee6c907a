"""Regression: re-run the smoke profile of the sls, denoise, inbetween and reconstruction tables
and compare each with its committed golden (``results/<table>.smoke.json``).

Goldens change only through ``python -m pytest tests/test_tables_regression.py --update-goldens``
(refused under CI). Each table runs its spec's ``default_priors``. Tolerances are in the metrics'
units; every prior of a cell must see the same observation (its fingerprint), and fingerprints that
differ from the golden's are a warning (``goldens.warn_if_inputs_changed``); tolerances are
``goldens.tolerances``.
Timing columns (``time_per_frame_s``; version 1: ``s_per_frame``) are measured, machine-dependent, and never compared.
"""

import json
import shutil
from pathlib import Path

import pytest

from benchmark.run.catalog import get_profile, load_table_spec
from benchmark.run.catalog import default_priors
from benchmark.run.table_run import run_table
from benchmark.core.work_units import metric_specs
from goldens import cells_seen_differently, check_or_update

ROOT = Path(__file__).resolve().parents[1]
TABLES = ("sls", "denoise", "inbetween", "reconstruction")
# CI-sized grids: the sls dense cells (100 anchors x 10,000 points) cost minutes on 2 CPU cores, so
# its golden covers three of the eight cells (landmarks only, sparse points, sparse frames), and the
# default suite re-computes one of them (landmarks only: since version 4 every cell runs the limb
# start search over 100 anchors, cheapest where the observation is 16 landmarks); -m slow
# (test_sls_smoke_golden_every_regression_cell) and --update-goldens run all three.
REGRESSION_GRID = {"sls": {"sweep": ["p0", "p100", "f5"]}}
DEFAULT_SUITE_GRID = {"sls": {"sweep": ["p0"]}}


def _smoke_table(name: str, grid: dict | None, out, anny_body) -> tuple[dict, dict]:
    spec = load_table_spec(name)
    if grid is not None:
        spec = {**spec, "grid": grid}
    result = run_table(spec, get_profile("smoke", table=name), priors=default_priors(spec), body=anny_body, device="cpu", seed=0,
                       out_dir=out)
    assert not result["failures"], result["failures"]
    return spec, result["table"]


@pytest.fixture(scope="module", params=TABLES)
def smoke(request, tmp_path_factory, anny_body):
    name = request.param
    grids = REGRESSION_GRID if request.config.getoption("--update-goldens") else {**REGRESSION_GRID, **DEFAULT_SUITE_GRID}
    out = tmp_path_factory.mktemp(f"{name}_smoke")
    spec, table = _smoke_table(name, grids.get(name), out, anny_body)
    yield name, spec, table
    shutil.rmtree(out, ignore_errors=True)


def test_smoke_table_is_well_formed(smoke):
    name, spec, table = smoke
    assert [r["prior"] for r in table["rows"]] == default_priors(spec)
    n_cells = 1
    for values in spec["grid"].values():
        n_cells *= len(values)
    served = 0
    for row in table["rows"]:
        assert len(row["cells"]) == n_cells
        for cell in row["cells"]:
            if cell.get("na_reason"):
                assert isinstance(cell["na_reason"], str) and len(cell["na_reason"]) > 5
                continue
            served += 1
            for m in metric_specs(spec):
                v = cell.get(m["name"])
                assert v is None or v == v, f"{name}/{row['prior']}: {m['name']} is NaN"
    assert served > 0, f"{name}: no prior served any cell"
    # every prior that served a cell saw the same observation
    assert not cells_seen_differently(table), f"{name}: priors saw different observations in a cell"


def test_smoke_table_matches_golden(smoke, update_goldens):
    name, spec, table = smoke
    check_or_update(table, ROOT / "results" / f"{name}.smoke.json", spec, update_goldens, grid=spec["grid"])


@pytest.mark.slow
def test_sls_smoke_golden_every_regression_cell(tmp_path, anny_body):
    """The three sls cells of the golden (the default suite re-computes one)."""
    spec, table = _smoke_table("sls", REGRESSION_GRID["sls"], tmp_path, anny_body)
    check_or_update(table, ROOT / "results" / "sls.smoke.json", spec, False)


@pytest.mark.parametrize("name", TABLES)
def test_committed_default_profile_table_is_consistent(name):
    """The committed default-profile (quick) reference table, where one is committed: every planned
    unit done, rows from the spec's priors, and one observation per cell shared by every prior."""
    path = ROOT / "results" / f"{name}.quick.json"
    if not path.exists():
        pytest.skip(f"no committed default-profile table for {name}")
    table = json.loads(path.read_text())
    spec = load_table_spec(name)
    assert table["table"] == name and table["profile"] == "quick"
    assert (ROOT / "results" / f"{name}.quick.md").exists()
    assert table["counts"]["units_done"] == table["counts"]["units_planned"]
    assert set(r["prior"] for r in table["rows"]) <= set(default_priors(spec))
    for row in table["rows"]:
        for cell in row["cells"]:
            assert not str(cell.get("na_reason") or "").startswith("incomplete"), (row["prior"], cell)
    assert not cells_seen_differently(table)
