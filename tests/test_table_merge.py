"""Replacing one prior's rows of a table with a new run of that prior (benchmark.run.table_merge)."""

import copy
import json

import pytest

from benchmark.run.table_derive import derive_table
from benchmark.run.table_merge import replace_rows
from fake_units import PRIORS, FakeExecutor, meta, plan, table_spec

ALL = ["no-prior", *PRIORS]


def _tables(seqs=("s0", "s1", "s2")):
    """The table of a run of every prior; the same table where hmvae's units were worse (an older
    adapter: every error x 1.5); and a run of hmvae alone (its new row)."""
    units = plan(priors=ALL, seqs=seqs)
    results = [FakeExecutor()(u) for u in units]
    full = derive_table(table_spec(), results, meta(units, priors=ALL))
    old = copy.deepcopy(results)
    for r in old:
        if r["prior"] == "hmvae":
            for row in r["per_sequence"]:
                row["sums"] = {k: 1.5 * v for k, v in row["sums"].items()}
    base = derive_table(table_spec(), old, meta(units, priors=ALL))
    mine = [u for u in units if u.prior == "hmvae"]
    new = derive_table(table_spec(), [r for r in results if r["prior"] == "hmvae"], meta(mine, priors=["hmvae"]))
    return full, base, new


def test_a_replaced_row_gives_the_table_of_one_run_with_every_paired_comparison_derived_again():
    full, base, new = _tables()
    assert base["rows"] != full["rows"]
    merged = replace_rows(base, new)
    assert merged["rows"] == full["rows"]  # the row, and every other row's comparisons against it
    assert [r["prior"] for r in merged["rows"]] == ALL
    assert merged["counts"] == full["counts"]
    assert merged["provenance"]["timings"]["fit_s"] == pytest.approx(full["provenance"]["timings"]["fit_s"])
    assert merged["provenance"]["rows_replaced"][0]["priors"] == ["hmvae"]
    assert base["rows"] != full["rows"]  # the base is not changed in place


def test_tables_read_back_from_json_give_the_same_comparisons_cell_by_cell():
    """JSON lists the grid axes sorted; each cell's bootstrap is seeded by its own coordinates (8
    sequences: with 3, every seed gives the same percentiles)."""
    full, base, new = _tables(seqs=[f"s{i}" for i in range(8)])
    back = lambda t: json.loads(json.dumps(t, sort_keys=True))  # noqa: E731
    assert list(back(base)["grid"]) != list(base["grid"])
    assert replace_rows(back(base), back(new))["rows"] == back(full)["rows"]


def test_rows_of_another_protocol_or_test_set_are_refused_naming_the_field():
    full, base, new = _tables()
    for key, value in (("seed", 1), ("sequences", ["s0"]), ("protocol_version", 0)):
        other = {**new, key: value}
        with pytest.raises(ValueError, match=f"NEW.json: field '{key}' differs from BASE.json's"):
            replace_rows(base, other, source="NEW.json", base_source="BASE.json")


def test_merge_rows_command_writes_the_merged_table_and_never_replaces_files_unasked(tmp_path, capsys):
    import json

    from benchmark.cli import main

    full, base, new = _tables()
    (tmp_path / "base.json").write_text(json.dumps(base))
    (tmp_path / "new.json").write_text(json.dumps(new))
    out = tmp_path / "merged"
    args = ["merge-rows", str(tmp_path / "base.json"), str(tmp_path / "new.json"), "--out", str(out)]
    assert main(args) == 0
    merged = json.loads((out / "table1.json").read_text())
    assert merged["rows"] == json.loads(json.dumps(full["rows"]))
    assert (out / "table1.md").exists()
    before = (out / "table1.json").read_text()
    assert main(args) != 0
    assert "exist; choose another --out or --stem, or pass --force" in capsys.readouterr().err
    assert (out / "table1.json").read_text() == before
    assert main(args + ["--force"]) == 0
    (tmp_path / "bad.json").write_text("{}")
    assert main(["merge-rows", str(tmp_path / "bad.json"), str(tmp_path / "new.json"), "--out", str(tmp_path / "o2")]) != 0
    assert "no field 'rows'" in capsys.readouterr().err


