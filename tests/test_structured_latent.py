"""Structured latent space (Marsot et al. 3DV 2022): cycles, representation, GradNorm, network,
adapter, training, checkpoints and ONNX export. Tiny sizes, no split, no body model."""

from __future__ import annotations

import math

import numpy as np
import pytest
import roma
import torch

from benchmark.core.motion import Motion
from benchmark.synthetic import cycles as cyc
from priors.base import FitBatch
from priors.structured_latent import (
    GradNorm, PAPER_CHUM_CONFIG, PAPER_CONFIG, StructuredLatentCVAE, StructuredLatentPrior, train_structured_latent,
)
from priors.structured_latent import checkpoint
from priors.structured_latent import representation as rep
from priors.structured_latent.checkpoint import CHECKPOINT_NAME
from priors.structured_latent.train import build_anchor_data

TINY = {"latent": 8, "shape_dim": 6, "channels": 8, "hidden": 16}


# -- helpers ------------------------------------------------------------------------------------
def _plan_motion(fps: float = 30.0):
    from benchmark.synthetic.generator import Segment, SequencePlan, SyntheticSequence
    from benchmark.synthetic.rest import CanonicalSkeletons
    from benchmark.synthetic.subjects import Style, Subject

    subject = Subject("t", (0.0, 0.67, 0.5, 0.5, 0.45, 0.5), Style())
    plan = SequencePlan(subject=subject, seed=1, phase0=0.3, kind="test", segments=[
        Segment("walk", 0.0, 2.6, {"speed": 1.0, "direction": "forward", "turn_rate": 0.0}),
        Segment("sidestep", 2.6, 4.6, {"mirror": False, "width": 1.0}),
    ])
    seq = SyntheticSequence(plan, CanonicalSkeletons().rest_skeleton(subject.phenotype))
    return plan, seq, seq.to_motion(fps, meta={"subject_info": subject.to_meta()})


