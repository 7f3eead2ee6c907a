"""The motion tables (denoise, inbetween, reconstruction): units on one short handmade motion, and one
end-to-end table run through the same runner as table1."""

import json
import math

import pytest
import torch

from benchmark.run.catalog import get_profile, load_table_spec
from benchmark.core.motion import Motion
from benchmark.protocols import denoise, inbetween, motion_fit, reconstruction
from benchmark.core.work_units import plan_units, si_metric
from benchmark.core.rotations import slerp_matrices
from priors.base import MotionDenoiser
from priors.no_prior import NoPrior
from priors.slerp import SlerpBaseline

STEPS = 4


def _motion(seed: int, seconds: float = 2.2, fps: float = 50.0, subject: str = "s") -> Motion:
    """Smooth handmade motion: sinusoidal joint rotations (0.3 rad), a slow turn, walking forward."""
    g = torch.Generator().manual_seed(seed)
    n = int(round(seconds * fps))
    t = torch.arange(n, dtype=torch.float64) / fps
    amp = torch.rand(22, 3, generator=g) * 0.3
    phase = torch.rand(22, 3, generator=g) * 2 * math.pi
    poses = amp * torch.sin(2 * math.pi * 1.2 * t[:, None, None].float() + phase)
    poses[:, 0] = torch.stack([torch.zeros(n), 0.4 * t.float(), torch.zeros(n)], -1)  # turn about y
    trans = torch.stack([0.1 * t.float(), 0.02 * torch.sin(6 * t.float()), 0.9 * t.float()], -1)
    return Motion(poses=poses, trans=trans, timestamps=t, shape=torch.full((6,), 0.5), body="anny",
                  source=f"hand{seed}", meta={"subject": subject})


@pytest.fixture(scope="module")
def motions():
    return {"a": _motion(1, subject="s1"), "b": _motion(2, subject="s2")}


@pytest.fixture(scope="module")
def vposer():
    from priors.vposer import VPoserSlerp

    return VPoserSlerp()


def _unit(spec, prior, cell, ids, seed=0):
    profile = {**get_profile("smoke"), "steps": STEPS}
    units = plan_units(spec, profile, [prior], ids, seed, "cpu", {prior: {}})
    return next(u for u in units if u.cell == cell), profile


def _run(module, spec, adapter, body, source, cell, ids=("a",)):
    unit, profile = _unit(spec, adapter.name, cell, list(ids))
    return module.run_unit(unit, spec, profile, adapter, body, source, "cpu")


def _values(result, spec):
    """Per-sequence reported values {metric: value} of the first sequence."""
    row = result["per_sequence"][0]
    out = {}
    for m in spec["metrics"]:
        key, factor = si_metric(m["name"])
        if key in row["sums"]:  # a metric n/a for this prior (row["na"]) is left out
            out[m["name"]] = factor * row["sums"][key] / row["frames"]
    return out


class _EchoDenoiser(MotionDenoiser, NoPrior):
    """A prior whose denoise_motion returns its input: its output is the observation."""

    name = "echo"

    def denoise_motion(self, rotations, trans, timestamps, mode, iterations):
        return rotations, trans


# -------------------------------------------------------------------------------- metrics

def test_quaternion_loss_zero_for_identical_and_sign_invariant():
    g = torch.Generator().manual_seed(0)
    R = motion_fit.global_rotations(torch.eye(3).expand(1, 1, 22, 3, 3))
    import roma

    rot = roma.rotvec_to_rotmat(torch.randn(2, 5, 22, 3, generator=g))
    assert torch.allclose(motion_fit.quaternion_loss(rot, rot), torch.zeros(2, 5), atol=1e-6)
    assert torch.allclose(R, torch.eye(3).expand_as(R))
    other = roma.rotvec_to_rotmat(torch.randn(2, 5, 22, 3, generator=g))
    loss = motion_fit.quaternion_loss(other, rot)
    assert bool((loss > 0).all()) and bool((loss <= math.sqrt(2 * 22) + 1e-6).all())
    # a half-turn of the root about y moves every joint's world rotation by pi: |q - q'| = sqrt(2) each
    flip = roma.rotvec_to_rotmat(torch.tensor([0.0, math.pi, 0.0])).expand(2, 5, 3, 3)
    turned = torch.cat([(flip @ rot[:, :, 0])[:, :, None], rot[:, :, 1:]], 2)
    assert torch.allclose(motion_fit.quaternion_loss(turned, rot), torch.full((2, 5), math.sqrt(2 * 22)), atol=1e-5)


