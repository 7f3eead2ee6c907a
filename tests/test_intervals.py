"""Uncertainty in the tables: bootstrap intervals over sequences and paired comparisons
(:mod:`benchmark.core.intervals`), their place in the derived table, and how the writers and the
report show them (intervals, the mark of a significant win over no-prior; old tables unchanged)."""

import copy
import csv
import io
import json

import numpy as np
import pytest

from benchmark.core.intervals import bootstrap_ci, excludes_zero, paired_bootstrap, weighted_mean
from benchmark.core.json_io import canonical_json
from benchmark.core.work_units import stable_seed
from benchmark.report.cells import CellReport
from benchmark.report.plots import error_bars
from benchmark.report.sections import metric_table
from benchmark.run.table_derive import derive_table
from benchmark.run.csv_format import format_csv
from benchmark.run.writers import SIGNIFICANT_MARK, format_latex, format_markdown
from fake_units import FakeExecutor, meta, plan, profile, table_spec

PRIORS = ["no-prior", "vposer-slerp", "hmvae"]
SEQS = [f"s{i}" for i in range(8)]


# ---------------------------------------------------------------- the statistics

def test_bootstrap_ci_covers_the_mean_and_narrows_with_more_sequences():
    sample = np.random.default_rng(1).normal(10.0, 2.0, size=400)
    widths = []
    for n in (16, 400):
        values, weights = sample[:n], np.ones(n)
        lo, hi = bootstrap_ci(values, weights, np.random.default_rng(0))
        assert lo < values.mean() < hi and lo < 10.0 < hi
        # close to the normal approximation 2 * 1.96 * sd / sqrt(n)
        assert hi - lo == pytest.approx(2 * 1.96 * values.std() / np.sqrt(n), rel=0.25)
        widths.append(hi - lo)
    assert widths[1] < widths[0] / 3  # sqrt(400 / 16) = 5


def test_bootstrap_ci_is_of_the_weighted_mean():
    values, weights = np.array([1.0, 1.2, 0.9, 5.0, 5.2, 4.9]), np.array([100, 100, 100, 1, 1, 1])
    lo, hi = bootstrap_ci(values, weights, np.random.default_rng(0))
    assert weighted_mean(values, weights) == pytest.approx(np.dot(values, weights) / weights.sum())
    assert lo < weighted_mean(values, weights) < hi < values.mean()  # the heavy sequences dominate


def test_bootstrap_is_deterministic_for_a_seed():
    values, weights = np.arange(10.0), np.arange(1.0, 11.0)
    a = bootstrap_ci(values, weights, np.random.default_rng(42))
    assert a == bootstrap_ci(values, weights, np.random.default_rng(42))
    assert a != bootstrap_ci(values, weights, np.random.default_rng(43))


@pytest.mark.parametrize("level, z", [(0.95, 1.959964), (0.90, 1.644854)])
def test_bootstrap_ci_takes_the_two_tails_of_the_level(level, z):
    """A sample symmetric about 10: the bootstrap distribution of its mean is symmetric about 10, so
    the percentile interval is too, each half about z * sd / sqrt(n) wide (z the normal quantile of
    (1 + level) / 2). Many resamples make the tails exact to about 1 %. Catches a tail taken at the
    wrong quantile (e.g. the lower one at 1 - level), which the width checks above let through."""
    values = 10.0 + np.linspace(-2.0, 2.0, 21)
    lo, hi = bootstrap_ci(values, np.ones(21), np.random.default_rng(0), n=50_000, level=level)
    half = z * values.std() / np.sqrt(len(values))
    assert 10.0 - lo == pytest.approx(half, rel=0.05)
    assert hi - 10.0 == pytest.approx(half, rel=0.05)


def test_excludes_zero_needs_the_whole_interval_on_one_side():
    """An interval that touches 0 does not exclude it (a paired interval of differences that are all
    <= 0 with some exactly 0 ends at 0): no significance mark."""
    assert not excludes_zero((-1.0, 0.0)) and not excludes_zero((0.0, 1.0)) and not excludes_zero((-1.0, 1.0))
    assert excludes_zero((-1.0, -1e-9)) and excludes_zero((1e-9, 1.0))


