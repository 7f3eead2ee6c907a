"""Several starts per sequence for the encoded priors (``objective.multi_start``, a table1 version 8
candidate; benchmark.protocols.multi_start.MultiStart): the copies start where the rule says, each
sequence keeps the copy with the lowest final objective, and one start is the single-start fit."""

from __future__ import annotations

import copy

import pytest
import torch

from benchmark.protocols.completion import fit
from benchmark.protocols.fit_state import FitState, init_state
from benchmark.protocols.step_rules import PlateauRule
from benchmark.protocols.multi_start import MultiStart, select_copies, vary_copies
from benchmark.protocols.start_search import encoded_start
from benchmark.run.registry import make_adapter
from tests.test_start_search import _fresh_cache, _walkers


def test_the_rule_reads_its_mapping_and_names_what_is_wrong():
    assert MultiStart.from_spec(None) is None
    assert MultiStart.from_spec({"starts": 4, "noise": 0.25}) == MultiStart(starts=4, noise=0.25)
    for bad, words in (({"starts": 0}, "'starts' must be an integer"), ({"starts": 2.5}, "'starts' must be"),
                       ({"starts": 3, "noise": 0}, "'noise' > 0"), ({"count": 3}, "unknown key(s) ['count']"),
                       ([3], "expected a mapping")):
        with pytest.raises(ValueError, match=None) as err:
            MultiStart.from_spec(bad)
        assert words in str(err.value) and "objective.multi_start" in str(err.value)


def test_copies_start_encoded_at_the_own_start_and_with_seeded_noise(anny_body, monkeypatch, brief_searches):
    _fresh_cache(monkeypatch)
    batch = _walkers(anny_body, frames=4, points=60)
    adapter = make_adapter("sequential-primitives")
    g = torch.Generator().manual_seed(0)
    own = init_state(adapter, anny_body, batch, g, "cpu", search_heading=False, latent_init="mean")
    mean = {k: v.detach().clone() for k, v in own.latents.items()}
    state, _ = encoded_start(adapter, anny_body, batch, own, g, device="cpu", lr=0.03, lambda_prior=0.01)
    rule = MultiStart(starts=4, noise=0.5)
    copies, _ = encoded_start(adapter, anny_body, batch, own, g, device="cpu", lr=0.03, lambda_prior=0.01, copies=4)
    again, _ = encoded_start(adapter, anny_body, batch, own, g, device="cpu", lr=0.03, lambda_prior=0.01, copies=4)
    vary_copies(copies, own, rule, torch.Generator().manual_seed(1))
    vary_copies(again, own, rule, torch.Generator().manual_seed(1))
    B = batch.batch_size
    for k, v in copies.latents.items():
        view = v.detach().view(B, 4, *state.latents[k].shape[1:])
        assert v.is_leaf and v.requires_grad and torch.equal(v, again.latents[k])  # seeded
        # copy 0 is the encoded start (the encoder on the repeated batch: equal up to float rounding)
        assert torch.allclose(view[:, 0], state.latents[k].detach(), atol=1e-5) and torch.equal(view[:, 1], mean[k])
        noise = view[:, 2:] - view[:, :1]
        assert 0.3 < float(noise.std()) < 0.7 and not torch.equal(view[:, 2], view[:, 3])
    for name in ("shape_param", "root", "trans", "heading", "offset"):  # copy 1: the fit's own start; the others encoded
        x = getattr(state, name)
        if x is not None:
            view = getattr(copies, name).detach().view(B, 4, *x.shape[1:])
            assert torch.equal(view[:, 1], getattr(own, name).detach())
            assert torch.allclose(view[:, [0, 2, 3]], x.detach()[:, None].expand(-1, 3, *x.shape[1:]), atol=1e-5)
    back = select_copies(copies, torch.arange(B) * 4 + 1, state)  # copy 1 of each sequence: the own start
    assert all(torch.equal(back.latents[k].detach(), mean[k]) and back.latents[k].is_leaf for k in state.latents)
    assert torch.equal(back.shape_param.detach(), own.shape_param.detach())


