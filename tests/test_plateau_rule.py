"""The step rule of table1 protocol v6 (benchmark.protocols.step_rules.PlateauRule,
optimise_to_plateau): a fit stops where its objective has plateaued at the constant learning rate,
a fit still falling cannot pass, and the verdict reaches the per-sequence diagnostics."""

import pytest
import torch

from benchmark.core.fit_diagnostics import cell_diagnostics, cell_flagged, sequence_diagnostics
from benchmark.protocols.step_rules import PlateauRule, optimise, optimise_to_plateau


def _problem(scales, targets=None):
    """B independent 1-D problems: objective_b = 1 + scale_b * (x_b - target_b)^2 from x = 0 (targets: 3)."""
    x = torch.zeros(len(scales), requires_grad=True)
    s = torch.tensor(scales)
    c = torch.tensor(targets or [3.0] * len(scales))
    trace = []

    def step_loss(step):
        f = 1.0 + s * (x - c).square()
        trace.append(f.detach())
        return f.sum(), lambda: {"f": float(f.detach().mean())}

    return x, trace, step_loss


def test_stops_at_the_plateau_then_anneals():
    x, trace, step_loss = _problem([1.0, 1.0])
    rule = PlateauRule(window=20, tolerance=0.005, smoothing=5, check_every=5, anneal_steps=10)
    history, log = optimise_to_plateau("toy", [x], 2000, 0.1, 0.1, step_loss, trace, rule)
    assert log["stopped"] == "plateau" and log["converged"] == [True, True]
    assert log["steps"] == max(log["descent_steps"]) + 10 == len(trace)
    assert max(log["descent_steps"]) < 2000 and x.detach().sub(3.0).abs().max() < 0.1
    assert all(abs(v) <= 0.005 for v in log["plateau_decrease"])
    assert history[-1]["step"] == log["steps"] - 1


def test_a_fit_still_falling_at_the_cap_is_not_converged():
    """A tiny learning rate: the objective falls slowly but steadily; the cap stops it unconverged,
    whereas the versions 1-5 flag (the last 10 % of a cosine schedule) calls the same fit converged."""
    x, trace, step_loss = _problem([1.0, 1.0])
    rule = PlateauRule(window=20, tolerance=0.005, smoothing=5, check_every=5, anneal_steps=10)
    _, log = optimise_to_plateau("toy", [x], 200, 1e-3, 0.1, step_loss, trace, rule)
    assert log["stopped"] == "cap" and log["converged"] == [False, False] and log["steps"] == 200
    assert min(log["plateau_decrease"]) > 0.005

    x2, trace2, step_loss2 = _problem([1.0, 1.0])
    optimise("toy", [x2], 200, 1e-3, 0.01, step_loss2)
    old = sequence_diagnostics(torch.stack(trace2))
    assert all(d["converged"] for d in old)  # the old flag was fooled by the shrunken steps


def test_each_sequence_stops_at_its_own_plateau_and_is_held_there():
    x, trace, step_loss = _problem([1.0, 1.0], [0.5, 10.0])  # Adam's steps are ~lr: the second needs more
    rule = PlateauRule(window=20, tolerance=0.002, smoothing=5, check_every=5, anneal_steps=0)
    _, log = optimise_to_plateau("toy", [x], 5000, 0.05, 0.1, step_loss, trace, rule)
    fast, slow = log["descent_steps"]
    assert log["converged"] == [True, True] and fast < slow == log["steps"]
    values = torch.stack(trace)[:, 0]
    assert torch.all(values[fast:] == values[fast])  # held: the first sequence never moved again
    assert (x.detach() - torch.tensor([0.5, 10.0])).abs().max() < 0.5


def test_variables_that_are_not_batch_first_are_refused():
    x = torch.zeros(3, requires_grad=True)
    trace = []

    def step_loss(step):
        f = (x - 1.0).square().sum()[None].expand(2)  # 2 sequences, one variable of 3 values shared
        trace.append(f.detach())
        return f.sum(), dict

    with pytest.raises(ValueError, match="batch first"):
        optimise_to_plateau("toy", [x], 500, 0.1, 0.1, step_loss, trace, PlateauRule())


def test_a_rising_objective_is_not_a_plateau():
    x = torch.zeros(1, requires_grad=True)
    trace = []

    def step_loss(step):  # the objective rises by 1 % per step whatever the optimiser does
        f = 1.0 + 0.0 * x + 0.01 * step
        trace.append(f.detach())
        return f.sum(), dict

    rule = PlateauRule(window=10, tolerance=0.005, smoothing=2, check_every=1, anneal_steps=0)
    _, log = optimise_to_plateau("toy", [x], 60, 0.1, 0.1, step_loss, trace, rule)
    assert log["stopped"] == "cap" and log["converged"] == [False] and log["plateau_decrease"][0] < -0.005