def test_paired_interval_excludes_zero_for_a_shift_and_includes_it_for_noise():
    rng = np.random.default_rng(3)
    difficulty = rng.gamma(2.0, 10.0, size=12)  # shared by both cells: hard sequences are hard for both
    weights = rng.integers(30, 120, size=12)
    better = difficulty - 2.0 + rng.normal(0, 0.5, size=12)
    diff, ci = paired_bootstrap(better, difficulty, weights, np.random.default_rng(0))
    assert diff == pytest.approx(weighted_mean(better - difficulty, weights))
    assert ci[1] < 0 and excludes_zero(ci)
    # unpaired, the spread of the difficulty hides the same shift
    assert bootstrap_ci(better, weights, np.random.default_rng(0))[1] > weighted_mean(difficulty, weights)
    noise = difficulty + rng.normal(0, 0.5, size=12)
    _, ci = paired_bootstrap(noise, difficulty, weights, np.random.default_rng(0))
    assert ci[0] < 0 < ci[1] and not excludes_zero(ci)


@pytest.mark.parametrize("call, match", [
    (lambda r: bootstrap_ci([1.0], [1], r), "at least 2 sequences"),
    (lambda r: bootstrap_ci([1.0, float("nan")], [1, 1], r), "finite"),
    (lambda r: bootstrap_ci([1.0, 2.0], [1, 0], r), "weights must be finite and > 0"),
    (lambda r: bootstrap_ci([1.0, 2.0], [1], r), "same length"),
    (lambda r: bootstrap_ci([1.0, 2.0], [1, 1], 0), "numpy.random.Generator"),
    (lambda r: bootstrap_ci([1.0, 2.0], [1, 1], r, n=0), "resamples"),
    (lambda r: bootstrap_ci([1.0, 2.0], [1, 1], r, level=95), "level"),
    (lambda r: paired_bootstrap([1.0, 2.0], [1.0, 2.0, 3.0], [1, 1], r), "same sequences"),
])
def test_bad_input_is_a_clear_error(call, match):
    with pytest.raises(ValueError, match=match):
        call(np.random.default_rng(0))


# ---------------------------------------------------------------- the derived table

def _derive(seqs=SEQS, priors=PRIORS, scale=None):
    """A table of fake units; ``scale``: prior -> factor on its Chamfer sums (a clear shift)."""
    units = plan(priors=priors, seqs=seqs)
    results = [FakeExecutor()(u) for u in units]
    for r in results:
        for row in r["per_sequence"]:
            row["sums"]["chamfer_m"] *= (scale or {}).get(r["prior"], 1.0)
    return derive_table(table_spec(), results, meta(units))


@pytest.fixture(scope="module")
def table():
    return _derive(scale={"hmvae": 0.6})


def _cell(table, prior, j=0):
    return next(r for r in table["rows"] if r["prior"] == prior)["cells"][j]


def test_cells_hold_their_interval_and_the_values_it_came_from(table):
    assert table["bootstrap"]["resamples"] == 2000 and table["bootstrap"]["level"] == 0.95
    assert "bootstrap" in table["interval_definition"] and "paired" in table["paired_definition"]
    cell = _cell(table, "vposer-slerp", 2)
    seqs = cell["per_sequence"]
    assert seqs["id"] == SEQS and len(seqs["frames"]) == 8 and sum(seqs["frames"]) == cell["frames"]
    for m in ("chamfer_mm", "chamfer_surface_mm", "mpjpe_mm"):
        lo, hi = cell[f"{m}_ci95"]
        assert lo < cell[m] < hi
        assert weighted_mean(seqs[m], seqs["frames"]) == pytest.approx(cell[m], rel=1e-12)
        # anyone can recompute it from the JSON and the documented seed rule
        rng = np.random.default_rng(stable_seed("bootstrap", table["seed"], "vposer-slerp",
                                                canonical_json({"points": 1000, "fps": 5}), m))
        assert [lo, hi] == list(bootstrap_ci(seqs[m], seqs["frames"], rng))
    json.dumps(table, allow_nan=False)
    assert _derive(scale={"hmvae": 0.6}) == table  # seeded: the same table every time


def test_paired_comparisons_against_no_prior_and_the_best(table):
    for j in range(6):
        win = _cell(table, "hmvae", j)["paired"]["chamfer_mm"]
        assert set(win) == {"no_prior"}  # hmvae is the cell's best: no comparison with itself
        c = win["no_prior"]
        assert c["vs"] == "no-prior" and c["sequences"] == 8
        assert c["diff"] == pytest.approx(_cell(table, "hmvae", j)["chamfer_mm"] - _cell(table, "no-prior", j)["chamfer_mm"])
        assert c["diff"] < 0 and c["ci95"][1] < 0 and c["significant"] is True and c["better"] is True
        ref = _cell(table, "no-prior", j)["paired"]["chamfer_mm"]
        assert set(ref) == {"best"} and ref["best"]["vs"] == "hmvae" and ref["best"]["better"] is False
        assert ref["best"]["significant"] is True
    other = _cell(table, "vposer-slerp", 0)["paired"]
    assert set(other["chamfer_mm"]) == {"no_prior", "best"} and other["chamfer_mm"]["best"]["vs"] == "hmvae"
    for m, roles in other.items():
        for c in roles.values():
            assert c["ci95"][0] <= c["diff"] <= c["ci95"][1]
            assert c["significant"] == (c["ci95"][0] > 0 or c["ci95"][1] < 0)
            assert c["better"] == (c["diff"] < 0)  # every metric of table1 is better lower


