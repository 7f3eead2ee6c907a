"""A column that is another cell's observation is fitted once and shown under both names
(benchmark.run.same_cells): sls's f100 is p10000's observation."""

import copy

import pytest
import torch

from benchmark.core.work_units import plan_units, table_rules
from benchmark.protocols import sls_data
from benchmark.run.catalog import load_table_spec
from benchmark.run.same_cells import same_cells
from benchmark.run.table_derive import derive_table
from benchmark.run.table_merge import replace_rows
from benchmark.run.writers import format_latex, format_markdown
from fake_units import FakeExecutor, meta, plan, profile, table_spec

SAME = [{"cell": {"points": 100000}, "as": {"points": 1000}, "why": "every point: the 1000-point observation"}]


def _spec(**changes):
    spec = table_spec()
    spec["grid"] = {"points": [100, 1000]}
    spec["same_cells"] = copy.deepcopy(SAME)
    spec.update(changes)
    return spec


def _table(spec, priors=("no-prior", "hmvae")):
    units = plan(spec, priors=list(priors))
    return units, derive_table(spec, [FakeExecutor()(u) for u in units], meta(units, priors=list(priors)))


def test_a_same_cell_is_not_planned_and_its_column_is_its_source_s_cell():
    units, table = _table(_spec())
    assert sorted({u.cell["points"] for u in units}) == [100, 1000]  # nothing fitted for 100000
    assert table["grid"]["points"] == [100, 1000, 100000] and table["same_cells"] == SAME
    for row in table["rows"]:
        by = {c["points"]: c for c in row["cells"]}
        copy_, source = dict(by[100000]), dict(by[1000])
        assert copy_.pop("same_as") == {"points": 1000} and copy_.pop("units") == 0 and "fit_s" not in copy_
        for key in ("points", "units", "fit_s", "eval_s"):
            copy_.pop(key, None), source.pop(key, None)
        assert copy_ == source  # every metric, interval and paired comparison
    assert table["counts"]["cells"] == 6 and table["counts"]["units_planned"] == len(units)
    assert "column `100000` is column `1000`, fitted once and shown twice" in format_markdown(table)
    assert "100000 is column 1000" in format_latex(table)
    merged = replace_rows(table, _table(_spec(), priors=("hmvae",))[1])
    assert merged["rows"] == table["rows"]


def test_same_cells_enter_no_unit_s_hash():
    spec = _spec()
    plain = copy.deepcopy(spec)
    del plain["same_cells"]
    assert "same_cells" not in table_rules(spec)
    hashes = lambda s: [u.spec_hash for u in plan_units(s, profile(), ["hmvae"], ["s0"], 0, "cpu", {"hmvae": {}})]  # noqa: E731
    assert hashes(spec) == hashes(plain)


@pytest.mark.parametrize("bad, message", [
    ({"grid": {"points": [100, 1000], "fps": [5]}}, "one axis"),
    ({"same_cells": [{"cell": {"points": 1000}, "as": {"points": 100}}]}, "also in grid.points"),
    ({"same_cells": [{"cell": {"fps": 5}, "as": {"points": 100}}]}, "name the grid's axis"),
    ({"same_cells": ["f100"]}, "must be"),
])
def test_bad_same_cells_are_refused_naming_the_field(bad, message):
    with pytest.raises(ValueError, match=message):
        same_cells(_spec(**bad))


def test_sls_f100_is_p10000_s_observation_and_the_protocol_checks_it():
    spec = load_table_spec("sls")
    sls_data.check_same_cells(spec)
    other = copy.deepcopy(spec)
    other["same_cells"] = [{"cell": {"sweep": "f100"}, "as": {"sweep": "p1000"}}]
    with pytest.raises(ValueError, match="'f100' observes 10000 points at 100 anchors, 'p1000' 1000 at 100"):
        sls_data.check_same_cells(other)


def test_p10000_keeps_every_point_of_a_scan_in_its_order():
    """What makes f100 p10000: degrading a 10,000-point scan to 10,000 points returns it unchanged."""
    from benchmark.data.observations import PointCloudSequence
    from benchmark.data.degrade import degrade, fingerprint

    pts = torch.randn(1, 3, 10000, 3)
    pcs = PointCloudSequence(points=pts, lengths=torch.full((1, 3), 10000), timestamps=torch.arange(3.0)[None])
    kept = degrade(pcs, 10000, None, seed=7)
    assert torch.equal(kept.points, pts) and fingerprint(kept) == fingerprint(pcs)


def test_a_bad_same_cells_entry_fails_before_any_unit_runs(tmp_path):
    from benchmark.run.table_run import run_table

    spec = _spec(same_cells=[{"cell": {"points": 1000}, "as": {"points": 100}}])
    with pytest.raises(ValueError, match="also in grid.points"):
        run_table(spec, profile(), ["hmvae"], None, "cpu", 0, tmp_path)
    assert not (tmp_path / "units").exists()

