"""The limb start search of per-frame priors (benchmark.protocols.start_search.limb_start_search,
``objective.start_search: limbs``): hypotheses set the limb joints they name and nothing else, each
observed frame keeps its own best hypothesis, and a fit that starts from the search finds arms that
a T-pose start folds into a local minimum."""

from __future__ import annotations

import math

import pytest
import roma
import torch

from benchmark.core.motion import Motion
from benchmark.data.observations import make_scans
from benchmark.protocols.completion import fit, observation_batch
from benchmark.protocols.fit_state import init_state
from benchmark.protocols.start_search import (LIMB_START_STAGES, START_SEARCH_RULES, _best_per_frame, encoded_start,
                                                limb_hypotheses, limb_start_search, prior_free_start,
                                                supports_encoded_start, supports_start_search)
from benchmark.run.registry import make_adapter


def _motion(frames: int = 8, fps: float = 10.0, arms_down_from: int = 0) -> Motion:
    """A standing body, elbows bent forward and arms lowered from frame ``arms_down_from`` on (T-pose arms before)."""
    poses = torch.zeros(frames, 22, 3)
    down = torch.arange(frames) >= arms_down_from
    poses[down, 16, 2] = -1.2  # left shoulder lowered
    poses[down, 17, 2] = 1.2
    poses[down, 18, 1] = -1.57  # left elbow bent forward
    poses[down, 19, 1] = 1.57
    poses[:, 4, 0] = 0.3  # knees slightly bent
    poses[:, 5, 0] = 0.3
    trans = torch.zeros(frames, 3)
    trans[:, 1] = 1.0
    return Motion(poses=poses, trans=trans, timestamps=(torch.arange(frames) / fps).double(), source="arms")


def _batch(anny_body, motion: Motion, points: int = 400):
    scans, gt = make_scans(anny_body, [motion], fps=10.0, num_points=points, seed=0)
    n = scans.points.shape[1]
    return observation_batch(scans, n / 10.0, scans.timestamps - scans.timestamps[:, :1], "cpu"), gt


def _rotvec(adapter, state, joint: int) -> torch.Tensor:
    return roma.rotmat_to_rotvec(adapter.decode(state.latents, state.obs_t).rotations[:, :, joint])