def test_na_cells_get_no_interval_and_no_comparison():
    units = plan(priors=PRIORS, seqs=SEQS[:4])
    ex = FakeExecutor(na=lambda u: "cannot" if u.prior == "hmvae" and u.cell["points"] == 100 else None)
    table = derive_table(table_spec(), [ex(u) for u in units], meta(units))
    na = _cell(table, "hmvae", 0)
    assert na["na_reason"] == "cannot" and not {"chamfer_mm_ci95", "paired", "per_sequence"} & set(na)
    compared = [c for r in table["rows"] for c in r["cells"][0].get("paired", {}).get("chamfer_mm", {}).values()]
    assert compared and all(c["vs"] != "hmvae" for c in compared)


def test_one_sequence_has_no_interval_but_says_why():
    units = plan(priors=PRIORS, seqs=["s0"], prof=profile(batch_sequences=1))
    table = derive_table(table_spec(), [FakeExecutor()(u) for u in units], meta(units, prof=profile(batch_sequences=1)))
    cell = _cell(table, "vposer-slerp")
    assert cell["chamfer_mm_ci95"] is None and cell["ci_na"]["chamfer_mm"] == "1 sequence: no interval"
    c = cell["paired"]["chamfer_mm"]["no_prior"]
    assert c["ci95"] is None and c["significant"] is None and c["sequences"] == 1 and "no interval" in c["ci_na"]
    md = format_markdown(table)
    row = next(l for l in md.splitlines() if l.startswith("| vposer-slerp |"))
    assert row.split(" | ")[1] == f"{cell['chamfer_mm']:.1f}"  # no interval, no ± 0.0


# ---------------------------------------------------------------- writers and report

def _old(table):
    """The table as derived before the intervals."""
    old = copy.deepcopy(table)
    for key in ("interval_definition", "paired_definition", "bootstrap"):
        del old[key]
    for row in old["rows"]:
        for cell in row["cells"]:
            for key in [k for k in cell if k.endswith("_ci95") or k in ("per_sequence", "paired", "ci_na")]:
                del cell[key]
    return old


def test_markdown_shows_intervals_and_marks_significant_wins(table):
    lines = format_markdown(table).splitlines()
    c = _cell(table, "hmvae")
    lo, hi = c["chamfer_mm_ci95"]
    hmvae = next(l for l in lines if l.startswith("| hmvae |"))
    assert hmvae.split(" | ")[1] == f"{c['chamfer_mm']:.1f} [{lo:.1f}, {hi:.1f}] {SIGNIFICANT_MARK}"
    assert SIGNIFICANT_MARK not in next(l for l in lines if l.startswith("| no-prior |"))
    notes = [l for l in lines if l.startswith("In brackets: the 95% bootstrap interval")]
    assert len(notes) == 3 and f"{SIGNIFICANT_MARK}: better than `no-prior`" in notes[0]
    assert not any(" ± " in l for l in lines if l.startswith("| "))


def test_a_win_the_table_cannot_print_is_not_marked(table):
    """A paired difference that excludes 0 but is under half the last printed digit (two runs of one
    fit differing by float rounding: 57.9003 against 57.9 mm) is a tie on the page: no mark in the
    Markdown, the LaTeX or the report; the JSON keeps the comparison."""
    import copy

    from benchmark.run.writers import significant_win

    t = copy.deepcopy(table)
    c = _cell(t, "hmvae")
    comparison = c["paired"]["chamfer_mm"]["no_prior"]
    assert significant_win(c, "chamfer_mm")
    comparison.update(diff=-0.0003, ci95=[-0.0006, -0.00004])  # still "significant" and "better"
    assert comparison["significant"] is True and not significant_win(c, "chamfer_mm")
    row = next(l for l in format_markdown(t).splitlines() if l.startswith("| hmvae |"))
    assert SIGNIFICANT_MARK not in row.split(" | ")[1]
    assert r"$^\dagger$" not in next(l for l in format_latex(t).splitlines()
                                        if l.startswith("hmvae & ") and "scriptsize" in l).split(" & ")[1]
    comparison.update(diff=-0.05)  # half a printed digit (0.1 mm): shown as a win
    assert significant_win(c, "chamfer_mm")