def test_each_sequence_keeps_its_copy_with_the_lowest_objective(anny_body, monkeypatch, brief_searches):
    """Three starts, fitted side by side: the log holds every copy's final objective and the chosen
    one is each sequence's lowest; the state and the per-sequence logs are the batch's size; one
    start is the fit without the rule, bit for bit."""
    _fresh_cache(monkeypatch)
    batch = _walkers(anny_body, frames=4, points=60)
    adapter = make_adapter("sequential-primitives")
    args = dict(steps=40, lr=0.03, lambda_prior=0.01, device="cpu", loss_vertices=200, facing="observation",
                latent_init="mean", start_search="observation",
                plateau=PlateauRule(window=10, smoothing=2, check_every=5, anneal_steps=5, reductions=1))
    runs = {}
    for name, rule in (("none", None), ("one", MultiStart(starts=1)), ("three", MultiStart(starts=3))):
        runs[name] = fit(adapter, anny_body, batch, generator=torch.Generator().manual_seed(0), multi_start=rule, **args)
    state, info = runs["three"]
    log = info["multi_start"]
    assert len(log["objective"]) == 2 and all(len(row) == 3 for row in log["objective"])
    assert log["chosen"] == [min(range(3), key=row.__getitem__) for row in log["objective"]]
    assert info["data_trace"].shape[1] == 2 and len(info["plateau"]["converged"]) == 2
    assert all(v.shape[0] == 2 for v in state.latents.values()) and state.obs_t.shape[0] == 2
    for a, b in zip(runs["none"][0].parameters(), runs["one"][0].parameters()):
        assert torch.equal(a, b)
    assert "multi_start" not in runs["one"][1]


def test_fit_check_sets_the_candidate_rule_and_says_so():
    """``fit-check --multi-start K`` fits table1 under the candidate rule and its report says the
    protocol is not table1's as committed; a count below 1 is refused before anything is fitted."""
    from benchmark.run.catalog import load_table_spec
    from benchmark.tools.fit_check import MULTI_START_NOISE, run_robustness, with_multi_start

    committed = copy.deepcopy(load_table_spec("table1"))  # the loaded spec is shared: never change it in place
    assert "table1's rule as committed" in with_multi_start(copy.deepcopy(committed), 2, "plateau")  # version 8's rule
    spec = copy.deepcopy(committed)
    del spec["objective"]["multi_start"]  # a protocol without several starts (versions 1-7)
    assert with_multi_start(spec, None) == "" and "multi_start" not in spec["objective"]
    note = with_multi_start(spec, 4)
    assert spec["objective"]["multi_start"] == {"starts": 4, "noise": MULTI_START_NOISE}
    assert "not table1's protocol as committed" in note
    with pytest.raises(ValueError, match="--multi-start 0"):
        run_robustness("frequency-guided", multi_start=0)
    raced = copy.deepcopy(spec)
    note = with_multi_start(raced, 4, "plateau", "own")
    assert raced["objective"]["multi_start"] == {"starts": 4, "noise": MULTI_START_NOISE, "choose": "plateau",
                                                 "around": "own"}
    assert "choose: plateau, around: own" in note
    with pytest.raises(ValueError, match="add --multi-start K"):
        run_robustness("frequency-guided", around="own")
    assert load_table_spec("table1")["objective"]["multi_start"] == committed["objective"]["multi_start"]  # unchanged


def test_a_race_keeps_the_copy_lowest_at_the_first_plateau_and_holds_the_others():
    """``optimise_to_plateau``'s ``race``: two copies per sequence of a problem whose copies reach
    their first plateau at different heights; once both have, the lower goes on alone and the other
    is held where it was (its variables never move again); the winner's index and step are logged."""
    from benchmark.protocols.step_rules import optimise_to_plateau

    target = torch.tensor([[1.0], [1.0], [-2.0], [-2.0]])
    floor = torch.tensor([0.0, 3.0, 5.0, 0.5])  # sequence 0: copy 0 lower; sequence 1: copy 1 lower
    x = torch.tensor([[4.0], [-3.0], [2.0], [3.0]], requires_grad=True)
    trace, seen = [], []

    def step_loss(step):
        value = ((x - target) ** 2).sum(1) + floor
        trace.append(value.detach())
        seen.append(x.detach().clone())
        return value.sum(), lambda: {}

    rule = PlateauRule(window=10, smoothing=2, check_every=5, anneal_steps=0, reductions=2)
    _, log = optimise_to_plateau("toy", [x], 600, 0.1, 0.1, step_loss, trace, rule, race=2)
    race = log["race"]
    assert race["winner"] == [0, 1] and all(s > 0 for s in race["step"])
    steps = torch.stack(seen)
    for loser, step in ((1, race["step"][0]), (2, race["step"][1])):
        assert torch.equal(steps[step:, loser], steps[step:step + 1, loser].expand(len(seen) - step, 1))
    assert not torch.equal(steps[-1, 0], steps[race["step"][0], 0])  # the winner went on descending
    trace.clear()
    x.data.copy_(torch.tensor([[40.0], [-30.0], [20.0], [30.0]]))  # far off: still descending at the cap
    _, log = optimise_to_plateau("toy", [x], 30, 0.1, 0.1, step_loss, trace, rule, race=2)
    assert log["race"] == {"winner": [-1, -1], "step": [-1, -1]}  # chosen by the caller, after the anneal
    with pytest.raises(ValueError, match="whole groups"):
        y = torch.zeros(3, 1, requires_grad=True)
        optimise_to_plateau("toy", [y], 600, 0.1, 0.1, lambda s: (_append(trace, (y ** 2).sum(1)), lambda: {}),
                            trace, rule, race=2)


