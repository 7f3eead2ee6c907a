"""The batched L-BFGS (benchmark.protocols.quasi_newton, ``objective.optimiser: lbfgs``, a table1
version 8 candidate): each sequence is its own problem (its own history, line search and stop), it
reaches the minimum of an ill-conditioned problem that Adam crawls along, and the traces hold one
entry per iteration."""

import pytest
import torch

from benchmark.protocols.step_rules import PlateauRule, optimise_to_plateau
from benchmark.protocols.quasi_newton import OPTIMISERS, lbfgs_to_plateau, two_loop

RULE = PlateauRule(window=20, tolerance=1e-4, smoothing=5, check_every=5, anneal_steps=10)


def _problem(weights):
    """B independent problems: a 2-D Rosenbrock valley plus a 10-D quadratic with curvatures 1..1000
    (times the sequence's weight), from (-1.2, 1) and a seeded start; minimum 1e-3 at (1, 1), 0."""
    g = torch.Generator().manual_seed(0)
    B = len(weights)
    x = torch.tensor([[-1.2, 1.0]] * B, requires_grad=True)
    q = torch.randn(B, 10, generator=g).requires_grad_(True)
    scales, w = torch.logspace(0, 3, 10), torch.tensor(weights)
    trace, data = [], []

    def step_loss(step):
        rosen = 100 * (x[:, 1] - x[:, 0] ** 2) ** 2 + (1 - x[:, 0]) ** 2
        f = 1e-3 + rosen + w * (scales * q ** 2).sum(1)
        trace.append(f.detach())
        data.append(rosen.detach())
        return f.sum(), lambda: {"f": float(f.detach().mean())}

    return [x, q], trace, data, step_loss


def test_reaches_the_minimum_and_holds_every_sequence():
    tensors, trace, data, step_loss = _problem([1.0, 2.0, 4.0])
    history, log = lbfgs_to_plateau("toy", tensors, 500, 0.03, step_loss, trace, RULE, other_traces=(data,))
    assert log["optimiser"] == "lbfgs" and log["stopped"] == "plateau" and log["converged"] == [True] * 3
    assert torch.allclose(tensors[0].detach(), torch.ones(3, 2), atol=1e-3)
    assert tensors[1].detach().abs().max() < 1e-3
    # one entry per iteration (and the start) in every trace, at the accepted points: monotone
    assert len(trace) == len(data) == log["steps"] + 1
    f = torch.stack(trace)
    assert bool((f[1:] <= f[:-1] * (1 + 1e-6)).all())
    assert log["evaluations"] < 3 * log["steps"]
    assert history[0]["step"] == 0


def test_each_sequence_alone_is_fitted_as_in_the_batch():
    """Per-sequence curvature, line search and stop: a sequence's fit does not depend on its batch."""
    tensors, trace, _, step_loss = _problem([1.0, 30.0])
    _, log = lbfgs_to_plateau("toy", tensors, 500, 0.03, step_loss, trace, RULE)
    for i, w in enumerate([1.0, 30.0]):
        alone, trace1, _, step1 = _problem([w])
        with torch.no_grad():  # the same start as row i of the batch
            alone[1].copy_(torch.randn(2, 10, generator=torch.Generator().manual_seed(0))[i:i + 1])
        _, log1 = lbfgs_to_plateau("toy", alone, 500, 0.03, step1, trace1, RULE)
        assert log1["descent_steps"][0] == log["descent_steps"][i]
        assert torch.allclose(alone[0].detach()[0], tensors[0].detach()[i], atol=1e-5)


def test_fewer_iterations_than_adam_on_an_ill_conditioned_problem():
    """The lever it is a candidate for: Adam under the same plateau test on the same problem
    needs several times the steps (and ends farther from the minimum)."""
    tensors, trace, _, step_loss = _problem([1.0])
    _, log = lbfgs_to_plateau("toy", tensors, 3000, 0.03, step_loss, trace, RULE)
    adam_tensors, adam_trace, _, adam_loss = _problem([1.0])
    _, adam_log = optimise_to_plateau("toy", adam_tensors, 3000, 0.03, 0.1, adam_loss, adam_trace, RULE)
    assert 3 * log["steps"] < adam_log["steps"]
    assert float(trace[-1][0]) < float(adam_trace[-1][0])


def test_a_sequence_still_falling_at_the_cap_is_not_converged():
    tensors, trace, _, step_loss = _problem([1.0])
    _, log = lbfgs_to_plateau("toy", tensors, 25, 0.03, step_loss, trace, RULE)
    assert log["steps"] == 25 and log["stopped"] == "cap" and log["converged"] == [False]


