"""Regression of the committed default-profile (quick) reference tables, ``results/<table>.quick.json``.

Slow (a full quick table1 takes 1.5-2.5 hours on 2 CPU cores), so behind the ``slow`` marker:
``python -m pytest -m slow tests/test_quick_tables.py`` re-runs every table's quick profile with its
spec's ``default_priors`` and compares it with the committed table; ``--update-goldens`` rewrites
the committed JSON and Markdown instead (refused under CI). Set ``BENCHMARK_RUNS_DIR`` to a folder
to keep the work units there (``<dir>/<table>_quick``): a rerun resumes from them, so an
interrupted regeneration loses nothing, and units made by ``python -m benchmark run <table> --out
<dir>/<table>_quick`` with the same specification are reused.
"""

import json
import os
from pathlib import Path

import pytest

from benchmark.catalog import get_profile, load_table_spec
from benchmark.cli_run import default_priors
from benchmark.compare import compare_tables
from benchmark.protocols.table_run import run_table
from benchmark.writers import write_table
from test_table1_regression import TOLERANCES as TABLE1_TOLERANCES
from test_tables_regression import _tolerances

ROOT = Path(__file__).resolve().parents[1]
TABLES = ("table1", "sls", "denoise", "inbetween", "reconstruction")


@pytest.mark.slow
@pytest.mark.parametrize("name", TABLES)
def test_quick_table_matches_committed(name, tmp_path, anny_body, update_goldens):
    runs = os.environ.get("BENCHMARK_RUNS_DIR")
    out = Path(runs) / f"{name}_quick" if runs else tmp_path
    spec = load_table_spec(name)
    result = run_table(spec, get_profile("quick", table=name), priors=default_priors(spec), body=anny_body, device="cpu",
                       seed=0, out_dir=out)
    assert not result["failures"], result["failures"]
    table = result["table"]
    path = ROOT / "results" / f"{name}.quick.json"
    if update_goldens:
        write_table(table, path.parent, stem=f"{name}.quick", formats=("json", "md"))
        pytest.skip(f"{path} rewritten (explicit --update-goldens)")
    if not path.exists():
        pytest.fail(f"{path} is missing: create it with --update-goldens")
    tol = TABLE1_TOLERANCES if name == "table1" else _tolerances(spec)
    ok, rows = compare_tables(json.loads(path.read_text()), table, tol)
    problems = [r for r in rows if not r.get("ok", True)]
    assert ok, f"quick {name} differs from the committed table beyond tolerance: {problems[:6]}"
