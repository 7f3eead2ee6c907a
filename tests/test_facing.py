"""The facing search of a fit (benchmark.protocols.facing.facing_search): a body that faces away
from +z is fitted facing the right way, the same rule for every prior; the default fit rule of
table1 protocol v1 is unchanged."""

from __future__ import annotations

import math

import pytest
import torch

from benchmark.core.motion import Motion
from benchmark.data.observations import make_scans
from benchmark.protocols.completion import fit, observation_batch
from benchmark.protocols.facing import FACING_RULES, facing_search, mean_heading, observed_facing


def _turned_walker(yaw: float, frames: int = 20, fps: float = 10.0) -> Motion:
    """A body with bent knees and elbows (a pose a T-pose start cannot mirror), turned by ``yaw``."""
    poses = torch.zeros(frames, 22, 3)
    poses[:, 0, 1] = yaw
    t = torch.arange(frames) / fps
    poses[:, 4, 0] = 0.9 + 0.3 * torch.sin(2 * math.pi * t)  # left knee
    poses[:, 5, 0] = 0.9 - 0.3 * torch.sin(2 * math.pi * t)  # right knee
    poses[:, 1, 0] = -0.6  # hips flexed forward
    poses[:, 2, 0] = -0.6
    poses[:, 18, 1] = -1.2  # elbows
    poses[:, 19, 1] = 1.2
    poses[:, 16, 2] = -1.1  # arms down
    poses[:, 17, 2] = 1.1
    trans = torch.zeros(frames, 3)
    trans[:, 1] = 1.0
    return Motion(poses=poses, trans=trans, timestamps=t.double(), source="turned")


@pytest.mark.parametrize("yaw", [math.pi, -math.pi / 2])
def test_facing_search_turns_no_prior_the_right_way(anny_body, yaw):
    from benchmark.run.registry import make_adapter

    scans, _ = make_scans(anny_body, [_turned_walker(yaw)], fps=10.0, num_points=300, seed=0)
    out_t = torch.arange(8, dtype=torch.float64)[None] / 4.0
    batch = observation_batch(scans, 2.0, out_t, "cpu")
    state, log = facing_search(make_adapter("no-prior"), anny_body, batch, torch.Generator().manual_seed(0), "cpu",
                               lr=0.03, lambda_prior=0.01)
    chosen = log["facing_yaw_rad"][0]
    err = abs((chosen - yaw + math.pi) % (2 * math.pi) - math.pi)
    assert err <= math.pi / 4 + 1e-6, (chosen, yaw, log["facing_scores_mm"])
    # the state is the chosen hypothesis, batch-first, ready for the full fit
    assert state.root.shape == (1, batch.num_observed, 6) and state.root.requires_grad and state.root.is_leaf


def test_fit_refuses_an_unknown_facing_rule(anny_body):
    from benchmark.run.registry import make_adapter

    scans, _ = make_scans(anny_body, [_turned_walker(0.0, frames=4)], fps=10.0, num_points=50, seed=0)
    batch = observation_batch(scans, 0.4, torch.zeros(1, 2, dtype=torch.float64), "cpu")
    assert FACING_RULES == ("heading8", "search", "observation")
    with pytest.raises(ValueError, match="unknown facing rule 'mirror'"):
        fit(make_adapter("no-prior"), anny_body, batch, steps=1, lr=0.03, lambda_prior=0.01,
            generator=torch.Generator().manual_seed(0), device="cpu", facing="mirror")


_SLOW = pytest.mark.slow


@pytest.mark.parametrize("prior", ["vposer-slerp", "sequential-primitives", "motion-dvae", "hmvae",
                                   *(pytest.param(p, marks=_SLOW) for p in ("frequency-guided", "hmvae-trajectory",
                                                                             "structured-latent", "slerp"))])