def test_a_cap_below_the_rule_runs_the_cap_and_flags_every_sequence():
    x, trace, step_loss = _problem([1.0, 2.0])
    _, log = optimise_to_plateau("toy", [x], 20, 0.1, 0.1, step_loss, trace, PlateauRule())
    assert len(trace) == 20 and log["converged"] == [False, False] and log["plateau_decrease"] == [None, None]
    diags = sequence_diagnostics(torch.stack(trace), plateau=log)
    assert [d["converged"] for d in diags] == [False, False] and diags[0]["plateau_decrease"] is None
    cell = cell_diagnostics([{"diagnostics": d} for d in diags])
    assert cell["not_converged"] == 2 and cell["plateau_change_max"] is None and cell_flagged(cell)


def test_diagnostics_carry_the_verdict_and_the_steps():
    trace = torch.ones(120, 2)
    log = {"descent_steps": [100, 70], "steps": 120, "stopped": "plateau", "plateau_decrease": [0.001, -0.02],
           "converged": [True, False]}
    diags = sequence_diagnostics(trace, plateau=log)
    assert [d["converged"] for d in diags] == [True, False]
    assert diags[0]["steps"] == 120 and diags[0]["descent_steps"] == 100
    cell = cell_diagnostics([{"diagnostics": d} for d in diags])
    assert cell["not_converged"] == 1 and cell["plateau_change_max"] == pytest.approx(0.02) and cell["steps_max"] == 120


@pytest.mark.parametrize("bad", [{"windw": 5}, {"window": 0}, {"tolerance": -1}, {"anneal_steps": -1}])
def test_bad_rules_are_refused(bad):
    with pytest.raises(ValueError, match="objective.plateau"):
        PlateauRule.from_spec(bad)


def test_the_floor_makes_the_tolerance_absolute_near_zero():
    """An objective creeping from 0.014 to 0.011 (sls's landmark term, fitted almost exactly by a free
    body) changes by about 20 % relative: not a plateau without the floor; with floor 1, by 0.003 / 1."""
    jitter = [torch.tensor([0.014 - 0.00005 * i, 20.0 - 0.01 * i]) for i in range(60)]
    plain, floored = PlateauRule(), PlateauRule(floor=1.0)
    assert abs(float(plain.decrease(jitter)[0])) > 0.1
    assert abs(float(floored.decrease(jitter)[0])) <= floored.tolerance
    # above the floor it is the relative change, as without one
    assert float(floored.decrease(jitter)[1]) == pytest.approx(float(plain.decrease(jitter)[1]))
    assert PlateauRule.from_spec({"floor": 1}).floor == 1.0
    with pytest.raises(ValueError, match="floor"):
        PlateauRule.from_spec({"floor": -1})


def _l1_problem(targets):
    """B independent 1-D problems with a kink: objective_b = 1 + |x_b - target_b| from x = 0; at a
    constant rate Adam's steps keep jumping across the kink by about the rate."""
    x = torch.zeros(len(targets), requires_grad=True)
    c = torch.tensor(targets)
    trace = []

    def step_loss(step):
        f = 1.0 + (x - c).abs()
        trace.append(f.detach())
        return f.sum(), lambda: {"f": float(f.detach().mean())}

    return x, c, trace, step_loss


def test_reductions_let_each_fit_settle_at_its_own_lower_rate():
    plain = PlateauRule(window=20, tolerance=0.005, smoothing=5, check_every=5, anneal_steps=0)
    reduced = PlateauRule(window=20, tolerance=0.005, smoothing=5, check_every=5, anneal_steps=0, reductions=2,
                          factor=0.1)
    errors = {}
    for name, rule in (("plain", plain), ("reduced", reduced)):
        x, c, trace, step_loss = _l1_problem([2.0, 6.0])
        _, log = optimise_to_plateau("toy", [x], 3000, 0.2, 0.1, step_loss, trace, rule)
        assert log["converged"] == [True, True]
        errors[name] = (x.detach() - c).abs()
        if name == "reduced":
            assert log["reductions"] == [2, 2]
            first, second = log["descent_steps"]
            assert first < second  # each sequence on its own: the nearer target is reached and settled first
        else:
            assert "reductions" not in log
    assert bool((errors["reduced"] < 0.2 * errors["plain"]).all()), errors  # measured: 0.0006, 0.0005 against 0.016, 0.068


def test_a_fit_at_the_cap_before_its_last_reduction_is_not_converged():
    x, c, trace, step_loss = _l1_problem([2.0])
    rule = PlateauRule(window=20, tolerance=0.005, smoothing=5, check_every=5, anneal_steps=0, reductions=3,
                       factor=0.5)
    _, log = optimise_to_plateau("toy", [x], 80, 0.2, 0.1, step_loss, trace, rule)
    assert log["reductions"][0] < 3 and log["converged"] == [False] and log["stopped"] == "cap"