# -------------------------------------------------------------------------------- denoise

def test_denoise_units_noise_determinism_and_na(anny_body, motions, vposer):
    spec = load_table_spec("denoise")
    src = denoise.make_source(spec, anny_body, motions, seed=7)
    cell = {"sigma": 0.1, "mode": "optimisation"}
    r_no = _run(denoise, spec, NoPrior(), anny_body, src, cell)
    r_vp = _run(denoise, spec, vposer, anny_body, src, cell)
    r_reg = _run(denoise, spec, vposer, anny_body, src, {"sigma": 0.1, "mode": "regression"})
    for r in (r_no, r_vp, r_reg):
        assert r["na_reason"] is None and r["device_name"]
        v = _values(r, spec)
        assert all(math.isfinite(x) for x in v.values()), v
        assert v["time_per_frame_s"] > 0 and v["v2v_mm"] > 0 and v["gt_accel_mps2"] > 0
        assert v["obs_v2v_mm"] > 20  # 0.1 rad of noise on every joint
        assert v["obs_accel_mps2"] > v["gt_accel_mps2"]
    assert r_reg["method"] == "encode_motion -> decode"
    # version 2: no-prior (an exact encode_motion) starts at the noisy motion, VPoser at its encoder's
    # output; every fit stores its diagnostics (a cap below the plateau rule's least steps: unconverged)
    assert r_no["method"].startswith("fit (init observation, plateau rule, cap")
    assert r_vp["method"].startswith("fit (init encoder, plateau rule, cap")
    assert all(row["diagnostics"]["converged"] is False for row in r_no["per_sequence"])
    # the observation depends on (seed, sigma, sequence), never on the prior or the mode
    assert r_no["fingerprint"] == r_vp["fingerprint"] == r_reg["fingerprint"]
    again = denoise.make_source(spec, anny_body, motions, seed=7)
    assert again.noisy(["a"], 0.1)[1] == r_no["fingerprint"]
    assert denoise.make_source(spec, anny_body, motions, seed=8).noisy(["a"], 0.1)[1] != r_no["fingerprint"]
    assert src.noisy(["a"], 0.15)[1] != r_no["fingerprint"]
    # a sequence's noise does not depend on its batch
    both, _ = src.noisy(["a", "b"], 0.1)
    alone, _ = src.noisy(["a"], 0.1)
    assert torch.equal(both.rotations[:1], alone.rotations)
    # a prior without encoder nor denoise_motion cannot regress; the SLERP baseline is not in this table
    na = _run(denoise, spec, NoPrior(), anny_body, src, {"sigma": 0.1, "mode": "regression"})
    assert na["na_reason"] == denoise.NO_REGRESSION and na["per_sequence"] == []
    assert denoise.na_reason(spec, SlerpBaseline()) and denoise.na_reason(spec, vposer) is None


def test_denoise_motion_hook_and_metric_plumbing(anny_body, motions):
    spec = load_table_spec("denoise")
    src = denoise.make_source(spec, anny_body, motions, seed=0)
    r = _run(denoise, spec, _EchoDenoiser(), anny_body, src, {"sigma": 0.2, "mode": "regression"})
    v = _values(r, spec)
    assert r["method"] == "denoise_motion(mode='regression')"
    assert v["v2v_mm"] == pytest.approx(v["obs_v2v_mm"], rel=1e-5)  # echoing the observation scores the observation
    assert v["accel_mps2"] == pytest.approx(v["obs_accel_mps2"], rel=1e-4)