def test_every_prior_fits_through_the_facing_search(anny_body, prior):
    """Per-frame, fixed-window and continuous priors, with and without their own root orientation,
    translation or heading (protocol v2): the facing found on the observation is the prior's
    starting facing, and the full fit continues from it (one prior of each kind in the default
    suite, plus HM-VAE, whose own coarse search chose wrong yaws on the quick sequences)."""
    from benchmark.run.registry import make_adapter

    scans, _ = make_scans(anny_body, [_turned_walker(math.pi, frames=8), _turned_walker(0.5, frames=8)],
                          fps=10.0, num_points=200, seed=0)
    out_t = (torch.arange(6, dtype=torch.float64) / 8.0)[None].expand(2, -1)
    batch = observation_batch(scans, 0.8, out_t, "cpu")
    adapter = make_adapter(prior)
    # table1 v2: the facing found on the observation (prior-free search), the prior's start turned to it
    start, log = observed_facing(adapter, anny_body, batch, torch.Generator().manual_seed(0), "cpu", lr=0.03,
                                 lambda_prior=0.01)
    target = torch.tensor(log["facing_yaw_rad"], dtype=torch.float32)
    turned = mean_heading(start, batch)
    assert torch.allclose(torch.remainder(turned - target + math.pi, 2 * math.pi) - math.pi, torch.zeros(2), atol=1e-3)
    err = torch.remainder(target - torch.tensor([math.pi, 0.5]) + math.pi, 2 * math.pi) - math.pi
    assert (err.abs() <= math.pi / 4 + 1e-6).all(), log
    if prior not in ("vposer-slerp", "sequential-primitives", "motion-dvae"):
        return  # the full fit below: one prior of each kind in the default suite
    # the full fit continues from such a start for every kind of prior, here with a subsampled data term
    state, info = fit(adapter, anny_body, batch, steps=3, lr=0.03, lambda_prior=0.01,
                      generator=torch.Generator().manual_seed(0), device="cpu", loss_vertices=300, facing="observation",
                      shape_lr_scale=10.0, points_per_step=100)
    assert len(info["facing_yaw_rad"]) == 2 and len(info["facing_scores_mm"][0]) == 8
    assert info["data_trace"].shape == (3, 2) and torch.isfinite(info["data_trace"]).all()
    assert state.shape_param.shape[0] == 2


def test_observation_facing_is_searched_once_per_observation(anny_body, monkeypatch):
    """Every prior of a cell sees the same observation: the prior-free facing search runs once per
    observation and process, and the result served again is bit for bit the one computed afresh."""
    from benchmark.protocols import facing

    scans, _ = make_scans(anny_body, [_turned_walker(math.pi, frames=6)], fps=10.0, num_points=120, seed=0)
    batch = observation_batch(scans, 0.6, (torch.arange(4, dtype=torch.float64) / 6.0)[None], "cpu")
    other, _ = make_scans(anny_body, [_turned_walker(0.5, frames=6)], fps=10.0, num_points=120, seed=0)
    batch2 = observation_batch(other, 0.6, (torch.arange(4, dtype=torch.float64) / 6.0)[None], "cpu")
    calls = []
    real = facing.facing_search
    monkeypatch.setattr(facing, "facing_search", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setattr(facing, "_FACING_CACHE", facing.OrderedDict())
    args = dict(device="cpu", lr=0.03, lambda_prior=0.01)
    yaw1, log1 = facing.observation_facing(anny_body, batch, torch.Generator().manual_seed(0), **args)
    g = torch.Generator().manual_seed(5)
    state = g.get_state()
    yaw2, log2 = facing.observation_facing(anny_body, batch, g, **args)
    assert len(calls) == 1 and torch.equal(yaw1, yaw2) and log1 == log2
    assert torch.equal(g.get_state(), state)  # a served result draws nothing, as the search itself
    facing.observation_facing(anny_body, batch2, g, **args)  # another observation: searched
    facing.observation_facing(anny_body, batch, g, lr=0.02, lambda_prior=0.01, device="cpu")  # another lr
    assert len(calls) == 3
    monkeypatch.setattr(facing, "_FACING_CACHE", facing.OrderedDict())
    yaw3, log3 = facing.observation_facing(anny_body, batch, torch.Generator().manual_seed(0), **args)
    assert len(calls) == 4 and torch.equal(yaw1, yaw3) and log1 == log3