def test_a_flat_fit_capped_before_its_last_reduction_is_not_converged():
    """A constant objective (zero gradient): flat at every check. With two reductions and a window of
    25 steps it is reduced at step 25 and would be judged anew from step 50; a cap of 40 stops it
    at its first reduced rate with a change of exactly 0, within the tolerance: still not converged,
    for it never met the rule at its last rate. (The fit above, at the cap before its last
    reduction, is also still falling; this one is not, so only the reductions count can tell.)"""
    x = torch.zeros(1, requires_grad=True)
    trace = []

    def step_loss(step):
        f = 1.0 + 0.0 * x
        trace.append(f.detach())
        return f.sum(), lambda: {"f": float(f.detach().mean())}

    rule = PlateauRule(window=20, tolerance=0.005, smoothing=5, check_every=5, anneal_steps=0, reductions=2,
                       factor=0.5)
    _, log = optimise_to_plateau("toy", [x], 40, 0.1, 0.1, step_loss, trace, rule)
    assert log["reductions"] == [1] and log["plateau_decrease"] == [0.0] and log["descent_steps"] == [40]
    assert log["converged"] == [False] and log["stopped"] == "cap"
    assert sequence_diagnostics(torch.stack(trace), plateau=log)[0]["converged"] is False


@pytest.mark.parametrize("cap", [50, 55, 65])
def test_a_fit_cut_to_its_last_rate_at_or_just_before_the_cap_is_not_converged(cap):
    """A constant objective, two reductions, a window of 25 steps: reduced at steps 25 and 50. With
    a cap of 50 its second reduction falls on the cap's own check; with 55 or 65 it holds at the cap
    less than a window after it. Its change is 0, within the tolerance, but it was never measured
    over a whole window at its last rate: not converged (it was flagged converged before)."""
    x = torch.zeros(1, requires_grad=True)
    trace = []

    def step_loss(step):
        f = 1.0 + 0.0 * x
        trace.append(f.detach())
        return f.sum(), lambda: {}

    rule = PlateauRule(window=20, tolerance=0.005, smoothing=5, check_every=5, anneal_steps=0, reductions=2,
                       factor=0.5)
    _, log = optimise_to_plateau("toy", [x], cap, 0.1, 0.1, step_loss, trace, rule)
    assert log["reductions"] == [2] and log["descent_steps"] == [cap] and log["plateau_decrease"] == [0.0]
    assert log["converged"] == [False] and log["stopped"] == "cap"
    # a whole window at the last rate before the cap: held by the rule, converged
    trace.clear()
    _, log = optimise_to_plateau("toy", [x], 200, 0.1, 0.1, step_loss, trace, rule)
    assert log["reductions"] == [2] and log["descent_steps"] == [75] and log["converged"] == [True]


def test_min_steps_keeps_every_sequence_descending():
    x, c, trace, step_loss = _l1_problem([2.0, 6.0])
    rule = PlateauRule(window=20, tolerance=0.005, smoothing=5, check_every=5, anneal_steps=0, reductions=1,
                       min_steps=400)
    _, log = optimise_to_plateau("toy", [x], 3000, 0.2, 0.1, step_loss, trace, rule)
    assert min(log["descent_steps"]) >= 400 and log["converged"] == [True, True]


@pytest.mark.parametrize("bad", [{"factor": 1.0}, {"factor": 0}, {"reductions": -1}, {"min_steps": -5}])
def test_bad_reduction_rules_are_refused(bad):
    with pytest.raises(ValueError, match="objective.plateau"):
        PlateauRule.from_spec(bad)


def _creep_after_the_first_reduction():
    """A flat objective until step 30, then one falling by 0.3 % per unit of Adam's step (the
    optimised variable's gradient is constant, so each step is the sequence's own rate)."""
    x = torch.zeros(1, requires_grad=True)
    trace, start = [], []

    def step_loss(step):
        if step == 30:
            start.append(x.detach().clone())
        trace.append(1.0 - 0.003 * (x.detach() - start[0]) if start else torch.ones(1))
        return -x.sum(), lambda: {}

    return x, trace, step_loss


@pytest.mark.parametrize("rate_scaled", [False, True])
def test_a_rate_scaled_tolerance_does_not_pass_a_fit_creeping_at_its_reduced_rate(rate_scaled):
    # at 0.3 x the rate the creep is 0.36 % per window: within 0.5 %, not within 0.5 % x 0.3
    x, trace, step_loss = _creep_after_the_first_reduction()
    rule = PlateauRule(window=20, tolerance=0.005, smoothing=5, check_every=5, anneal_steps=0, reductions=2,
                       factor=0.3, rate_scaled=rate_scaled)
    _, log = optimise_to_plateau("toy", [x], 400, 0.2, 0.1, step_loss, trace, rule)
    if rate_scaled:
        assert log["converged"] == [False] and log["stopped"] == "cap" and log["reductions"] == [1]
        assert log["plateau_decrease"][0] > rule.tolerance * rule.factor
    else:
        assert log["converged"] == [True] and log["descent_steps"][0] < 100 and log["reductions"] == [2]