def test_limb_hypotheses_set_the_named_joints_only(anny_body):
    adapter = make_adapter("no-prior")
    batch, _ = _batch(anny_body, _motion(frames=4), points=50)
    state = init_state(adapter, anny_body, batch, torch.Generator().manual_seed(0), "cpu", search_heading=False)
    base = adapter.decode(state.latents, state.obs_t).rotations
    arms = limb_hypotheses(adapter, state, 0)
    starts = LIMB_START_STAGES[0][2]
    assert len(arms) == len(starts) ** 2  # every combination of the left and right arm's starts
    for i, hyp in enumerate(arms):
        rot = adapter.decode(hyp, state.obs_t).rotations
        left, right = starts[i // len(starts)], starts[i % len(starts)]
        for joints, cfg, sign in ((LIMB_START_STAGES[0][0], left, 1.0), (LIMB_START_STAGES[0][1], right, -1.0)):
            for part, j in joints.items():
                want = torch.tensor(cfg.get(part, (0.0, 0.0, 0.0))) * torch.tensor([1.0, sign, sign])
                got = roma.rotmat_to_rotvec(rot[:, :, j])
                assert torch.allclose(got, want.expand_as(got), atol=1e-5), (i, part, got[0, 0], want)
        others = [j for j in range(22) if j not in (16, 17, 18, 19)]
        assert torch.allclose(rot[:, :, others], base[:, :, others], atol=1e-6)
    legs = limb_hypotheses(adapter, state, 1)
    assert torch.allclose(adapter.decode(legs[0], state.obs_t).rotations, base, atol=1e-6)  # None keeps the legs
    bent = roma.rotmat_to_rotvec(adapter.decode(legs[-1], state.obs_t).rotations)
    assert torch.allclose(bent[0, 0, 4], torch.tensor([1.2, 0.0, 0.0]), atol=1e-5)  # left knee
    assert torch.allclose(bent[0, 0, 5], torch.tensor([1.2, 0.0, 0.0]), atol=1e-5)  # right knee (x: mirror-invariant)
    own, prev, nxt = limb_hypotheses(adapter, state, len(LIMB_START_STAGES))
    pose = state.latents["pose"]
    assert torch.equal(own["pose"], pose) and torch.equal(prev["pose"][:, 1:], pose[:, :-1])
    assert torch.equal(nxt["pose"][:, :-1], pose[:, 1:]) and torch.equal(prev["pose"][:, 0], pose[:, 0])
    assert limb_hypotheses(adapter, state, len(LIMB_START_STAGES) + 1) is None


@pytest.mark.parametrize("start_fit", ["exact", "smooth"])
def test_each_frame_keeps_its_own_best_hypothesis(anny_body, start_fit):
    """Frames 0-3 have T-pose arms, frames 4-7 lowered arms with bent elbows; hypotheses at each
    half's true pose: every frame keeps the one that is right for it (on the Chamfer and on the
    soft-min Chamfer, objective.start_fit)."""
    adapter = make_adapter("no-prior")
    motion = _motion(frames=8, arms_down_from=4)
    batch, _ = _batch(anny_body, motion)
    state = init_state(adapter, anny_body, batch, torch.Generator().manual_seed(0), "cpu", search_heading=False)
    with torch.no_grad():  # the true root translation and knees, so only the arms differ between hypotheses
        state.trans.copy_(motion.trans[None].to(state.trans) + state.trans.mean(1, keepdim=True) * 0)
    true_rot = roma.rotvec_to_rotmat(motion.poses)[None]
    first = torch.cat([true_rot[:, :4], true_rot[:, :4]], 1)  # T-pose arms everywhere
    second = torch.cat([true_rot[:, 4:], true_rot[:, 4:]], 1)  # lowered arms everywhere
    hyps = [adapter.encode_motion(r, torch.zeros(1, 8, 3), state.obs_t) for r in (first, second)]
    out, counts = _best_per_frame(adapter, anny_body, batch, state, hyps, lr=0.03, lambda_prior=0.0, start_fit=start_fit)
    assert counts == [4, 4]
    shoulder = _rotvec(adapter, out, 16)[0, :, 2]
    assert bool((shoulder[:4].abs() < 0.4).all()) and bool((shoulder[4:] < -0.8).all()), shoulder
    for x in (out.latents["pose"], out.root, out.trans, out.shape_param):
        assert x.is_leaf and x.requires_grad
    assert out.latents["pose"].shape == state.latents["pose"].shape and out.root.shape == state.root.shape


def test_the_search_finds_arms_a_tpose_start_misses(anny_body):
    """Lowered arms with elbows bent forward: from the T-pose the fit folds them into a local
    minimum; from the limb search it finds them (arm joints within a few centimetres)."""
    adapter = make_adapter("no-prior")
    batch, gt = _batch(anny_body, _motion(frames=3), points=500)
    errors = {}
    for rule in ("none", "limbs"):
        state, info = fit(adapter, anny_body, batch, steps=40, lr=0.03, lambda_prior=0.0,
                          generator=torch.Generator().manual_seed(0), device="cpu", loss_vertices=500,
                          facing="observation", shape_lr_scale=10, latent_init="mean", start_search=rule)
        with torch.no_grad():
            from benchmark.protocols.completion import decode_output

            out, _, _ = decode_output(state, anny_body, batch.timestamps)
        aligned = (out.joints - out.joints[:, :, :1]) - (gt.joints - gt.joints[:, :, :1]).to(out.joints)
        errors[rule] = float(aligned[:, :, [18, 19, 20, 21]].norm(dim=-1).mean()) * 1000
        if rule == "limbs":
            assert len(info["start_choice_counts"]) == len(LIMB_START_STAGES) + 1
    assert errors["limbs"] < 40.0 and errors["limbs"] < 0.5 * errors["none"], errors


def test_the_search_applies_to_per_frame_priors_that_can_encode_a_pose(anny_body):
    assert START_SEARCH_RULES == ("none", "limbs", "observation")
    assert supports_encoded_start(make_adapter("hmvae")) and supports_encoded_start(make_adapter("sequential-primitives"))
    assert not supports_encoded_start(make_adapter("no-prior")) and not supports_encoded_start(make_adapter("vposer-slerp"))
    assert supports_start_search(make_adapter("no-prior")) and supports_start_search(make_adapter("vposer-slerp"))
    assert not supports_start_search(make_adapter("sequential-primitives"))
    assert not supports_start_search(make_adapter("hmvae"))  # fixed-window
    adapter = make_adapter("sequential-primitives")
    batch, _ = _batch(anny_body, _motion(frames=4), points=50)
    state = init_state(adapter, anny_body, batch, torch.Generator().manual_seed(0), "cpu", search_heading=False)
    same, log = limb_start_search(adapter, anny_body, batch, state, lr=0.03, lambda_prior=0.01)
    assert same is state and log["start_search"].startswith("none")


def test_vposer_hypotheses_are_its_encoder_means(anny_body):
    adapter = make_adapter("vposer-slerp")
    batch, _ = _batch(anny_body, _motion(frames=3), points=50)
    state = init_state(adapter, anny_body, batch, torch.Generator().manual_seed(0), "cpu", search_heading=False,
                       latent_init="mean")
    hyps = limb_hypotheses(adapter, state, 0)
    rot = adapter.decode(hyps[4], state.obs_t).rotations  # both arms lowered, elbows straight
    shoulder = roma.rotmat_to_rotvec(rot[:, :, 16])
    assert float(shoulder[..., 2].mean()) < -0.6, shoulder  # the decoded arm is lowered, as the encoder understood it
    assert hyps[4]["z"].shape == state.latents["z"].shape


def test_fit_refuses_an_unknown_start_search(anny_body):
    batch, _ = _batch(anny_body, _motion(frames=2), points=30)
    with pytest.raises(ValueError, match="unknown start search 'joints'"):
        fit(make_adapter("no-prior"), anny_body, batch, steps=1, lr=0.03, lambda_prior=0.01,
            generator=torch.Generator().manual_seed(0), device="cpu", start_search="joints")


# -- table1 protocol v5: the encoded prior-free start of window and continuous priors -------------
def _walkers(anny_body, frames: int = 8, points: int = 200, count: int = 2):
    from tests.test_facing import _turned_walker

    scans, _ = make_scans(anny_body, [_turned_walker(math.pi, frames=frames), _turned_walker(0.5, frames=frames)][:count],
                          fps=10.0, num_points=points, seed=0)
    out_t = (torch.arange(frames, dtype=torch.float64) / 10.0)[None].expand(count, -1)
    return observation_batch(scans, frames / 10.0, out_t, "cpu")


def _fresh_cache(monkeypatch):
    from benchmark.protocols import start_search

    monkeypatch.setattr(start_search, "_START_CACHE", start_search.OrderedDict())


@pytest.mark.parametrize("prior", ["sequential-primitives", pytest.param("hmvae", marks=pytest.mark.slow)])
def test_encoded_start_is_the_prior_free_start_encoded(anny_body, monkeypatch, prior, brief_searches):
    """A window prior (free heading and offset: sequential primitives; free root orientation and
    translation: HM-VAE) starts from the prior-free start at the output timestamps, encoded; its
    body shape; its rigid parameters set to the prior-free root and translation."""
    from benchmark.protocols.fit_state import body_parameters

    _fresh_cache(monkeypatch)
    batch = _walkers(anny_body)
    adapter = make_adapter(prior)
    g = torch.Generator().manual_seed(0)
    args = dict(device="cpu", lr=0.03, lambda_prior=0.01)
    own = init_state(adapter, anny_body, batch, g, "cpu", search_heading=False, latent_init="mean")
    state, log = encoded_start(adapter, anny_body, batch, own, g, **args)
    ref, _ = prior_free_start(anny_body, batch, g, **args)
    rot, trans = body_parameters(ref, batch.output_timestamps)
    want = adapter.encode_motion(rot, trans, batch.output_timestamps)
    for k, v in state.latents.items():
        assert torch.equal(v.detach(), want[k].to(v)) and v.requires_grad and v.is_leaf, k
    assert torch.equal(state.shape_param.detach(), ref.shape_param.detach())
    ref_rot, ref_trans = body_parameters(ref, batch.timestamps, observed=True)
    got_rot, got_trans = body_parameters(state, batch.timestamps, observed=True)
    if state.trans is not None:  # the prior does not decode translation: the free translation is the reference's
        assert torch.equal(state.trans.detach(), ref_trans)
    else:  # a free offset: the decoded translation matches the reference's on average
        assert torch.allclose((got_trans - ref_trans).mean(1), torch.zeros(2, 3), atol=1e-5)
    if state.root is not None:
        assert torch.allclose(roma.special_gramschmidt(state.root.detach().unflatten(-1, (3, 2))), ref_rot[:, :, 0],
                              atol=1e-5)
    # the prior's term measures from this start where it measures from a start (the sequential primitives' z_init)
    if prior == "sequential-primitives":
        assert torch.allclose(adapter.prior_term(state.latents), torch.zeros(2), atol=1e-6)
    assert log["start"] == "encoded prior-free start" and len(log["start_choice_counts"]) == len(LIMB_START_STAGES) + 1
    assert got_rot.shape == ref_rot.shape


def test_encoded_start_leaves_per_frame_priors_and_is_searched_once(anny_body, monkeypatch, brief_searches):
    """Per-frame priors keep their own limb search: no-prior's fit under "observation" (its start
    served from the prior-free start's cache) is the same as under "limbs" (searched in the fit), bit
    for bit; the prior-free start runs once per observation and is served as a fresh copy."""
    from benchmark.protocols import start_search

    _fresh_cache(monkeypatch)
    batch = _walkers(anny_body, frames=3, points=60, count=1)
    adapter = make_adapter("no-prior")
    g = torch.Generator().manual_seed(0)
    state = init_state(adapter, anny_body, batch, g, "cpu", search_heading=False)
    same, log = encoded_start(adapter, anny_body, batch, state, g, device="cpu", lr=0.03, lambda_prior=0.01)
    assert same is state and log["start_search"].startswith("none")
    assert "observation" in START_SEARCH_RULES
    calls = []
    real = start_search.limb_start_search
    runs = []
    for rule in ("limbs", "observation"):  # "limbs": searched in the fit; "observation": the prior-free start's cache
        if rule == "observation":  # count the searches from here on: the prior-free start's
            monkeypatch.setattr(start_search, "limb_start_search", lambda *a, **k: calls.append(1) or real(*a, **k))
        st, info = fit(adapter, anny_body, batch, steps=2, lr=0.03, lambda_prior=0.01, generator=torch.Generator().manual_seed(0),
                       device="cpu", loss_vertices=300, facing="observation", latent_init="mean", start_search=rule)
        runs.append((st, info))
    assert torch.equal(runs[0][0].latents["pose"], runs[1][0].latents["pose"])
    assert torch.equal(runs[0][1]["data_trace"], runs[1][1]["data_trace"])
    assert runs[1][1]["facing_yaw_rad"] == runs[0][1]["facing_yaw_rad"] and len(start_search._START_CACHE) == 1
    assert len(calls) == 1  # the prior-free start, searched once for this observation
    a, _ = prior_free_start(anny_body, batch, g, device="cpu", lr=0.03, lambda_prior=0.01)
    with torch.no_grad():
        a.latents["pose"].add_(1.0)  # a caller's change never reaches the cache
    b, _ = prior_free_start(anny_body, batch, g, device="cpu", lr=0.03, lambda_prior=0.01)
    assert len(calls) == 1 and not torch.equal(a.latents["pose"], b.latents["pose"])
    c, _ = prior_free_start(anny_body, batch, g, device="cpu", lr=0.03, lambda_prior=0.01)
    assert torch.equal(b.latents["pose"], c.latents["pose"]) and len(calls) == 1


def _soft_chamfers_built(monkeypatch) -> list:
    """The start cache emptied; the temperature of every soft-min Chamfer the searches build from
    here on, appended to the returned list."""
    from benchmark.metrics import soft_chamfer
    from benchmark.protocols import brief_fit

    _fresh_cache(monkeypatch)
    built = []
    real = soft_chamfer.SoftChamfer
    monkeypatch.setattr(brief_fit, "SoftChamfer", lambda *a: built.append(a[2]) or real(*a))
    return built


def test_the_smooth_start_fit_searches_on_the_soft_chamfer_and_is_kept_apart(anny_body, monkeypatch, brief_searches):
    """``objective.start_fit: smooth``: the prior-free start's limb search's brief fits run on the
    soft-min Chamfer (its facing search's stay on the Chamfer, as the exact rule's); the two starts
    are kept under different keys (neither served for the other), each deterministic; an unknown
    value names the key."""
    from benchmark.protocols import brief_fit, start_search

    built = _soft_chamfers_built(monkeypatch)
    batch = _walkers(anny_body, frames=3, points=60, count=1)
    g = torch.Generator().manual_seed(0)
    args = dict(device="cpu", lr=0.03, lambda_prior=0.01)
    exact, _ = prior_free_start(anny_body, batch, g, **args)
    assert built == []
    soft, log = prior_free_start(anny_body, batch, g, start_fit="smooth", **args)
    assert built == [brief_fit.START_SOFTMIN_M] * (len(LIMB_START_STAGES) + 1)  # one per stage, none for the facing
    assert len(start_search._START_CACHE) == 2 and not torch.equal(exact.latents["pose"], soft.latents["pose"])
    _fresh_cache(monkeypatch)
    again, _ = prior_free_start(anny_body, batch, g, start_fit="smooth", **args)
    assert torch.equal(again.latents["pose"], soft.latents["pose"]) and torch.equal(again.trans, soft.trans)
    with pytest.raises(ValueError, match="unknown objective.start_fit 'bogus'; choose one of exact, smooth"):
        fit(make_adapter("no-prior"), anny_body, batch, steps=2, generator=g, start_fit="bogus", **args)


def test_smooth_encoded_searches_only_the_encoders_start_smooth(anny_body, monkeypatch, brief_searches):
    """``objective.start_fit: smooth-encoded``: the prior-free start an encoder encodes is the
    smooth one (the sequential primitives' encoded start, the soft-min Chamfer built); no-prior's
    own start and a per-frame prior's own search are the exact ones (served from the exact start's
    key, no soft-min Chamfer built); a search's own functions refuse the spec-level value."""
    from benchmark.protocols import brief_fit, start_search
    from benchmark.protocols.brief_fit import check_search_fit, search_fit

    assert [search_fit(f, e) for f in ("exact", "smooth", "smooth-encoded") for e in (False, True)] == [
        "exact", "exact", "smooth", "smooth", "exact", "smooth"]
    with pytest.raises(ValueError, match="'smooth-encoded' is not one search's rule"):
        check_search_fit("smooth-encoded")
    built = _soft_chamfers_built(monkeypatch)
    batch = _walkers(anny_body, frames=3, points=60, count=1)
    g = torch.Generator().manual_seed(0)
    args = dict(device="cpu", lr=0.03, lambda_prior=0.01)
    with pytest.raises(ValueError, match="not one search's rule"):
        prior_free_start(anny_body, batch, g, start_fit="smooth-encoded", **args)
    for name in ("no-prior", "vposer-slerp"):
        adapter = make_adapter(name)
        own = init_state(adapter, anny_body, batch, g, "cpu", search_heading=False, latent_init="mean")
        start_search.searched_start(adapter, anny_body, batch, own, "observation", g, start_fit="smooth-encoded", **args)
    assert built == []
    adapter = make_adapter("sequential-primitives")
    own = init_state(adapter, anny_body, batch, g, "cpu", search_heading=False, latent_init="mean")
    state, log = start_search.searched_start(adapter, anny_body, batch, own, "observation", g,
                                             start_fit="smooth-encoded", **args)
    assert log["start"] == "encoded prior-free start" and built == [brief_fit.START_SOFTMIN_M] * (len(LIMB_START_STAGES) + 1)
    smooth, _ = prior_free_start(anny_body, batch, g, start_fit="smooth", **args)  # served: the one just encoded
    assert len(built) == len(LIMB_START_STAGES) + 1
    exact, _ = prior_free_start(anny_body, batch, g, **args)
    assert not torch.equal(exact.latents["pose"], smooth.latents["pose"])


def test_the_start_fit_key_is_read_checked_and_set_by_fit_check():
    from benchmark.protocols.completion_unit import start_fit_rule
    from benchmark.tools.fit_check import with_start_fit

    assert start_fit_rule({"objective": {}}) == "exact" and start_fit_rule({"objective": {"start_fit": "smooth"}}) == "smooth"
    with pytest.raises(ValueError, match="unknown objective.start_fit 'soft'"):
        start_fit_rule({"objective": {"start_fit": "soft"}})
    spec = {"objective": {}}
    assert with_start_fit(spec, None) == "" and with_start_fit(spec, "exact") == "" and spec == {"objective": {}}
    assert "objective.start_fit smooth (not table1's protocol as committed)" in with_start_fit(spec, "smooth")
    assert spec["objective"]["start_fit"] == "smooth"
    with pytest.raises(ValueError, match="--start-fit 'soft'"):
        with_start_fit(spec, "soft")