def _gait_motion(freq: float = 1.2, duration: float = 4.0, fps: float = 30.0, speed: float = 1.0, seed: int = 0) -> Motion:
    """Handmade gait-like motion: opposite sinusoidal hip flexion, knees, arms, forward walk."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(int(round(duration * fps)), dtype=torch.float64) / fps
    ph = 2 * math.pi * freq * t.float()
    poses = torch.zeros(len(t), 22, 3)
    poses[:, 1, 0] = -0.4 * torch.sin(ph)  # hips: rotation about x (negative = thigh forward)
    poses[:, 2, 0] = 0.4 * torch.sin(ph)
    poses[:, 4, 0] = 0.3 * (1 + torch.sin(ph + 1.0))
    poses[:, 5, 0] = 0.3 * (1 - torch.sin(ph + 1.0))
    poses[:, 16, 2] = -1.2 + 0.2 * torch.sin(ph)
    poses[:, 17, 2] = 1.2 + 0.2 * torch.sin(ph)
    poses[:, 0, 1] = 0.3 + 0.05 * torch.rand(1, generator=g)  # a heading, removed by the alignment
    trans = torch.stack([0.1 * t.float(), 0.02 * torch.sin(2 * ph), speed * t.float()], dim=-1)
    return Motion(poses=poses, trans=trans, timestamps=t, shape=torch.rand(6, generator=g), body="anny", source=f"hand:{seed}")


def _tiny_adapter(seed: int = 0) -> StructuredLatentPrior:
    torch.manual_seed(seed)
    net = StructuredLatentCVAE(**TINY)
    net.set_normalisation([-1.0, -0.5, -1.0], [1.0, 0.5, 5.0], 4.0)
    return StructuredLatentPrior.from_network(net)


# -- cycles ---------------------------------------------------------------------------------------
def test_gait_phase_track_matches_the_generator():
    plan, seq, _ = _plan_motion()
    grid, phase = cyc.gait_phase_track(plan)
    assert torch.equal(grid, seq._grid)
    assert torch.allclose(phase, seq._phase, atol=1e-12)


def test_plan_cycles_on_a_generated_sequence():
    plan, seq, motion = _plan_motion()
    found = cyc.find_cycles(motion)
    gait = [c for c in found if c.kind == "gait"]
    local = [c for c in found if c.kind == "local"]
    assert gait and local and len(found) == len(gait) + len(local)
    walk_period = 1 / plan.subject.style.cadence  # speed 1
    for c in gait:
        assert c.action == "walk" and c.duration == pytest.approx(walk_period, rel=1e-3)
        assert c.end <= 2.6 - 0.25 + 1e-9  # never into the walk -> sidestep cross-fade
        phase = np.interp([c.start, c.end], seq._grid.numpy(), seq._phase.numpy())
        start = {"left_strike": 0.0, "right_strike": 0.5}[c.start_event]
        frac = (phase - start) % 1.0
        assert np.minimum(frac, 1.0 - frac).max() < 1e-6  # starts and ends on the foot strike
    for c in local:
        assert c.action == "sidestep" and c.start >= 2.6 + 0.25 - 1e-9 and c.end <= 4.6 + 1e-9
        assert c.duration == pytest.approx(1 / 0.9, rel=1e-6)  # sidestep frequency 0.9 * tempo (1.0)
    assert all(cyc.MIN_CYCLE_S <= c.duration <= cyc.MAX_CYCLE_S for c in found)
    assert [c.action for c in cyc.find_cycles(motion, actions=["walk"])] == ["walk"] * len(gait)


def test_cycle_windows_are_resampled_anchor_motions():
    _, _, motion = _plan_motion()
    out = cyc.cycle_windows([motion], anchors=100)
    assert len(out) == len(cyc.find_cycles(motion))
    w = out[0]
    info = w.meta["cycle"]
    assert w.num_frames == 100 and w.poses.shape == (100, 22, 3) and w.shape is not None
    assert float(w.timestamps[0]) == 0.0 and float(w.timestamps[-1]) == pytest.approx(info["end"] - info["start"])
    assert info["motion_index"] == 0 and info["kind"] in ("gait", "local")
    # the anchors are the source motion at start + t
    ref = motion.resample(info["start"] + w.timestamps)
    assert torch.allclose(roma.rotvec_to_rotmat(w.poses), roma.rotvec_to_rotmat(ref.poses), atol=1e-4)
    assert torch.allclose(w.trans, ref.trans, atol=1e-5)
    assert len(cyc.cycle_windows([motion], max_cycles=1)) == 1


def test_detected_cycles_and_missing_plan():
    m = _gait_motion(freq=1.2, duration=4.0)
    with pytest.raises(KeyError, match="no field 'actions'"):
        cyc.find_cycles(m, method="plan")
    found = cyc.find_cycles(m)  # auto: no plan in meta -> detection
    assert len(found) >= 3 and all(c.kind == "detected" for c in found)
    assert np.mean([c.duration for c in found]) == pytest.approx(1 / 1.2, rel=0.02)
    flat = _gait_motion(freq=1.2)
    flat.poses[:] = 0.0
    assert cyc.detect_cycles(flat) == []


# -- representation -------------------------------------------------------------------------------
def test_representation_round_trip_and_alignment():
    g = torch.Generator().manual_seed(0)
    B, n = 3, rep.ANCHORS
    R = roma.rotvec_to_rotmat(torch.randn(B, n, 22, 3, generator=g) * 0.7)
    R[:, :, list(rep.FOOT_JOINTS)] = torch.eye(3)
    trans = torch.randn(B, n, 3, generator=g)
    tau = torch.sort(torch.rand(B, n, generator=g) * 2.5, dim=1).values
    tau = tau - tau[:, :1]
    tmin, tmax, tau_max = torch.tensor([-3.0, -2.0, -3.0]), torch.tensor([3.0, 2.0, 3.0]), 3.0
    chi = rep.motion_to_chi(R, trans, tau, tmin, tmax, tau_max)
    assert chi.shape == (B, n, 124)
    R2, t2, tau2 = rep.chi_to_motion(chi, tmin, tmax, tau_max)
    assert torch.allclose(R2, R, atol=1e-5) and torch.allclose(t2, trans, atol=1e-5) and torch.allclose(tau2, tau.float(), atol=1e-6)
    assert torch.allclose(rep.motion_to_chi(R2, t2, tau2, tmin, tmax, tau_max), chi, atol=1e-5)
    x = torch.randn(50, 6, generator=g)
    from benchmark.core.rotations import sixd_to_matrix

    assert torch.allclose(rep.sixd_columns_to_matrix(x), sixd_to_matrix(x, "columns"), atol=1e-6)
    # identity rotations give zeros in the pose channels (the paper's identity removal, columns layout)
    eye = torch.eye(3).expand(1, n, 22, 3, 3)
    assert rep.motion_to_chi(eye, torch.zeros(1, n, 3), torch.zeros(1, n), tmin, tmax, tau_max)[..., rep.POSE].abs().max() == 0
    # alignment: first frame faces +z at x = z = 0; the inverse restores the input
    Rc, tc, yaw0, off = rep.canonicalise(R, trans)
    assert rep.heading(Rc[:, 0, 0]).abs().max() < 1e-5
    assert tc[:, 0, [0, 2]].abs().max() < 1e-6 and torch.allclose(tc[:, 0, 1], trans[:, 0, 1], atol=1e-6)
    Rb, tb = rep.uncanonicalise(Rc, tc, yaw0, off)
    assert torch.allclose(Rb, R, atol=1e-5) and torch.allclose(tb, trans, atol=1e-5)


# -- GradNorm -------------------------------------------------------------------------------------
def test_gradnorm_balances_gradient_norms():
    torch.manual_seed(0)
    shared = torch.nn.Linear(4, 8)
    heads = torch.nn.ModuleList([torch.nn.Linear(8, 1), torch.nn.Linear(8, 1)])
    gn = GradNorm(["small", "large"], alpha=1.5, lr=0.05)
    opt = torch.optim.Adam([*shared.parameters(), *heads.parameters()], lr=1e-3)
    x = torch.randn(64, 4)
    y = torch.randn(64, 2)
    for _ in range(30):
        h = torch.tanh(shared(x))
        losses = {"small": (heads[0](h)[:, 0] - y[:, 0]).square().mean(),
                  "large": 100.0 * (heads[1](h)[:, 0] - y[:, 1]).square().mean()}
        total = gn.combine(losses, shared.weight)
        opt.zero_grad()
        total.backward()
        opt.step()
    w = gn.as_dict()
    assert w["large"] < 1.0 < w["small"]  # the term with the larger gradient is weighed down
    assert sum(w.values()) == pytest.approx(2.0, abs=1e-5)
    with pytest.raises(KeyError, match="large"):
        gn.combine({"small": losses["small"]}, shared.weight)


# -- adapter --------------------------------------------------------------------------------------
def _batch(B: int = 2, window: float = 4.0) -> FitBatch:
    obs_t = torch.linspace(0.0, 3.9, 6, dtype=torch.float64).expand(B, 6)
    return FitBatch(points=torch.zeros(B, 6, 4, 3), lengths=torch.full((B, 6), 4), timestamps=obs_t, window_s=window,
                    output_timestamps=(torch.arange(120, dtype=torch.float64) / 30).expand(B, 120))


def test_declaration_and_paper_network():
    a = StructuredLatentPrior
    assert a.name == "structured-latent" and a.window.kind == "continuous"
    assert a.encodes_translation and a.encodes_root_orientation and a.heading_normalised and a.shape_conditioned
    assert a.has_encoder and a.sixd_layout == "columns" and a.joints == tuple(j for j in range(22) if j not in (10, 11))
    net = a.paper_network()
    assert net.latent == PAPER_CONFIG["latent"] == 64 and net.shape_dim == 8
    assert a.paper_network(latent=256).latent == PAPER_CHUM_CONFIG["latent"] == 256


def test_decode_shapes_orthonormal_times_and_gradients():
    a = _tiny_adapter()
    batch = _batch(B=2, window=4.0)
    lat = {k: v.clone().requires_grad_(True) for k, v in a.init_latents(batch, torch.Generator().manual_seed(0)).items()}
    assert lat["z"].shape == (2, TINY["latent"]) and torch.equal(lat["window_s"], torch.full((2, 1), 4.0))
    shape = torch.full((2, 6), 0.5, requires_grad=True)
    dec = a.decode(lat, batch.output_timestamps, shape)
    assert dec.rotations.shape == (2, 120, 22, 3, 3) and dec.trans.shape == (2, 120, 3)
    eye = torch.eye(3)
    assert (dec.rotations.transpose(-1, -2) @ dec.rotations - eye).abs().max() < 1e-5
    assert torch.allclose(torch.det(dec.rotations), torch.ones(2, 120, 22), atol=1e-5)
    assert torch.equal(dec.rotations[:, :, [10, 11]], eye.expand(2, 120, 2, 3, 3))  # feet are not modelled
    at = dec.extra["anchor_times"]
    assert at.shape == (2, 100) and (at.diff(dim=1) >= 0).all() and at[:, 0].abs().max() == 0
    assert torch.allclose(at[:, -1], torch.full((2,), 4.0))
    anchors, tau = a.decode_anchors(lat, shape)
    assert anchors.rotations.shape == (2, 100, 22, 3, 3) and anchors.trans.shape == (2, 100, 3) and tau.shape == (2, 100)
    assert (tau >= 0).all() and (tau.diff(dim=1) >= 0).all() and (tau <= a.net.tau_max * 1.5 + 1).all()
    loss = dec.trans.square().sum() + (dec.rotations - eye).square().sum() + a.prior_term(lat).sum()
    loss.backward()
    assert torch.isfinite(lat["z"].grad).all() and lat["z"].grad.abs().sum() > 0
    assert torch.isfinite(shape.grad).all() and shape.grad.abs().sum() > 0
    assert lat["window_s"].grad is None  # read detached: a constant of the fit
    assert torch.allclose(a.prior_term(lat), lat["z"].detach().square().sum(-1))
    with pytest.raises(ValueError, match="shape must be"):
        a.decode(lat, batch.output_timestamps, torch.zeros(2, 10))


def test_encode_motion_gives_posterior_means():
    a = _tiny_adapter()
    m = _gait_motion(duration=2.0)
    R, tr, ts = m.rotmats()[None].expand(2, -1, -1, -1, -1), m.trans[None].expand(2, -1, -1), m.timestamps[None].expand(2, -1)
    lat = a.encode_motion(R, tr, ts)
    assert lat["z"].shape == (2, TINY["latent"]) and torch.allclose(lat["z"][0], lat["z"][1])
    assert lat["window_s"][0, 0] == pytest.approx(float(m.timestamps[-1] - m.timestamps[0]))
    dec = a.decode(lat, ts - ts[:, :1])
    assert dec.rotations.shape == (2, m.num_frames, 22, 3, 3)
    # the canonical frame is independent of where the motion starts and which way it faces
    yaw = roma.rotvec_to_rotmat(torch.tensor([0.0, 1.0, 0.0]))
    R2 = R.clone()
    R2[:, :, 0] = yaw @ R[:, :, 0]
    lat2 = a.encode_motion(R2, tr @ yaw.T + torch.tensor([5.0, 0.0, -2.0]), ts)
    assert torch.allclose(lat2["z"], lat["z"], atol=1e-4)


# -- training and checkpoints ------------------------------------------------------------------------
def test_tiny_training_decreases_the_loss_and_round_trips_the_checkpoint(tmp_path):
    motions = [_gait_motion(freq=f, duration=3.0, speed=s, seed=i) for i, (f, s) in enumerate([(1.0, 1.0), (1.4, 2.0), (0.9, 0.6)])]
    data = build_anchor_data(motions, find_cycles=cyc.find_cycles, windows_s=(2.0,), window_stride_s=0.5)
    assert data["counts"]["cycles"] > 0 and data["counts"]["windows"] > 0
    model, record = train_structured_latent(tmp_path, steps=60, data=data, val_data=build_anchor_data(motions[:1], find_cycles=cyc.find_cycles),
                                            config=TINY, log_every=10, phase2_fraction=0.25, batch1=8, batch2=8)
    h1 = record["phase1"]["history"]
    assert h1[-1]["loss"] < h1[0]["loss"] and h1[-1]["pose"] < h1[0]["pose"]
    assert record["steps"] == {"total": 60, "phase1": 45, "phase2": 15}
    assert set(record["phase2"]["gradnorm_weights"]) == {"spatial", "time"}
    assert record["phase2"]["final_val"]["joint_error_mm"] > 0
    assert (tmp_path / "structured_latent.json").is_file()
    a = StructuredLatentPrior(weights=str(tmp_path / CHECKPOINT_NAME))
    assert not any(p.requires_grad for p in a.parameters())
    for k, v in model.state_dict().items():
        assert torch.equal(a.net.state_dict()[k], v)
    assert a.net.tau_max == pytest.approx(max(float(data["tau"].max()), 0))
    # strict loading: a missing or an unexpected key is an error naming it
    ckpt = torch.load(tmp_path / CHECKPOINT_NAME, weights_only=True)
    bad = {"state_dict": dict(ckpt["state_dict"]), "config": ckpt["config"]}
    bad["state_dict"].pop("enc_mu.weight")
    torch.save(bad, tmp_path / "missing.pt")
    with pytest.raises(KeyError, match="enc_mu.weight"):
        checkpoint.load(tmp_path / "missing.pt")
    bad["state_dict"] = {**ckpt["state_dict"], "extra.weight": torch.zeros(1)}
    torch.save(bad, tmp_path / "extra.pt")
    with pytest.raises(ValueError, match="extra.weight"):
        checkpoint.load(tmp_path / "extra.pt")
    with pytest.raises(FileExistsError, match="--force"):
        StructuredLatentPrior.train_embedded(out_dir=tmp_path)


def test_official_weights_and_missing_embedded_weights_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown.*checkpoint file format"):
        StructuredLatentPrior(size="paper", weights=str(tmp_path / "official.pt"))
    with pytest.raises(ValueError, match="no loader for official weights"):
        StructuredLatentPrior(size="paper")
    with pytest.raises(FileNotFoundError, match="no such file; check the path given with --weights"):
        StructuredLatentPrior(weights=str(tmp_path / "nope.pt"))
    with pytest.raises(ValueError, match="unknown size"):
        StructuredLatentPrior(size="huge")


def test_onnx_export_parity(tmp_path):
    onnx = pytest.importorskip("onnx")  # noqa: F841
    ort = pytest.importorskip("onnxruntime")
    a = _tiny_adapter()
    spec = a.export_decoder()
    path = tmp_path / "sls.onnx"
    torch.onnx.export(spec.module, spec.example_inputs, str(path), input_names=spec.input_names,
                      output_names=spec.output_names,
                      dynamic_axes={n: {0: "batch"} for n in [*spec.input_names, *spec.output_names]},
                      opset_version=17, dynamo=False)
    g = torch.Generator().manual_seed(1)
    z = torch.randn(3, TINY["latent"], generator=g)
    shape = torch.rand(3, 6, generator=g)
    with torch.no_grad():
        ref = spec.module(z, shape)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    out = sess.run(None, {"z": z.numpy(), "shape": shape.numpy()})
    assert [o.shape for o in out] == [(3, 100, 22, 3, 3), (3, 100, 3), (3, 100)]
    for o, r in zip(out, ref):
        np.testing.assert_allclose(o, r.numpy(), rtol=1e-3, atol=1e-5)


class _Killed(Exception):
    """Stands for the process being killed mid-training."""


def test_training_checkpoints_and_resumes_exactly(tmp_path, monkeypatch):
    """`train structured-latent --resume` (it trains with its own two-phase loop): an interrupted
    training continues from its last saved state and ends with the uninterrupted run's weights."""
    from priors import training_state

    motions = [_gait_motion(freq=f, duration=3.0, speed=s, seed=i) for i, (f, s) in enumerate([(1.0, 1.0), (1.4, 2.0)])]
    data = build_anchor_data(motions, find_cycles=cyc.find_cycles, windows_s=(2.0,), window_stride_s=0.5)

    def train(state_dir, resume=False):
        with training_state.training_session(state_dir, resume=resume, checkpoint_every=5):
            return train_structured_latent(None, steps=24, data=data, config=TINY, log_every=5, phase2_fraction=0.25,
                                           batch1=8, batch2=8)[0]

    full = train(tmp_path / "a")
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["loop0.pt", "loop1.pt"]  # one per phase
    save, saves = training_state.save_state, []

    def save_then_die(path, state):
        save(path, state)
        saves.append(state["step"])
        if len(saves) == 2:
            raise _Killed

    monkeypatch.setattr(training_state, "save_state", save_then_die)
    with pytest.raises(_Killed):
        train(tmp_path / "b")  # killed after phase 1's state at step 10
    monkeypatch.undo()
    resumed = train(tmp_path / "b", resume=True)
    for k, v in full.state_dict().items():
        assert torch.equal(resumed.state_dict()[k], v), k
