"""Table writers: Markdown, CSV, LaTeX and the files, from a derived table."""

import csv
import io
import json

import pytest

from benchmark.run.catalog import load_table_spec
from benchmark.run.table_derive import derive_table
from benchmark.run.csv_format import format_csv
from benchmark.run.writers import format_latex, format_markdown, metric_label, write_table
from fake_units import FakeExecutor, meta, plan, table_spec

NA = "2 s windows cannot hold 100 points"


@pytest.fixture(scope="module")
def table():
    priors = ["vposer-slerp", "my_prior", "hmvae"]
    units = plan(priors=priors)
    ex = FakeExecutor(na=lambda u: NA if u.prior == "hmvae" and u.cell["points"] == 100 else None)
    results = [ex(u) for u in units]
    dropped = next(u.unit_id for u in units if u.prior == "my_prior" and u.cell == {"points": 10000, "fps": 10})
    return derive_table(table_spec(), [r for r in results if r["unit_id"] != dropped], meta(units, priors=priors))


def _cell(table, prior, points, fps):
    row = next(r for r in table["rows"] if r["prior"] == prior)
    return next(c for c in row["cells"] if c["points"] == points and c["fps"] == fps)


def test_markdown_header_columns_arrows_and_footnotes(table):
    md = format_markdown(table)
    lines = md.splitlines()
    assert lines[0] == "# Spatio-temporal completion of point-cloud sequences (Marsot et al. 2022, Table 1)"
    assert "- profile `smoke`, sequences 2, steps 30, batch_sequences 2" in lines
    assert f"- table `table1`, protocol version {load_table_spec('table1')['protocol_version']} (completion)" in lines
    assert "- device `cpu`" in lines and "- seed 0" in lines
    assert any(l.startswith("> **Warning.** Profile `smoke`") and "not comparable to the paper's" in l for l in lines)
    # headline first, each metric its own table, unit and direction in the heading
    headings = [l for l in lines if l.startswith("## ")]
    assert headings == ["## Chamfer (mm) ↓", "## Surface Chamfer (mm) ↓", "## MPJPE (mm) ↓"]
    header = next(l for l in lines if l.startswith("| Prior |"))
    assert header == ("| Prior | 100 pts / 5 fps | 100 pts / 10 fps | 1000 pts / 5 fps | 1000 pts / 10 fps "
                      "| 10000 pts / 5 fps | 10000 pts / 10 fps |")
    c = _cell(table, "vposer-slerp", 100, 5)
    first_row = next(l for l in lines if l.startswith("| vposer-slerp |"))
    lo, hi = c["chamfer_mm_ci95"]
    assert first_row.split(" | ")[1] == f"{c['chamfer_mm']:.1f} [{lo:.1f}, {hi:.1f}]"  # no no-prior row: no mark
    hmvae_row = next(l for l in lines if l.startswith("| hmvae |"))
    assert hmvae_row.count("n/a [^2]") == 2  # footnotes are numbered in reading order
    mine = next(l for l in lines if l.startswith("| my_prior |"))
    assert mine.rstrip(" |").endswith("n/a [^1]") and mine.count("n/a") == 1
    assert "[^1]: incomplete: 1 of 2 units" in lines and f"[^2]: {NA}" in lines
    # paper rows: in the headline table only, labelled as the paper's numbers on its own data
    paper = [l for l in lines if "(paper, own data)" in l]
    assert paper[0] == "| *vposer-slerp (paper, own data)* | *27* | *25* | *24* | *20* | *24* | *20* |"
    assert len(paper) == 4 and lines.index(paper[-1]) < lines.index("## Surface Chamfer (mm) ↓")


def test_full_profile_has_no_warning(table):
    full = dict(table, profile="full", profile_description="")
    assert "Warning" not in format_markdown(full)
    assert "WARNING" not in format_latex(full)