def test_csv_and_latex_carry_the_interval_and_the_comparisons(table):
    rows = list(csv.DictReader(io.StringIO(format_csv(table))))
    c = _cell(table, "hmvae")
    row = next(r for r in rows if r["prior"] == "hmvae" and r["points"] == "100" and r["fps"] == "5"
               and r["metric"] == "chamfer_mm")
    assert [float(row["ci95_lo"]), float(row["ci95_hi"])] == c["chamfer_mm_ci95"]
    assert float(row["vs_no_prior_diff"]) == c["paired"]["chamfer_mm"]["no_prior"]["diff"]
    assert (row["vs_no_prior_significant"], row["vs_no_prior_better"], row["best_prior"], row["vs_best_diff"]) == (
        "true", "true", "hmvae", "")
    ref = next(r for r in rows if r["prior"] == "no-prior" and r["points"] == "100" and r["fps"] == "5"
               and r["metric"] == "chamfer_mm")
    assert ref["vs_no_prior_diff"] == "" and ref["best_prior"] == "hmvae" and ref["vs_best_better"] == "false"
    tex = format_latex(table)
    hmvae = next(l for l in tex.splitlines() if l.startswith("hmvae & ") and "scriptsize" in l)
    assert hmvae.count(r"$^\dagger$") == 6
    assert rf"{c['chamfer_mm']:.1f}{{\scriptsize\,[{c['chamfer_mm_ci95'][0]:.1f}, " in hmvae
    assert r"$^\dagger$ better than no-prior" in tex


def test_tables_without_intervals_are_written_as_before(table):
    old = _old(table)
    md = format_markdown(old)
    c = _cell(old, "hmvae")
    hmvae = next(l for l in md.splitlines() if l.startswith("| hmvae |"))
    assert hmvae.split(" | ")[1] == f"{c['chamfer_mm']:.1f} ± {c['chamfer_mm_std']:.1f}"
    assert SIGNIFICANT_MARK not in md and "In brackets" not in md
    rows = list(csv.DictReader(io.StringIO(format_csv(old))))
    assert rows[0]["ci95_lo"] == "" and rows[0]["vs_no_prior_diff"] == "" and rows[0]["best_prior"] == ""
    tex = format_latex(old)
    assert "dagger" not in tex and "scriptsize" not in tex and f"hmvae & {c['chamfer_mm']:.1f} & " in tex


def test_report_table_and_error_bars(table):
    def reports(t):
        return {(r["prior"], i): CellReport(t["table"], r["prior"], c, f"a{i}", []) for r in t["rows"]
                for i, c in enumerate(r["cells"])}

    grid = list(table["grid"])
    page = metric_table(table, "chamfer_mm", reports(table), grid)
    c = _cell(table, "hmvae")
    assert f"{c['chamfer_mm']:.1f} [{c['chamfer_mm_ci95'][0]:.1f}, {c['chamfer_mm_ci95'][1]:.1f}]" in page
    assert page.count('class="win"') == 6 and "In brackets" in page
    old = _old(table)
    page = metric_table(old, "chamfer_mm", reports(old), grid)
    assert f"{c['chamfer_mm']:.1f} ± {c['chamfer_mm_std']:.1f}" in page and 'class="win"' not in page
    cells = table["rows"][2]["cells"]
    bars = error_bars(cells, "chamfer_mm")
    assert bars.shape == (2, 6)
    assert bars[:, 0] == pytest.approx([c["chamfer_mm"] - c["chamfer_mm_ci95"][0], c["chamfer_mm_ci95"][1] - c["chamfer_mm"]])
    assert error_bars(old["rows"][2]["cells"], "chamfer_mm")[:, 0] == pytest.approx([c["chamfer_mm_std"]] * 2)


# ---------------------------------------------------------------- measured times

def _timed_table():
    """A table with a measured time (``timing: true``): one time per frame per unit, as the denoise
    protocol records it (the batch's seconds shared by its sequences)."""
    spec = table_spec()
    spec["metrics"] = list(spec["metrics"]) + [{"name": "time_per_frame_s", "better": "lower", "timing": True}]
    units = plan(spec=spec, priors=PRIORS, seqs=SEQS[:4])
    results = [FakeExecutor()(u) for u in units]
    per_frame = {"no-prior": 0.2, "vposer-slerp": 0.1, "hmvae": 0.3}
    for r in results:
        for row in r["per_sequence"]:
            row["sums"]["time_per_frame_s"] = per_frame[r["prior"]] * row["frames"]
    return derive_table(spec, results, meta(units))


