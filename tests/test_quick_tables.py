"""Regression of the committed default-profile (quick) reference tables, ``results/<table>.quick.json``.

Slow (the quick table1 of protocol v2 takes about an hour on 2 CPU cores with --jobs 2, sls about as long), so behind the ``slow`` marker:
``python -m pytest -m slow tests/test_quick_tables.py`` re-runs every table's quick profile with its
spec's ``default_priors`` and compares it with the committed table; ``--update-goldens`` rewrites
the committed JSON and Markdown instead (refused under CI). Set ``BENCHMARK_RUNS_DIR`` to a folder
to keep the work units there (``<dir>/<table>_quick``): a rerun resumes from them, so an
interrupted regeneration loses nothing, and units made by ``python -m benchmark run <table> --out
<dir>/<table>_quick`` with the same specification are reused. With ``BENCHMARK_REGENERATE_PRIORS=a,b``
only those priors run, and ``--update-goldens`` puts their rows into the committed table
(``goldens.check_or_update``).
"""

import os
from pathlib import Path

import pytest

from benchmark.run.catalog import get_profile, load_table_spec
from benchmark.run.catalog import default_priors
from benchmark.run.backends.local import default_jobs
from benchmark.run.table_run import run_table
from goldens import check_or_update, regenerated_priors

ROOT = Path(__file__).resolve().parents[1]
TABLES = ("table1", "sls", "denoise", "inbetween", "reconstruction")


@pytest.mark.slow
@pytest.mark.parametrize("name", TABLES)
def test_quick_table_matches_committed(name, tmp_path, anny_body, update_goldens):
    runs = os.environ.get("BENCHMARK_RUNS_DIR")
    out = Path(runs) / f"{name}_quick" if runs else tmp_path
    spec = load_table_spec(name)
    golden = ROOT / "results" / f"{name}.quick.json"
    only = regenerated_priors()
    priors = [p for p in default_priors(spec) if p in only] if only else default_priors(spec)
    if only and not priors:
        pytest.skip(f"BENCHMARK_REGENERATE_PRIORS={','.join(only)}: none of {name}'s default priors")
    # one worker process per core, as `python -m benchmark run` (run_table alone runs its units in this process)
    result = run_table(spec, get_profile("quick", table=name), priors=priors, body=anny_body, device="cpu",
                       seed=0, out_dir=out, backend_options={"jobs": default_jobs("cpu")})
    assert not result["failures"], result["failures"]
    check_or_update(result["table"], golden, spec, update_goldens)