def _append(trace, value):
    trace.append(value.detach())
    return value.sum()


def test_a_raced_fit_logs_each_choice_and_its_step(anny_body, monkeypatch, brief_searches):
    """``MultiStart(choose="plateau")`` in a fit: the log names each sequence's copy and the step
    of the choice, the state is the batch's size; the rule is refused without the plateau rule."""
    _fresh_cache(monkeypatch)
    batch = _walkers(anny_body, frames=4, points=60)
    adapter = make_adapter("sequential-primitives")
    args = dict(steps=60, lr=0.03, lambda_prior=0.01, device="cpu", loss_vertices=200, facing="observation",
                latent_init="mean", start_search="observation")
    rule = MultiStart(starts=2, choose="plateau")
    state, info = fit(adapter, anny_body, batch, generator=torch.Generator().manual_seed(0), multi_start=rule,
                      plateau=PlateauRule(window=10, smoothing=2, check_every=5, anneal_steps=5, reductions=1), **args)
    log = info["multi_start"]
    assert len(log["chosen"]) == 2 and len(log["chosen_at_step"]) == 2 and set(log["chosen"]) <= {0, 1}
    assert all(v.shape[0] == 2 for v in state.latents.values()) and len(info["plateau"]["converged"]) == 2
    with pytest.raises(ValueError, match="needs the plateau step rule"):
        fit(adapter, anny_body, batch, generator=torch.Generator().manual_seed(0), multi_start=rule, **args)
    assert MultiStart.from_spec({"starts": 2, "choose": "plateau"}) == rule
    with pytest.raises(ValueError, match="choose one of end, plateau"):
        MultiStart.from_spec({"starts": 2, "choose": "first"})


def test_copies_about_the_own_start_take_no_encoded_start():
    """``around: own``: every copy starts from the fit's own start (its rigid parameters and
    shape), copy 0 exactly, the others with seeded noise on the latents; the encoded rule keeps its
    copies and its draws."""
    own = FitState(adapter=None, latents={"z": torch.zeros(2, 3)}, shape_param=torch.ones(2, 1),
                   obs_t=torch.zeros(2, 1), window_s=1.0, root=torch.full((2, 1, 3), 0.5))
    def copies():
        return FitState(adapter=None, latents={"z": torch.full((8, 3), 7.0, requires_grad=True)},
                        shape_param=torch.full((8, 1), 3.0), obs_t=torch.zeros(8, 1), window_s=1.0,
                        root=torch.full((8, 1, 3), 9.0))
    state = copies()
    with torch.no_grad():
        vary_copies(state, own, MultiStart(starts=4, around="own"), torch.Generator().manual_seed(0))
    z = state.latents["z"].detach().view(2, 4, 3)
    assert torch.equal(z[:, 0], own.latents["z"]) and (z[:, 1:].abs() > 0).all() and 0.2 < float(z[:, 1:].std()) < 1.0
    assert torch.equal(state.shape_param, torch.ones(8, 1)) and torch.equal(state.root, torch.full((8, 1, 3), 0.5))
    enc = copies()
    with torch.no_grad():
        vary_copies(enc, own, MultiStart(starts=4), torch.Generator().manual_seed(0))
    z = enc.latents["z"].detach().view(2, 4, 3)
    assert torch.equal(z[:, 0], torch.full((2, 3), 7.0)) and torch.equal(z[:, 1], own.latents["z"])
    assert torch.equal(enc.root.view(2, 4, 1, 3)[:, 0], torch.full((2, 1, 3), 9.0))
    with pytest.raises(ValueError, match="choose one of encoded, own"):
        MultiStart.from_spec({"starts": 2, "around": "mean"})