# -------------------------------------------------------------------------------- inbetween

def test_slerp_baseline_exact_on_observed_frames(anny_body, motions):
    spec = load_table_spec("inbetween")
    src = inbetween.make_source(spec, anny_body, motions, seed=0)
    clean = src.clean(["a", "b"])
    gap = 15
    targets, idx, key, _ = inbetween.observation(clean, spec, gap)
    adapter = SlerpBaseline()
    lat = adapter.encode_motion(targets.init_rotations, targets.init_trans, targets.timestamps)
    state = motion_fit.init_motion_state(adapter, anny_body, targets, torch.Generator().manual_seed(0), "cpu", latents=lat)
    rot, trans = motion_fit.decode_parameters(state, clean.timestamps)
    assert torch.allclose(rot[:, idx], clean.rotations[:, idx], atol=1e-5)
    assert torch.allclose(trans[:, idx], clean.trans[:, idx], atol=1e-6)
    # the missing frames are the SLERP / LERP between frame 9 and the key frame
    w = (torch.arange(10, key, dtype=torch.float64) - 9) / (key - 9)
    R = slerp_matrices(clean.rotations[:, 9:10], clean.rotations[:, key:key + 1], w[None, :, None].float())
    assert torch.allclose(rot[:, 10:key], R, atol=1e-5)
    lin = clean.trans[:, 9:10] + w[None, :, None].float() * (clean.trans[:, key:key + 1] - clean.trans[:, 9:10])
    assert torch.allclose(trans[:, 10:key], lin, atol=1e-5)


def test_inbetween_units(anny_body, motions, vposer):
    spec = load_table_spec("inbetween")
    src = inbetween.make_source(spec, anny_body, motions, seed=0)
    results = {a.name: _run(inbetween, spec, a, anny_body, src, {"gap": 5}) for a in (SlerpBaseline(), NoPrior(), vposer)}
    fps = {r["fingerprint"] for r in results.values()}
    assert len(fps) == 1  # the same observation for every prior
    for name, r in results.items():
        assert r["na_reason"] is None and r["per_sequence"][0]["frames"] == 5
        v = _values(r, spec)
        assert all(math.isfinite(x) and x >= 0 for x in v.values()), (name, v)
    assert _values(results["slerp"], spec)["mpjpe_mm"] > 0
    assert results["slerp"]["fit_log"] == [] and results["no-prior"]["fit_log"]
    with pytest.raises(ValueError, match="outside"):
        inbetween.observed_frames(10, 55, 60)


# -------------------------------------------------------------------------------- reconstruction

def test_reconstruction_units(anny_body, motions, vposer):
    spec = load_table_spec("reconstruction")
    src = reconstruction.make_source(spec, anny_body, motions, seed=0)
    assert reconstruction.na_reason(spec, NoPrior()) == reconstruction.NO_ENCODER
    assert reconstruction.na_reason(spec, SlerpBaseline())
    assert reconstruction.na_reason(spec, vposer) is None
    r = _run(reconstruction, spec, vposer, anny_body, src, {"window": 2.0})
    v = _values(r, spec)
    assert all(math.isfinite(x) for x in v.values()) and v["mpjpe_mm"] > 0 and r["per_sequence"][0]["frames"] == 60
    # an exact encoder (the SLERP adapter's identity) with the ground truth's root and translation
    # reconstructs the motion: every error is zero, the acceleration is the ground truth's
    exact = _values(_run(reconstruction, spec, SlerpBaseline(), anny_body, src, {"window": 2.0}), spec)
    assert exact["mpjpe_mm"] < 1e-2 and exact["mpjpe_local_mm"] < 1e-2 and exact["v2v_mm"] < 1e-2
    assert exact["accer_mps2"] < 1e-2 and v["mpjpe_local_mm"] > 0
    assert exact["accel_mps2"] == pytest.approx(exact["gt_accel_mps2"], rel=1e-3)
    assert exact["gt_travel_mm"] == pytest.approx(v["gt_travel_mm"])
    # a prior given the ground truth's translation has no root error of its own: n/a with its reason (v3)
    assert "root_mm" not in exact and "root_mm" not in v
    assert r["per_sequence"][0]["na"] == {"root_m": reconstruction.ROOT_FROM_GROUND_TRUTH}


