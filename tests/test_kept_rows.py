"""A plateau descent evaluates only the sequences still descending
(benchmark.protocols.kept_rows.KeptRows): the held ones' objective and gradient are kept from their
first step at the held point. The pieces it needs (a StaticChamfer of some elements, a state and a
batch of some sequences) give those sequences what the whole batch gives them, and a prior whose
sequences interact is evaluated whole."""

from __future__ import annotations

import pytest
import torch

from benchmark.metrics.static_chamfer import StaticChamfer
from benchmark.protocols import completion
from benchmark.protocols.completion import fit
from benchmark.protocols.fit_state import batch_rows, init_state, rows_independent, state_rows
from benchmark.protocols.step_rules import PlateauRule
from benchmark.run.registry import make_adapter
from tests.test_start_search import _fresh_cache, _walkers


def test_a_static_chamfer_of_some_elements_gives_them_the_whole_batchs_values_and_gradients():
    g = torch.Generator().manual_seed(0)
    b = torch.randn(6, 50, 3, generator=g)
    lengths = torch.tensor([50, 20, 35, 50, 7, 41])
    whole = StaticChamfer(b, lengths)
    a = torch.randn(6, 30, 3, generator=g, requires_grad=True)
    for _ in range(2):  # the second call starts its searches from the first one's answers
        full = whole(a)
    grad_full, = torch.autograd.grad(full.sum(), a)
    rows = torch.tensor([1, 4, 5])
    part = whole.select(rows)
    assert torch.equal(part.b, whole.b[rows]) and part._hints is not None  # the searches go on from where they were
    sub = a.detach()[rows].requires_grad_(True)
    value = part(sub)
    grad_part, = torch.autograd.grad(value.sum(), sub)
    assert torch.equal(value, full.detach()[rows])
    assert torch.allclose(grad_part, grad_full[rows], rtol=1e-6, atol=1e-9)
    assert torch.equal(part.indices(sub.detach(), [30] * 3)[0], whole.indices(a.detach(), [30] * 6)[0][rows])


def test_rows_of_a_state_and_a_batch_send_gradients_to_those_rows_only(anny_body):
    batch = _walkers(anny_body, frames=4, points=60)
    state = init_state(make_adapter("no-prior"), anny_body, batch, torch.Generator().manual_seed(0), "cpu")
    rows = torch.tensor([1])
    sub, sub_batch = state_rows(state, rows), batch_rows(batch, rows)
    assert sub_batch.batch_size == 1 and torch.equal(sub_batch.points, batch.points[1:])
    loss = sum(p.sum() for p in sub.parameters())
    loss.backward()
    for p in state.parameters():
        assert p.grad is not None and not bool(p.grad[0].any()) and bool(p.grad[1].any())


def test_the_check_refuses_sequences_that_interact(anny_body):
    batch = _walkers(anny_body, frames=4, points=60)
    adapter = make_adapter("no-prior")
    state = init_state(adapter, anny_body, batch, torch.Generator().manual_seed(0), "cpu")
    with torch.no_grad():
        state.trans += torch.arange(2.0)[:, None, None]  # the two sequences apart

    def pick(rows):
        return state if rows is None else state_rows(state, rows)

    def own(rows):  # each sequence's own translation
        return pick(rows).trans.square().sum((1, 2))

    def coupled(rows):  # every sequence against the batch's mean: they interact
        t = pick(rows).trans
        return (t - t.mean(0, keepdim=True)).square().sum((1, 2))

    assert rows_independent(own, adapter, 2, "cpu")
    assert not rows_independent(coupled, adapter, 2, "cpu")


@pytest.mark.parametrize("prior", ["no-prior", pytest.param("sequential-primitives", marks=pytest.mark.slow)])
def test_a_fit_with_kept_rows_is_the_whole_batch_fit(anny_body, monkeypatch, prior):
    """table1's fit under the plateau rule, with the held sequences kept and evaluated whole: the same
    steps, verdicts and variables (to float rounding), fewer sequence evaluations."""
    batch = _walkers(anny_body, frames=4, points=60, count=2)
    batch = batch_rows(batch, torch.tensor([0, 1, 1]))  # three sequences, two of them the same observation
    # the sequential primitives from their encoded start (computed once, then cached), no-prior from the T-pose
    start = dict(facing="observation", start_search="observation") if prior != "no-prior" else {}
    args = dict(steps=200, lr=0.03, lambda_prior=0.01, device="cpu", loss_vertices=200, latent_init="mean", **start,
                plateau=PlateauRule(window=10, smoothing=2, check_every=5, anneal_steps=5, reductions=1))
    check, real = completion.rows_independent, completion.batch_rows
    evaluated, runs = {}, {}
    _fresh_cache(monkeypatch)
    for kept in (False, True):
        counts = []
        monkeypatch.setattr(completion, "rows_independent", check if kept else (lambda *a: False))
        monkeypatch.setattr(completion, "batch_rows", lambda bt, rows: (counts.append(rows.tolist()), real(bt, rows))[1])
        runs[kept] = fit(make_adapter(prior), anny_body, batch, generator=torch.Generator().manual_seed(0), **args)
        evaluated[kept] = counts
    (s0, i0), (s1, i1) = runs[False], runs[True]
    assert i0["plateau"]["descent_steps"] == i1["plateau"]["descent_steps"]
    assert i0["plateau"]["converged"] == i1["plateau"]["converged"] and i0["plateau"]["steps"] == i1["plateau"]["steps"]
    assert len(set(i0["plateau"]["descent_steps"])) > 1  # the sequences stop at different steps
    assert evaluated[False] == [] and evaluated[True]  # the rows still descending, evaluated alone only with kept rows
    assert all(0 < len(rows) < 3 for rows in evaluated[True])
    assert torch.allclose(i0["data_trace"], i1["data_trace"], rtol=1e-4, atol=1e-4)
    for a, b in zip(s0.parameters(), s1.parameters()):
        assert torch.allclose(a, b, rtol=1e-3, atol=1e-4)


def test_an_adapter_with_per_batch_state_it_does_not_select_is_evaluated_whole(anny_body, monkeypatch):
    """The sequential primitives' prior term pulls towards the batch's initial latents: its
    batch_rows selects them. Without it the check finds the objective cannot be evaluated on some
    sequences, and the fit evaluates the whole batch."""
    import contextlib

    batch = _walkers(anny_body, frames=4, points=60)
    adapter = make_adapter("sequential-primitives")
    state = init_state(adapter, anny_body, batch, torch.Generator().manual_seed(0), "cpu", search_heading=False)

    def prior_of(rows):
        st = state if rows is None else state_rows(state, rows)
        return st.adapter.prior_term(st.latents) + st.shape_param.sum(1)

    with torch.no_grad():
        state.latents["z"] += 0.5  # away from the initial latents: a non-zero prior term per sequence
    assert rows_independent(prior_of, adapter, 2, "cpu")
    monkeypatch.setattr(type(adapter), "batch_rows", lambda self, rows: contextlib.nullcontext())
    assert not rows_independent(prior_of, adapter, 2, "cpu")


def test_check_prior_fails_an_adapter_whose_sequences_depend_on_each_other(monkeypatch, capsys):
    import contextlib

    from benchmark.tools.conformance import check_prior
    from priors.sequential_primitives.adapter import SequentialPrimitivesPrior

    monkeypatch.setattr(SequentialPrimitivesPrior, "batch_rows", lambda self, rows: contextlib.nullcontext())
    assert not check_prior("sequential-primitives", steps=1)
    out = capsys.readouterr().out
    assert "[FAIL] sequences independent" in out and "batch_rows(rows)" in out