def test_csv_long_format(table):
    rows = list(csv.DictReader(io.StringIO(format_csv(table))))
    assert len(rows) == 3 * 6 * 3  # prior x cell x metric
    assert list(rows[0]) == ["table", "protocol_version", "profile", "prior", "points", "fps", "metric", "unit",
                             "value", "std", "sequences", "frames", "na_reason", "ci95_lo", "ci95_hi",
                             "vs_no_prior_diff", "vs_no_prior_ci95_lo", "vs_no_prior_ci95_hi", "vs_no_prior_significant",
                             "vs_no_prior_better", "best_prior", "vs_best_diff", "vs_best_ci95_lo", "vs_best_ci95_hi",
                             "vs_best_significant", "vs_best_better"]
    c = _cell(table, "vposer-slerp", 1000, 10)
    row = next(r for r in rows if r["prior"] == "vposer-slerp" and r["points"] == "1000" and r["fps"] == "10"
               and r["metric"] == "mpjpe_mm")
    assert float(row["value"]) == c["mpjpe_mm"] and float(row["std"]) == c["mpjpe_mm_std"]
    assert (row["unit"], int(row["sequences"]), int(row["frames"]), row["na_reason"]) == ("mm", 3, c["frames"], "")
    na = next(r for r in rows if r["prior"] == "hmvae" and r["points"] == "100")
    assert na["value"] == "" and na["na_reason"] == NA


def test_latex_booktabs_headline(table):
    tex = format_latex(table)
    assert r"\begin{tabular}{lrrrrrr}" in tex and tex.rstrip().endswith(r"\end{tabular}")
    for rule in (r"\toprule", r"\midrule", r"\bottomrule"):
        assert rule in tex
    assert r"Chamfer (mm) $\downarrow$" in tex
    assert r"my\_prior & " in tex and "my_prior &" not in tex
    assert r"n/a$^{2}$" in tex and f"$^{{2}}$ {NA}" in tex and r"$^{1}$ incomplete: 1 of 2 units" in tex
    assert r"vposer-slerp & 27 & 25 & 24 & 20 & 24 & 20 \\" in tex
    c = _cell(table, "vposer-slerp", 100, 5)
    lo, hi = c["chamfer_mm_ci95"]
    assert f"vposer-slerp & {c['chamfer_mm']:.1f}{{\\scriptsize\\,[{lo:.1f}, {hi:.1f}]}} & " in tex
    assert "Surface" not in tex  # headline metric only


def test_write_table_files(table, tmp_path):
    paths = write_table(table, tmp_path, stem="table1.smoke")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table1.smoke.csv", "table1.smoke.json", "table1.smoke.md", "table1.smoke.tex"]
    assert json.loads(paths["json"].read_text()) == table
    assert paths["md"].read_text() == format_markdown(table)
    with pytest.raises(ValueError, match="unknown output format"):
        write_table(table, tmp_path, formats=["pdf"])


def test_metric_labels():
    assert metric_label("chamfer_mm") == "Chamfer (mm)"
    assert metric_label("pa_mpjpe_mm") == "PA-MPJPE (mm)"
    assert metric_label("foot_skate_cm") == "Foot skate (cm)"


def test_a_table_read_back_from_json_is_written_as_it_was(table, tmp_path):
    """The JSON lists the grid axes, the profile sizes and the paper's rows sorted; the cells keep the
    grid order, so the columns (points first), the paper rows and the header come out the same."""
    from benchmark.core.work_units import grid_axes

    table = {**table, "paper": {"columns": ["100/5", "1000/10"], "chamfer_mm": {"vposer-slerp": [27, 20], "hmvae": [83, 48]}}}
    paths = write_table(table, tmp_path, formats=("json",))
    back = json.loads(paths["json"].read_text())
    assert list(back["grid"]) == sorted(table["grid"]) != list(table["grid"])  # what JSON does to it
    assert grid_axes(back) == list(table["grid"]) == ["points", "fps"]
    for fmt in (format_markdown, format_csv, format_latex):
        assert fmt(back) == fmt(table)


def test_an_untrained_row_is_marked_in_markdown_and_latex(table):
    """A row whose prior read no weights file (``prior_info[...]["untrained"]``) carries a footnote
    saying it measures no trained prior; the other rows carry none."""
    import copy

    marked = copy.deepcopy(table)
    marked.setdefault("prior_info", {}).setdefault("my_prior", {})["untrained"] = True
    md = format_markdown(marked)
    rows = [l for l in md.splitlines() if l.startswith("| my_prior")]
    assert rows and all(l.startswith("| my_prior [^") for l in rows)
    assert "my_prior read no weights file" in md and "untrained parameters" in md
    assert not any(l.startswith("| vposer-slerp [^") for l in md.splitlines())
    assert "my_prior read no weights file" not in format_markdown(table)
    tex = format_latex(marked)
    assert any(l.startswith(r"my\_prior$^{") for l in tex.splitlines()) and "untrained parameters" in tex