def test_root_path_errors_by_hand():
    # ground truth: the root walks 1 m along x in 3 equal steps; the decoded root stays 0.1 m to the side
    # for the first two frames and lands on the ground truth for the last two
    gt = torch.zeros(1, 4, 2, 3)
    gt[0, :, 0, 0] = torch.tensor([0.0, 1 / 3, 2 / 3, 1.0])
    dec = gt.clone()
    dec[0, :2, 0, 2] += 0.1
    dec[0, :, 1] += 5.0  # other joints do not count
    root, travel = reconstruction.root_path_errors(dec, gt)
    assert root == pytest.approx([0.05]) and travel == pytest.approx([1.0])


# -------------------------------------------------------------------------------- end to end

def test_run_table_inbetween_smoke(anny_body, motions, tmp_path):
    from benchmark.run.table_run import run_table
    from benchmark.run.registry import register, registry, unregister

    data = tmp_path / "data"
    for sid, m in motions.items():
        m.save(data / f"{sid}.npz")
    added = "slerp" not in registry()
    if added:
        register("slerp", SlerpBaseline)
    try:
        spec = load_table_spec("inbetween")
        profile = {**get_profile("smoke"), "steps": 2}
        out = run_table(spec, profile, ["slerp", "no-prior"], anny_body, "cpu", 0, tmp_path / "out", data=str(data))
    finally:
        if added:
            unregister("slerp")
    assert not out["failures"]
    files = {k: str(v) for k, v in out["files"].items()}
    table = json.loads(open(next(v for v in files.values() if v.endswith(".json"))).read())
    assert table["table"] == "inbetween" and table["counts"]["units_done"] == 8
    for row in table["rows"]:
        for cell in row["cells"]:
            assert cell.get("na_reason") is None and math.isfinite(cell["mpjpe_mm"]) and cell["frames"] == cell["gap"]


def test_a_motion_whose_last_frame_ends_before_the_windows_is_skipped(tmp_path, anny_body, caplog):
    """A 2.0 s motion at 24 fps (48 frames) ends at 1.958 s: resampled to 30 fps it cannot hold a 2 s
    window's 60th frame (1.967 s). It is skipped with a warning, the others run; alone it is an error
    naming the span it needs (it used to fail every unit with 'outside the motion')."""
    import numpy as np

    def write(name, frames, fps):
        np.savez(tmp_path / name, poses=np.zeros((frames, 22, 3), np.float32), trans=np.zeros((frames, 3), np.float32),
                 timestamps=np.arange(frames) / fps, fps=np.float64(fps), source=np.str_(name))

    write("m24.npz", 48, 24.0)
    write("m30.npz", 90, 30.0)
    spec = load_table_spec("inbetween")
    with caplog.at_level("WARNING"):
        motions = motion_fit.load_table_motions(spec, str(tmp_path), anny_body)
    assert sorted(motions) == ["m30.npz"] and "m24.npz" in caplog.text
    (tmp_path / "m30.npz").unlink()
    with pytest.raises(ValueError, match=r"no motion spans the 1.967 s .* m24.npz: 1.958 s"):
        motion_fit.load_table_motions(spec, str(tmp_path), anny_body)
    src = inbetween.make_source(spec, anny_body, {"ok": motions["m30.npz"]}, seed=0)
    assert src.clean(["ok"]).num_frames == 60