def test_rate_scaled_is_read_from_the_spec_and_checked():
    assert PlateauRule.from_spec({"rate_scaled": True}).rate_scaled
    assert not PlateauRule.from_spec({}).rate_scaled
    with pytest.raises(ValueError, match="rate_scaled must be true or false"):
        PlateauRule.from_spec({"rate_scaled": "yes"})
    rule = PlateauRule(tolerance=0.01, factor=0.5, rate_scaled=True)
    assert rule.tolerance_at(torch.tensor([0, 1, 2])).tolist() == pytest.approx([0.01, 0.005, 0.0025])


def test_fit_check_sets_the_rate_scaled_candidate_and_says_so():
    """``fit-check --rate-scaled`` judges table1's fits under the candidate rule, says so in its
    report, and leaves the loaded table spec as committed."""
    import copy

    from benchmark.run.catalog import load_table_spec
    from benchmark.tools.fit_check import with_rate_scaled

    spec = copy.deepcopy(load_table_spec("table1"))
    assert with_rate_scaled(spec, False) == "" and not spec["objective"]["plateau"].get("rate_scaled")
    note = with_rate_scaled(spec, True)
    assert spec["objective"]["plateau"]["rate_scaled"] is True and "not table1's protocol as committed" in note
    assert PlateauRule.from_spec(spec["objective"]["plateau"]).reductions == 2  # the rest of the rule kept
    assert not load_table_spec("table1")["objective"]["plateau"].get("rate_scaled")
    cosine = copy.deepcopy(spec)
    cosine["objective"]["step_rule"] = "cosine"
    with pytest.raises(ValueError, match="--rate-scaled needs table1's plateau step rule"):
        with_rate_scaled(cosine, True)


def _rows_problem(scales, targets):
    """_problem with a ``rows_loss``: the same objective on a subset of the sequences, and a count of
    the sequence evaluations each way."""
    x = torch.zeros(len(scales), 2, requires_grad=True)
    s = torch.tensor(scales)[:, None]
    c = torch.tensor(targets)[:, None] * torch.tensor([1.0, -0.5])
    trace, other, evaluated = [], [], []

    def objective(rows):
        f = 1.0 + (s[rows] * (x[rows] - c[rows]).square()).sum(1)
        trace.append(f.detach())
        other.append(2.0 * f.detach())
        evaluated.append(len(rows))
        return f.sum(), lambda: {"f": float(trace[-1].mean()), "g": float(other[-1].mean())}

    step_loss = lambda step: objective(torch.arange(len(scales)))  # noqa: E731
    rows_loss = lambda step, rows: objective(rows)  # noqa: E731
    return x, trace, other, evaluated, step_loss, rows_loss


def test_held_sequences_are_kept_not_evaluated_and_the_fit_is_the_same():
    """KeptRows: once a sequence is held, the descent evaluates only the others and feeds Adam the
    held one's kept gradient; the fit, the traces, the history and the verdicts are bit for bit
    those of evaluating the whole batch, for fewer sequence evaluations."""
    rule = PlateauRule(window=20, tolerance=0.002, smoothing=5, check_every=5, anneal_steps=10, reductions=2)
    runs = []
    for with_rows in (False, True):
        x, trace, other, evaluated, step_loss, rows_loss = _rows_problem([1.0, 1.0, 0.3], [0.5, 10.0, 4.0])
        history, log = optimise_to_plateau("toy", [x], 5000, 0.05, 0.1, step_loss, trace, rule,
                                           rows_loss=rows_loss if with_rows else None, row_traces=(other,))
        runs.append((x.detach().clone(), torch.stack(trace), torch.stack(other), history, log, evaluated))
    (x0, t0, o0, h0, l0, n0), (x1, t1, o1, h1, l1, n1) = runs
    assert len(set(l0["descent_steps"])) == 3  # the sequences stop at three different steps
    assert torch.equal(x0, x1) and torch.equal(t0, t1) and torch.equal(o0, o1)
    assert h0 == h1 and l0 == l1
    steps, (first, second, last) = l0["steps"], sorted(l0["descent_steps"])
    assert n0 == [3] * steps
    # a held sequence is evaluated once more at its held point, then kept until the anneal
    assert n1 == [3] * (first + 1) + [2] * (second - first) + [1] * (last - second - 1) + [3] * (steps - last)
    assert last - second > 50