def test_a_measured_time_gets_no_interval_and_no_significance():
    table = _timed_table()
    cell = _cell(table, "vposer-slerp")
    assert cell["time_per_frame_s"] == pytest.approx(0.1)
    # the batch's one timing repeated per sequence is no sample: no [0.1, 0.1] interval, no †
    assert cell["time_per_frame_s_ci95"] is None and "measured time" in cell["ci_na"]["time_per_frame_s"]
    c = cell["paired"]["time_per_frame_s"]["no_prior"]
    assert c["diff"] == pytest.approx(-0.1) and c["better"] is True
    assert c["ci95"] is None and c["significant"] is None and "measured time" in c["ci_na"]
    assert cell["chamfer_mm_ci95"] is not None  # the other metrics keep theirs
    md = format_markdown(table)
    section = md.split("## Time per frame (s)")[1].split("## ")[0]
    row = next(l for l in section.splitlines() if l.startswith("| vposer-slerp |"))
    assert row.split(" | ")[1] == "0.1" and SIGNIFICANT_MARK not in row
    rows = list(csv.DictReader(io.StringIO(format_csv(table))))
    timed = next(r for r in rows if r["prior"] == "vposer-slerp" and r["metric"] == "time_per_frame_s")
    assert timed["ci95_lo"] == "" and timed["vs_no_prior_significant"] == "" and timed["vs_no_prior_better"] == "true"


# ---------------------------------------------------------------- few sequences

@pytest.mark.parametrize("n", [2, 3, 5])
def test_too_few_sequences_claim_no_significance(n):
    """An interval of n same-sign differences excludes 0 whatever their size (noise does it with
    probability 2 / 2**n): 2 to 5 sequences keep the difference and its interval, never a †."""
    units = plan(priors=PRIORS, seqs=SEQS[:n], prof=profile(batch_sequences=n))
    results = [FakeExecutor()(u) for u in units]
    for r in results:  # hmvae clearly better on every sequence: the interval excludes 0
        for row in r["per_sequence"]:
            row["sums"]["chamfer_m"] *= 0.5 if r["prior"] == "hmvae" else 1.0
    table = derive_table(table_spec(), results, meta(units, prof=profile(batch_sequences=n)))
    c = _cell(table, "hmvae")["paired"]["chamfer_mm"]["no_prior"]
    assert c["sequences"] == n and c["ci95"][1] < 0 and c["better"] is True
    assert c["significant"] is None and f"{n} sequences in common" in c["ci_na"]
    row = next(l for l in format_markdown(table).splitlines() if l.startswith("| hmvae |"))
    assert SIGNIFICANT_MARK not in row and "[" in row  # the interval is shown, the mark is not
    assert next(r for r in csv.DictReader(io.StringIO(format_csv(table)))
                if r["prior"] == "hmvae" and r["metric"] == "chamfer_mm")["vs_no_prior_significant"] == ""


def test_six_sequences_can_be_significant():
    table = _derive(seqs=SEQS[:6], scale={"hmvae": 0.5})
    c = _cell(table, "hmvae")["paired"]["chamfer_mm"]["no_prior"]
    assert c["sequences"] == 6 and c["significant"] is True and "ci_na" not in c


def test_headers_say_the_mean_is_frame_weighted_over_the_scored_frames(table):
    """Markdown and LaTeX say what the derivation averages: a frame-weighted mean over the frames
    the table scores (its spec's scored_frames; test_metric_directions checks inbetween's)."""
    from benchmark.run.writers import averaged_over

    md, tex = format_markdown(table), format_latex(table)
    assert averaged_over(table).startswith("mean over all output frames of all sequences (a frame-weighted mean")
    assert f"Each number: {averaged_over(table)}, then in brackets" in md and averaged_over(table) in tex
    assert "interval of that frame-weighted mean" in md and "6 sequences in common" in md


def test_a_sum_that_overflows_in_reported_units_is_a_clear_error():
    """A finite SI sum (1e307 m) is inf in mm: an error naming the unit, the sequence and the sum,
    not an AttributeError from the standard deviation."""
    units = plan(priors=PRIORS, seqs=SEQS[:2], prof=profile(batch_sequences=2))
    results = [FakeExecutor()(u) for u in units]
    results[0]["per_sequence"][1]["sums"]["chamfer_m"] = 1e307
    with pytest.raises(ValueError, match=rf"result {results[0]['unit_id']}: sequence 's1': sums\['chamfer_m'\] = 1e\+307"):
        derive_table(table_spec(), results, meta(units, prof=profile(batch_sequences=2)))