def test_a_new_rows_other_observation_fingerprint_is_recorded_cell_by_cell():
    """Another build of the body's cache (another machine) changes the exact hash of an observation
    that is the same to 0.1 micrometre: recorded per cell, not refused."""
    full, base, new = _tables()
    for table in (base, new):  # every prior saw one observation per cell (the fake units hash their prior too)
        for row in table["rows"]:
            for j, cell in enumerate(row["cells"]):
                cell["fingerprint"] = f"{j:064d}"
    assert replace_rows(base, new)["provenance"]["rows_replaced"][0]["observation_fingerprints_differ"] == []
    new["rows"][0]["cells"][2]["fingerprint"] = "f" * 64
    merged = replace_rows(base, new)
    differ = merged["provenance"]["rows_replaced"][0]["observation_fingerprints_differ"]
    cell = new["rows"][0]["cells"][2]
    assert differ == [{"prior": "hmvae", "fps": cell["fps"], "points": cell["points"]}]
    from goldens import cells_seen_differently  # the committed tables' consistency check

    assert cells_seen_differently(merged) == []  # recorded: not a finding
    merged["provenance"]["rows_replaced"][0]["observation_fingerprints_differ"] = []
    assert cells_seen_differently(merged) == [2]


def test_cells_are_matched_by_their_coordinates_never_by_position():
    """A NEW whose row lists its cells in another order (hand-made, or another writer's) merges to
    the same table; a row missing a cell, repeating one or not a row at all is refused by name."""
    full, base, new = _tables()
    shuffled = copy.deepcopy(new)
    shuffled["rows"][0]["cells"].reverse()
    assert replace_rows(base, shuffled)["rows"] == full["rows"]
    short = copy.deepcopy(new)
    short["rows"][0]["cells"].pop()
    with pytest.raises(ValueError, match=r"NEW.json: row 'hmvae' does not hold the grid's cells"):
        replace_rows(base, short, source="NEW.json")
    twice = copy.deepcopy(new)
    twice["rows"][0]["cells"][-1] = copy.deepcopy(twice["rows"][0]["cells"][0])
    with pytest.raises(ValueError, match=r"row 'hmvae' holds the cell .* twice"):
        replace_rows(base, twice, source="NEW.json")
    for bad in ({"cells": []}, {"prior": "hmvae"}, "x"):
        with pytest.raises(ValueError, match=r"NEW.json: row 0 is not a table row"):
            replace_rows(base, {**new, "rows": [bad]}, source="NEW.json")
    text = copy.deepcopy(new)
    text["rows"][0]["cells"][0]["mpjpe_mm"] = "12"
    with pytest.raises(ValueError, match=r"NEW.json: row 'hmvae', cell .*: mpjpe_mm is '12', not a finite number"):
        replace_rows(base, text, source="NEW.json")
    with pytest.raises(ValueError, match=r"NEW.json: holds no row"):
        replace_rows(base, {**new, "rows": []}, source="NEW.json")


def test_merge_rows_never_writes_over_its_inputs_or_outside_out(tmp_path, capsys):
    from pathlib import Path

    from benchmark.cli import main

    res = tmp_path / "res"
    res.mkdir()
    base = res / "table1.smoke.json"
    base.write_text((Path(__file__).resolve().parents[1] / "results" / "table1.smoke.json").read_text())
    before = base.read_bytes()
    cases = (
        (["--out", str(res), "--stem", "table1.smoke", "--force"], "is BASE (and NEW), which this command reads"),
        (["--out", str(tmp_path / "m"), "--stem", "../escaped"], "--stem '../escaped': must be a plain file name"),
        (["--out", str(base)], "is a file, not a folder"),
    )
    for extra, message in cases:
        assert main(["merge-rows", str(base), str(base), *extra]) == 2
        assert message in capsys.readouterr().err
    assert base.read_bytes() == before and not (tmp_path / "escaped.json").exists()
    assert main(["merge-rows", str(base), str(base), "--out", str(tmp_path / "m")]) == 0
    assert (tmp_path / "m" / "table1.json").is_file()