def test_rate_scaled_rule_uses_its_last_rate_tolerance():
    rule = PlateauRule(window=20, tolerance=1e-2, smoothing=5, check_every=5, reductions=2, factor=0.1,
                       rate_scaled=True)  # judged at 1e-2 * 0.1 ** 2 = 1e-4
    tensors, trace, _, step_loss = _problem([1.0])
    _, log = lbfgs_to_plateau("toy", tensors, 500, 0.03, step_loss, trace, rule)
    assert log["converged"] == [True] and abs(log["plateau_decrease"][0]) <= 1e-4


def test_two_loop_without_pairs_is_steepest_descent():
    g = torch.randn(3, 5, dtype=torch.float64)
    S = torch.zeros(3, 4, 5, dtype=torch.float64)
    d = two_loop(g, S, S.clone(), torch.zeros(3, 4, dtype=torch.bool), [2, 1, 0, 3])
    assert torch.equal(d, -g)


def test_variables_must_be_batch_first():
    x = torch.zeros(2, requires_grad=True)
    scalar = torch.zeros((), requires_grad=True)
    with pytest.raises(ValueError, match="batch first"):
        lbfgs_to_plateau("toy", [x, scalar], 10, 0.03, lambda s: (x.sum(), dict), [], RULE)


def test_an_unknown_optimiser_is_refused_naming_the_field():
    from benchmark.protocols.completion_unit import optimiser_rule
    from benchmark.tools.fit_check import with_optimiser

    assert OPTIMISERS == ("adam", "lbfgs")
    assert optimiser_rule({"objective": {}}) == "adam"
    with pytest.raises(ValueError, match="objective.optimiser: 'sgd'"):
        optimiser_rule({"objective": {"optimiser": "sgd"}})
    spec = {"objective": {"optimiser": "adam", "step_rule": "plateau"}}
    assert with_optimiser(spec, None) == "" and with_optimiser(spec, "adam") == ""
    assert "not table1's protocol as committed" in with_optimiser(spec, "lbfgs")
    assert spec["objective"]["optimiser"] == "lbfgs"
    with pytest.raises(ValueError, match="plateau step rule"):
        with_optimiser({"objective": {"step_rule": "cosine"}}, "lbfgs")


def test_min_steps_holds_no_sequence_before_it():
    """The robustness check's longer probe: the fit goes on past its plateau to ``min_steps``."""
    tensors, trace, _, step_loss = _problem([1.0])
    _, base = lbfgs_to_plateau("toy", tensors, 1000, 0.03, step_loss, trace, RULE)
    longer = PlateauRule(**{**RULE.__dict__, "min_steps": 3 * base["steps"]})
    tensors, trace, _, step_loss = _problem([1.0])
    _, log = lbfgs_to_plateau("toy", tensors, 1000, 0.03, step_loss, trace, longer)
    assert log["steps"] >= 3 * base["steps"] and log["converged"] == [True]


def test_the_completion_fit_runs_under_lbfgs_with_two_starts(anny_body, monkeypatch, brief_searches):
    """``fit(optimiser="lbfgs")`` on real bodies and an encoded prior, with the multi-start copies:
    the objective falls, every per-sequence log is the batch's size, the traces hold one entry per
    iteration; without the plateau rule it is refused."""
    from benchmark.protocols.completion import fit
    from benchmark.protocols.multi_start import MultiStart
    from benchmark.run.registry import make_adapter
    from tests.test_start_search import _fresh_cache, _walkers

    _fresh_cache(monkeypatch)
    batch = _walkers(anny_body, frames=4, points=60)
    adapter = make_adapter("sequential-primitives")
    args = dict(steps=30, lr=0.03, lambda_prior=0.01, device="cpu", loss_vertices=200, facing="observation",
                latent_init="mean", start_search="observation")
    rule = PlateauRule(window=10, smoothing=2, check_every=5, anneal_steps=5)
    state, info = fit(adapter, anny_body, batch, generator=torch.Generator().manual_seed(0), plateau=rule,
                      multi_start=MultiStart(starts=2), optimiser="lbfgs", **args)
    log = info["plateau"]
    assert log["optimiser"] == "lbfgs" and 0 < log["steps"] <= 30 and log["evaluations"] >= log["steps"]
    assert len(log["converged"]) == 2 and len(info["multi_start"]["chosen"]) == 2
    trace = info["data_trace"]
    assert trace.shape == (log["steps"] + 1, 2) and bool((trace[-1] < trace[0]).all())
    assert all(v.shape[0] == 2 for v in state.latents.values())
    with pytest.raises(ValueError, match="needs the plateau step rule"):
        fit(adapter, anny_body, batch, generator=torch.Generator().manual_seed(0), optimiser="lbfgs", **args)
    with pytest.raises(ValueError, match="unknown optimiser 'sgd'"):
        fit(adapter, anny_body, batch, generator=torch.Generator().manual_seed(0), optimiser="sgd", **args)
