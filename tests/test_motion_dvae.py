"""Motion-DVAE: geometry of the state, the network, its training, the adapter, denoising, loaders, ONNX."""

import json
import math

import pytest
import roma
import torch

from benchmark.core.frames import heading
from benchmark.core.skeleton import SMPL_LIKE_REST_JOINTS
from priors import training
from priors.base import FitBatch
from priors.motion_dvae import MotionDVAEPrior
from priors.checkpoints import load_state_strict
from priors.motion_dvae.checkpoint import load_official
from priors.motion_dvae.model import (
    EMBEDDED_CONFIG,
    PAPER_CONFIG,
    MotionDVAE,
)
from priors.motion_dvae.states import (
    STATE_DIM,
    body_points,
    canonical_poses,
    canonicalise,
    motion_state,
    noisy_poses,
    pose_to_state,
    state_to_motion,
    uncanonicalise,
    unwrap_rotvec,
    windows_to_state,
)
from priors.motion_dvae.train import train_motion_dvae

TINY = {"z_dim": 8, "hidden": 64, "mlp_hidden": 64}
REST = torch.tensor(SMPL_LIKE_REST_JOINTS)


def smooth_windows(n: int, frames: int, seed: int = 0) -> torch.Tensor:
    """(n, frames, 69) raw windows of smooth synthetic motion: sinusoidal joint rotations, a turning
    root and a walk in a random world direction."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(frames, dtype=torch.float32) / 30.0
    amp = torch.rand(n, 1, 22, 3, generator=g) * 0.4
    freq = 0.5 + torch.rand(n, 1, 22, 3, generator=g)
    phase = torch.rand(n, 1, 22, 3, generator=g) * 2 * math.pi
    aa = amp * torch.sin(2 * math.pi * freq * t[None, :, None, None] + phase)
    yaw0 = torch.rand(n, 1, generator=g) * 2 * math.pi - math.pi
    yaw = yaw0 + 0.5 * t[None]  # turning
    R = roma.rotvec_to_rotmat(torch.stack([torch.zeros_like(yaw), yaw, torch.zeros_like(yaw)], -1))
    root = R @ roma.rotvec_to_rotmat(aa[:, :, 0])
    aa = torch.cat([roma.rotmat_to_rotvec(root)[:, :, None], aa[:, :, 1:]], 2)
    step = torch.stack([torch.sin(yaw), torch.zeros_like(yaw), torch.cos(yaw)], -1) * (0.8 / 30.0)
    trans = torch.randn(n, 1, 3, generator=g) + torch.cumsum(step, 1)
    trans[..., 1] = 0.02 * torch.sin(2 * math.pi * t)[None]
    return torch.cat([aa.flatten(-2), trans], -1)


@pytest.fixture(scope="module")
def trained():
    """A tiny Motion-DVAE trained for a few steps of both phases (seconds), and its record."""
    windows = smooth_windows(48, 12, seed=1)
    model, record = train_motion_dvae(None, steps=60, denoise_steps=8, seed=0, config=TINY, batch_size=16, lr=3e-3,
                                      windows=windows, val_windows=smooth_windows(8, 12, seed=2), rest_joints=REST,
                                      log_every=10)
    return model, record, windows


@pytest.fixture(scope="module")
def adapter(trained):
    return MotionDVAEPrior.from_network(trained[0])


# -- geometry ---------------------------------------------------------------------------------
def test_canonical_frame_round_trip():
    w = smooth_windows(4, 10)
    rot = roma.rotvec_to_rotmat(w[..., :66].unflatten(-1, (22, 3)))
    trans = w[..., 66:]
    rot_c, trans_c, yaw, origin = canonicalise(rot, trans)
    assert torch.allclose(trans_c[:, 0, [0, 2]], torch.zeros(4, 2), atol=1e-5)
    assert torch.allclose(trans_c[:, 0, 1], trans[:, 0, 1], atol=1e-6)  # height kept
    assert heading(rot_c[:, 0, 0]).abs().max() < 1e-5
    assert torch.allclose(rot_c[:, :, 1:], rot[:, :, 1:])
    r2, t2 = uncanonicalise(rot_c, trans_c, yaw, origin)
    assert torch.allclose(r2, rot, atol=1e-5) and torch.allclose(t2, trans, atol=1e-5)
    # rigid: pairwise distances of the body points are unchanged
    p, pc = body_points(rot, trans, REST), body_points(rot_c, trans_c, REST)
    assert torch.allclose(torch.cdist(p[:, 3], p[:, 7]), torch.cdist(pc[:, 3], pc[:, 7]), atol=1e-4)


def test_state_layout_and_unwrap():
    w = smooth_windows(3, 8)
    pos = canonical_poses(w)
    s = pose_to_state(pos)
    assert pos.shape == (3, 8, 69) and s.shape == (3, 8, STATE_DIM)
    assert torch.allclose(s[:, 1:, 69:], (pos[:, 1:] - pos[:, :-1]) * 30.0)
    assert torch.allclose(s[:, 0, 69:], s[:, 1, 69:])
    rot, trans = state_to_motion(s)
    rot_c, trans_c, _, _ = canonicalise(roma.rotvec_to_rotmat(w[..., :66].unflatten(-1, (22, 3))), w[..., 66:])
    assert torch.allclose(rot, rot_c, atol=1e-5) and torch.allclose(trans, trans_c, atol=1e-6)
    assert torch.allclose(motion_state(rot_c, trans_c), s, atol=1e-4)
    # a rotation crossing angle pi stays continuous once unwrapped
    ang = torch.linspace(2.9, 3.4, 6)
    aa = torch.stack([torch.zeros_like(ang), ang, torch.zeros_like(ang)], -1)
    wrapped = roma.rotmat_to_rotvec(roma.rotvec_to_rotmat(aa))[None]
    un = unwrap_rotvec(wrapped)
    assert (un[0, 1:] - un[0, :-1]).norm(dim=-1).max() < 0.2
    assert torch.allclose(roma.rotvec_to_rotmat(un), roma.rotvec_to_rotmat(wrapped), atol=1e-5)


def test_noisy_poses_are_canonical():
    pos = canonical_poses(smooth_windows(5, 6))
    noisy, sigma = noisy_poses(pos, torch.Generator().manual_seed(0))
    assert noisy.shape == pos.shape and ((sigma >= 0.05) & (sigma <= 0.25)).all()
    assert heading(roma.rotvec_to_rotmat(noisy[:, 0, 3:6])).abs().max() < 1e-5
    assert torch.allclose(noisy[:, 0, [0, 2]], torch.zeros(5, 2), atol=1e-6)
    assert (noisy[..., 6:] - pos[..., 6:]).abs().mean() > 0.02


# -- the network ------------------------------------------------------------------------------
def test_shapes_prior_sampling_and_paper_size():
    net = MotionDVAE(**TINY).eval()
    x0 = torch.randn(3, STATE_DIM)
    z = net.sample_prior(x0, 9, generator=torch.Generator().manual_seed(0))
    z2 = net.sample_prior(x0, 9, generator=torch.Generator().manual_seed(0))
    assert z.shape == (3, 9, 8) and torch.equal(z, z2)
    states = net.generate(x0, z)
    assert states.shape == (3, 10, STATE_DIM) and torch.allclose(states[:, 0], x0, atol=1e-5)
    nll = net.prior_nll(x0, z)
    assert nll.shape == (3,) and torch.isfinite(nll).all()
    xn = net.normalise(states)
    zq, qm, qlv = net.encoder(xn, xn[:, 0], sample=False)
    assert zq.shape == (3, 9, 8) and torch.equal(zq, qm)
    # the generative LSTM is one layer of hidden 1024 in the paper size, z is 48
    paper = MotionDVAEPrior.paper_network()
    assert paper.gen_rnn.hidden_size == 1024 and paper.z_dim == 48 and not paper.training
    counts = paper.parameter_counts()
    assert counts["total"] > 20_000_000 and counts["dvae (generative + encoder)"] < counts["total"]
    assert PAPER_CONFIG["z_dim"] == EMBEDDED_CONFIG["z_dim"] == 48


def test_training_decreases_the_loss(trained):
    model, record, _ = trained
    hist = record["phase_dvae"]["history"]
    assert all(math.isfinite(h["loss"]) for h in hist)
    assert hist[-1]["loss"] < hist[0]["loss"]
    assert hist[-1]["point_sq_m2"] < hist[0]["point_sq_m2"]
    assert hist[0]["beta"] < 1.0 and hist[-1]["beta"] == 1.0  # KL annealing
    dn = record["phase_denoise"]["history"]
    assert all(math.isfinite(h["loss"]) for h in dn)
    assert record["phase_dvae"]["final_val"] is not None and math.isfinite(record["phase_dvae"]["final_val"]["loss"])
    assert not any(p.requires_grad for p in model.parameters())
    json.dumps(record)  # the record is plain JSON


def test_denoising_phase_leaves_the_generative_model_untouched():
    windows = smooth_windows(16, 8, seed=3)
    torch.manual_seed(0)
    model, _ = train_motion_dvae(None, steps=3, denoise_steps=1, config=TINY, batch_size=8, windows=windows,
                                 rest_joints=REST, log_every=10)
    # retrain only the denoising phase from this state and compare the frozen parts
    before = {k: v.clone() for k, v in model.state_dict().items()}
    model.train()
    for m in (model.denoise_encoder, model.init_state, model.noise):
        for p in m.parameters():
            p.requires_grad_(True)
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-2)
    pos = canonical_poses(windows)
    noisy, _ = noisy_poses(pos, torch.Generator().manual_seed(0))
    states = pose_to_state(noisy)
    obs = body_points(*state_to_motion(states), model.rest_joints)
    loss = model.denoise_loss(states, obs, beta=1.0)["loss"]
    loss.backward()
    opt.step()
    after = model.state_dict()
    for k in before:
        changed = not torch.equal(before[k], after[k])
        frozen = k.split(".")[0] in ("gen_rnn", "prior_mean", "prior_logvar", "decoder", "encoder")
        if frozen:
            assert not changed, k
    assert any(not torch.equal(before[k], after[k]) for k in before if k.startswith("denoise_encoder"))


# -- the adapter ------------------------------------------------------------------------------
def _batch(B=2, window_s=2.0):
    n = 5
    return FitBatch(points=torch.zeros(B, n, 10, 3), lengths=torch.full((B, n), 10), timestamps=torch.linspace(0, 1.9, n).expand(B, n),
                    window_s=window_s, output_timestamps=(torch.arange(60) / 30.0).expand(B, -1))


def test_adapter_latents_decode_prior_term(adapter):
    assert adapter.window.kind == "fixed" and adapter.window.frames == 30 and adapter.window.fps == 30.0
    assert adapter.encodes_translation and adapter.encodes_root_orientation and adapter.heading_normalised
    lat = adapter.init_latents(_batch(window_s=4.0), torch.Generator().manual_seed(0))
    assert lat["x0n"].shape == (2, STATE_DIM) and lat["z"].shape == (2, 119, 8)  # 120-frame grid
    lat = adapter.init_latents(_batch(), torch.Generator().manual_seed(0))
    assert lat["z"].shape == (2, 59, 8)
    again = adapter.init_latents(_batch(), torch.Generator().manual_seed(0))
    assert torch.equal(lat["z"], again["z"])
    grid = (torch.arange(60, dtype=torch.float64) / 30.0).expand(2, -1)
    lat = {k: v.clone().requires_grad_(True) for k, v in lat.items()}
    dec = adapter.decode(lat, grid)
    assert dec.rotations.shape == (2, 60, 22, 3, 3) and dec.trans.shape == (2, 60, 3)
    eye = dec.rotations.transpose(-1, -2) @ dec.rotations
    assert (eye - torch.eye(3)).abs().max() < 1e-4
    assert torch.allclose(dec.trans[:, 0], adapter.net.unnormalise(lat["x0n"])[:, :3], atol=1e-6)
    prior = adapter.prior_term(lat)
    assert prior.shape == (2,) and torch.isfinite(prior).all()
    (dec.trans.square().sum() + dec.rotations.sum() + prior.sum()).backward()
    assert lat["x0n"].grad.abs().sum() > 0 and lat["z"].grad.abs().sum() > 0
    adapter.prior_term_kind = "l2"
    try:
        assert torch.allclose(adapter.prior_term(lat), lat["z"].detach().square().sum(-1).mean(-1))
    finally:
        adapter.prior_term_kind = "learned"
    with pytest.raises(ValueError, match="timestamps"):
        adapter.decode(lat, grid[:, :30])
    with pytest.raises(ValueError, match="revision 1.*x0n"):  # a raw first state under the old key is refused
        adapter.decode({"x0": lat["x0n"], "z": lat["z"]}, grid)
    with pytest.raises(ValueError, match="30 fps"):
        adapter.decode(lat, grid * 2)
    assert not any(p.requires_grad for p in adapter.parameters())


def _motion(windows, i=0):
    w = windows[i : i + 2]
    rot = roma.rotvec_to_rotmat(w[..., :66].unflatten(-1, (22, 3)))
    return rot, w[..., 66:], (torch.arange(w.shape[1], dtype=torch.float64) / 30.0).expand(2, -1)


def test_encode_then_decode(trained, adapter):
    _, _, windows = trained
    rot, trans, ts = _motion(windows)
    lat = adapter.encode_motion(rot, trans, ts)
    assert lat["x0n"].shape == (2, STATE_DIM) and lat["z"].shape == (2, 11, 8)
    dec = adapter.decode(lat, ts)
    rot_c, trans_c, _, _ = canonicalise(rot, trans)
    truth = body_points(rot_c, trans_c, REST)
    err = (body_points(dec.rotations, dec.trans, REST) - truth).norm(dim=-1).mean()
    rand = {"x0n": lat["x0n"], "z": torch.randn(lat["z"].shape, generator=torch.Generator().manual_seed(5))}
    err_rand = (body_points(*(lambda d: (d.rotations, d.trans))(adapter.decode(rand, ts)), REST) - truth).norm(dim=-1).mean()
    assert torch.isfinite(err) and err < err_rand
    assert torch.equal(adapter.encode_motion(rot, trans, ts)["z"], lat["z"])  # deterministic


def test_an_encoded_motion_is_held_to_the_training_support(trained):
    """A joint turned about axes the training data never turns (deviation at the floor) is read at
    its training mean in every frame, and a first state far outside the training spread is held
    within X0_HOLD deviations (translation excepted); the latents are encoded from the held states."""
    import copy

    from priors.motion_dvae.adapter import X0_HOLD
    from priors.motion_dvae.model import STATE_STD_FLOOR

    net = copy.deepcopy(trained[0])
    net.state_std[24:27] = STATE_STD_FLOOR  # joint 7: never turned in the data
    net.state_std[27:30] = 0.005  # joint 8: barely turned
    held = MotionDVAEPrior.from_network(net)
    rot, trans, ts = _motion(trained[2])
    turned = rot.clone()
    for j in (7, 8):
        turned[:, :, j] = roma.rotvec_to_rotmat(torch.tensor([0.0, 0.0, 0.05])) @ turned[:, :, j]
    xn = net.normalise(held._prepare(turned, trans, ts, "test")[0])
    assert xn[:, :, 24:30].abs().amax(dim=(1, 2)).min() > 10 * X0_HOLD  # far outside the spread unheld
    lat = held.encode_motion(turned, trans, ts)
    assert lat["x0n"][:, 3:].abs().max() <= X0_HOLD + 1e-6 and lat["x0n"][:, 27:30].abs().max() > X0_HOLD - 1e-6
    assert torch.equal(lat["x0n"][:, 24:27], torch.zeros(2, 3))  # at the training mean
    assert torch.equal(lat["x0n"][:, :3], xn[:, 0, :3])  # the translation is not held
    support = xn.clone()
    support[..., net.state_std <= STATE_STD_FLOOR] = 0.0
    assert torch.equal(lat["z"], net.infer(net.encoder, support, lat["x0n"], sample=False)[0])


def test_denoise_motion_modes(trained, adapter):
    _, _, windows = trained
    rot, trans, ts = _motion(windows, 2)
    g = torch.Generator().manual_seed(0)
    noisy = roma.rotvec_to_rotmat(roma.rotmat_to_rotvec(rot) + 0.1 * torch.randn(rot.shape[:-1], generator=g))
    before = {k: v.clone() for k, v in adapter.state_dict().items()}
    reg = adapter.denoise_motion(noisy, trans, ts, mode="regression")
    assert reg.rotations.shape == (2, 12, 22, 3, 3) and reg.trans.shape == (2, 12, 3)
    assert torch.equal(adapter.denoise_motion(noisy, trans, ts, mode="regression").rotations, reg.rotations)
    opt = adapter.denoise_motion(noisy, trans, ts, mode="optimisation", iterations=3)
    assert opt.rotations.shape == (2, 12, 22, 3, 3) and len(opt.extra["losses"]) == 3
    assert not torch.allclose(opt.rotations, reg.rotations)
    for k, v in adapter.state_dict().items():
        assert torch.equal(v, before[k]), k
    assert not any(p.requires_grad for p in adapter.parameters())
    # world frame: the output starts near the input's first position and heading
    assert (reg.trans[:, 0, [0, 2]] - trans[:, 0, [0, 2]]).abs().max() < 0.5
    # other timestamps (15 fps): resampled to 30 fps internally, returned at the given times
    ts15 = (torch.arange(6, dtype=torch.float64) / 15.0).expand(2, -1)
    out = adapter.denoise_motion(noisy[:, ::2], trans[:, ::2], ts15)
    assert out.rotations.shape == (2, 6, 22, 3, 3) and out.trans.shape == (2, 6, 3)
    with pytest.raises(ValueError, match="mode"):
        adapter.denoise_motion(noisy, trans, ts, mode="fast")


# -- checkpoints ------------------------------------------------------------------------------
def test_project_checkpoint_round_trip_and_refusals(trained, tmp_path):
    model, _, _ = trained
    path = training.save_checkpoint(tmp_path / "motion_dvae.pt", model.state_dict(), model.config)
    a = MotionDVAEPrior(size="embedded", weights=str(path))
    for k, v in model.state_dict().items():
        assert torch.equal(a.net.state_dict()[k], v)
    sd = dict(model.state_dict())
    sd.pop("decoder.net.0.weight")
    training.save_checkpoint(tmp_path / "bad.pt", sd, model.config)
    with pytest.raises(KeyError, match="decoder.net.0.weight"):
        MotionDVAEPrior(size="embedded", weights=str(tmp_path / "bad.pt"))
    with pytest.raises(FileNotFoundError, match="no such file; check the path given with --weights"):
        MotionDVAEPrior(size="embedded", weights=str(tmp_path / "missing.pt"))
    with pytest.raises(FileExistsError, match="--force"):
        MotionDVAEPrior.train_embedded(out_dir=tmp_path)


def test_official_weights_give_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown"):
        MotionDVAEPrior(size="paper", weights=None)
    foreign = tmp_path / "official.pt"
    torch.save({"model": {"dvae.rnn_h.weight_ih_l0": torch.zeros(4, 4)}}, foreign)
    with pytest.raises(NotImplementedError, match="key map"):
        MotionDVAEPrior(size="paper", weights=str(foreign))
    # with a key map, a file in another naming loads strictly
    net = MotionDVAE(**TINY)
    renamed = {f"official.{k}": v.clone() + 1 for k, v in net.state_dict().items()}
    torch.save({"state_dict": renamed}, tmp_path / "mapped.pt")
    target = MotionDVAE(**TINY)
    load_official(tmp_path / "mapped.pt", target, key_map=lambda k: k[len("official."):])
    assert torch.equal(target.decoder.net[0].weight, net.decoder.net[0].weight + 1)
    with pytest.raises(ValueError, match="shape"):
        bad = dict(net.state_dict())
        bad["state_std"] = torch.ones(3)
        load_state_strict(MotionDVAE(**TINY), bad, "test", "motion-dvae")


# -- ONNX -------------------------------------------------------------------------------------
def test_onnx_export_parity(adapter, tmp_path):
    ort = pytest.importorskip("onnxruntime")
    spec = adapter.export_decoder()
    path = tmp_path / "motion_dvae.onnx"
    torch.onnx.export(spec.module, spec.example_inputs, str(path), input_names=spec.input_names,
                      output_names=spec.output_names,
                      dynamic_axes={n: {0: "batch"} for n in spec.input_names + spec.output_names},
                      opset_version=17, dynamo=False)
    g = torch.Generator().manual_seed(3)
    x0 = adapter.net.normalise(adapter.net.x0_mean).expand(3, -1) + 0.1 * torch.randn(3, STATE_DIM, generator=g)
    z = torch.randn(3, *spec.example_inputs[1].shape[1:], generator=g)
    with torch.no_grad():
        ref = spec.module(x0, z)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    out = sess.run(None, {"x0n": x0.numpy(), "z": z.numpy()})
    for r, o in zip(ref, out):
        assert r.shape == o.shape
        assert torch.allclose(torch.from_numpy(o), r, rtol=1e-3, atol=1e-5)
    dec = adapter.decode({"x0n": x0, "z": z}, (torch.arange(z.shape[1] + 1, dtype=torch.float64) / 30).expand(3, -1))
    assert torch.allclose(dec.rotations, ref[0], atol=1e-5)


# -- the feedback wiring ----------------------------------------------------------------------
def test_feedback_encoder_reads_the_decoded_state(tmp_path):
    torch.manual_seed(0)
    plain = MotionDVAE(**dict(TINY, feedback=False)).eval()
    fb = MotionDVAE(**dict(TINY, feedback=True)).eval()
    fb.load_state_dict(plain.state_dict())  # the same parameters, two wirings
    with torch.no_grad():
        for m in (plain.decoder,):  # a non-zero decoder, so the decoded state moves off x_0
            m.net[-1].weight.normal_(0, 0.1)
        fb.load_state_dict(plain.state_dict())
        xn = torch.randn(3, 7, 138)
        z_p, m_p, _, h_p, x_p = plain.infer(plain.encoder, xn, xn[:, 0], sample=False)
        z_f, m_f, _, h_f, x_f = fb.infer(fb.encoder, xn, xn[:, 0], sample=False)
        # the step-by-step generative pass equals the one-call decode of the same z
        assert torch.allclose(x_f, fb.decode_normalised(xn[:, 0], z_f), atol=1e-5)
        assert torch.allclose(h_f, fb.gen_features(xn[:, 0], z_f), atol=1e-5)
        assert torch.allclose(x_p, plain.decode_normalised(xn[:, 0], z_p))
    # the first latent sees x_0 in both wirings; the next ones see the decoded state with feedback
    assert torch.allclose(m_f[:, 0], m_p[:, 0], atol=1e-6)
    assert not torch.allclose(m_f[:, 1:], m_p[:, 1:], atol=1e-4)
    # the wiring travels with the checkpoint; an older checkpoint without the key is the plain wiring
    path = training.save_checkpoint(tmp_path / "motion_dvae.pt", fb.state_dict(), fb.config)
    assert MotionDVAEPrior(size="embedded", weights=str(path)).net.feedback is True
    old = {k: v for k, v in fb.config.items() if k != "feedback"}
    path = training.save_checkpoint(tmp_path / "old.pt", fb.state_dict(), old)
    assert MotionDVAEPrior(size="embedded", weights=str(path)).net.feedback is False


def test_encoder_only_training_keeps_the_generative_model(tmp_path):
    windows = smooth_windows(16, 8, seed=3)
    base, _ = train_motion_dvae(None, steps=2, denoise_steps=1, config=TINY, batch_size=8, windows=windows,
                                rest_joints=REST, log_every=10)
    path = training.save_checkpoint(tmp_path / "motion_dvae.pt", base.state_dict(), base.config)
    model, record = train_motion_dvae(None, steps=3, denoise_steps=0, config=TINY, batch_size=8, windows=windows,
                                      rest_joints=REST, log_every=10, init_weights=path, init_denoise=True,
                                      train_generative=False, lr=1e-2, encoder_point_weight=400.0)
    before, after = base.state_dict(), model.state_dict()
    for k in before:
        part = k.split(".")[0]
        if part in ("gen_rnn", "prior_mean", "prior_logvar", "decoder", "dec_logvar", "denoise_encoder", "init_state", "noise"):
            assert torch.equal(before[k], after[k]), k
    assert any(not torch.equal(before[k], after[k]) for k in before if k.startswith("encoder."))
    assert record["phase_dvae"]["trained"] == ["encoder"] and record["phase_denoise"]["trained"] == []
    assert record["phase_dvae"]["point_weight"] == 400.0 and record["phase_dvae"]["validation_point_weight"] == 100.0
    with pytest.raises(ValueError, match="encoder-only"):
        train_motion_dvae(None, steps=1, denoise_steps=0, config=TINY, windows=windows, rest_joints=REST,
                          encoder_point_weight=400.0)
    with pytest.raises(ValueError, match="needs init_weights"):
        train_motion_dvae(None, steps=1, denoise_steps=0, config=TINY, windows=windows, rest_joints=REST,
                          train_generative=False)


def test_encoder_input_noise_trains_the_encoder_on_noisy_copies(tmp_path):
    windows = smooth_windows(16, 8, seed=3)
    pos = canonical_poses(windows)
    noisy, _ = noisy_poses(pos, torch.Generator().manual_seed(0), (0.05, 0.05), body_only=True)
    assert torch.equal(noisy[..., :6], pos[..., :6])  # translation and root as they were: the same canonical frame
    assert 0.03 < float((noisy[..., 6:] - pos[..., 6:]).std()) < 0.07
    assert torch.equal(noisy_poses(pos, None, (0.0, 0.0), body_only=True)[0], pos)
    # the loss reads the encoder's input from encoder_states; given the clean states, it is the clean loss
    torch.manual_seed(1)
    m = MotionDVAE(**dict(TINY, feedback=True)).eval()
    states = pose_to_state(pos[:2])
    pts = body_points(*state_to_motion(states), REST)
    with torch.no_grad():
        torch.manual_seed(2)
        plain = m.dvae_loss(states, pts, beta=1.0)
        torch.manual_seed(2)
        same = m.dvae_loss(states, pts, beta=1.0, encoder_states=states.clone())
        torch.manual_seed(2)
        other = m.dvae_loss(states, pts, beta=1.0, encoder_states=pose_to_state(noisy[:2]))
    assert torch.equal(plain["loss"], same["loss"]) and not torch.equal(plain["loss"], other["loss"])

    base, _ = train_motion_dvae(None, steps=1, denoise_steps=1, config=TINY, batch_size=8, windows=windows,
                                rest_joints=REST, log_every=10)
    path = training.save_checkpoint(tmp_path / "motion_dvae.pt", base.state_dict(), base.config)
    kw = dict(denoise_steps=0, config=TINY, batch_size=8, windows=windows, rest_joints=REST, log_every=10,
              init_weights=path, init_denoise=True, train_generative=False, lr=1e-2)
    model, record = train_motion_dvae(None, steps=2, encoder_input_noise=(0.0, 0.1), **kw)
    assert record["phase_dvae"]["encoder_input_noise_rad"] == [0.0, 0.1] and record["phase_dvae"]["trained"] == ["encoder"]
    before, after = base.state_dict(), model.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before if not k.startswith("encoder."))
    assert any(not torch.equal(before[k], after[k]) for k in before if k.startswith("encoder."))
    with pytest.raises(ValueError, match="encoder-only"):
        train_motion_dvae(None, steps=1, denoise_steps=0, config=TINY, windows=windows, rest_joints=REST,
                          encoder_input_noise=(0.0, 0.1))
    with pytest.raises(ValueError, match="0 <= lo <= hi"):
        train_motion_dvae(None, steps=1, **dict(kw, encoder_input_noise=(0.2, 0.1)))


# -- the residual input of the clean encoder --------------------------------------------------
def test_residual_encoder_starts_as_the_encoder_without_it(tmp_path):
    torch.manual_seed(0)
    fb = MotionDVAE(**dict(TINY, feedback=True)).eval()
    with torch.no_grad():
        fb.decoder.net[-1].weight.normal_(0, 0.1)  # a decoder that moves off x_0
    res = MotionDVAE(**dict(TINY, feedback=True, encoder_residual=True)).eval()
    missing = res.load_state_dict(fb.state_dict(), strict=False).missing_keys
    assert sorted(missing) == ["encoder.res_logvar.weight", "encoder.res_mean.weight"]
    xn = torch.randn(3, 7, 138)
    with torch.no_grad():
        assert torch.equal(res.encode_means(xn), fb.encode_means(xn))  # zero residual weights: the same encoder
        res.encoder.res_mean.weight.normal_(0, 0.1)
        z = res.encode_means(xn)
        # the heads read target minus decoded pose: at t = 1 that is x_1 - x_0 (the decoded frame 0 is x_0)
        gap = (xn[:, 1, :69] - xn[:, 0, :69]).clamp(-3, 3)
        assert not torch.allclose(z[:, 0], fb.encode_means(xn)[:, 0])
        state, heads = res.encoder.start(xn, xn[:, 0])
        assert torch.allclose(z[:, 0], res.encoder.posterior(state[0], 1, heads, gap)[0], atol=1e-6)
    # the denoising encoder has no residual input; the wiring travels with the checkpoint
    assert not hasattr(res.denoise_encoder, "res_mean")
    path = training.save_checkpoint(tmp_path / "motion_dvae.pt", res.state_dict(), res.config)
    assert MotionDVAEPrior(size="embedded", weights=str(path)).net.encoder_residual is True
    path = training.save_checkpoint(tmp_path / "old.pt", fb.state_dict(), fb.config)
    assert MotionDVAEPrior(size="embedded", weights=str(path)).net.encoder_residual is False
    with pytest.raises(ValueError, match="needs feedback=True"):
        MotionDVAE(**dict(TINY, feedback=False, encoder_residual=True))
    with pytest.raises(ValueError, match="needs the decoded state"):
        res.encoder.posterior(state[0], 1, heads)


def test_root_markers_weigh_the_root_heading():
    torch.manual_seed(1)
    m = MotionDVAE(**dict(TINY, feedback=True)).eval()
    states = windows_to_state(smooth_windows(2, 6, seed=4))
    pts = body_points(*state_to_motion(states), REST)
    with torch.no_grad():
        m.decoder.net[-1].weight.normal_(0, 0.1)
        torch.manual_seed(2)
        plain = m.dvae_loss(states, pts, beta=1.0, point_weight=10.0)
        torch.manual_seed(2)
        marked = m.dvae_loss(states, pts, beta=1.0, point_weight=10.0, root_marker_m=1.5)
        # the same draw: the difference is the root markers' squared errors, weighted
        torch.manual_seed(2)
        z, _, _, _, rec_n = m.infer(m.encoder, m.normalise(states), m.normalise(states)[:, 0], sample=True)
        rot, _ = state_to_motion(m.unnormalise(rec_n[:, 1:]))
        gt, _ = state_to_motion(states[:, 1:])
        extra = ((rot[..., 0, :, 0] - gt[..., 0, :, 0]).square().sum(-1) + (rot[..., 0, :, 2] - gt[..., 0, :, 2]).square().sum(-1))
    assert torch.allclose(marked["loss"] - plain["loss"], 10.0 * 1.5 ** 2 * extra.mean(), rtol=1e-4, atol=1e-6)
    assert marked["point_sq_m2"] > plain["point_sq_m2"]


def test_residual_training_from_a_checkpoint_without_it(tmp_path):
    windows = smooth_windows(16, 8, seed=3)
    base, _ = train_motion_dvae(None, steps=1, denoise_steps=1, config=dict(TINY, encoder_residual=False), batch_size=8,
                                windows=windows, rest_joints=REST, log_every=10)
    assert base.feedback and not base.encoder_residual
    path = training.save_checkpoint(tmp_path / "motion_dvae.pt", base.state_dict(), base.config)
    model, record = train_motion_dvae(None, steps=2, denoise_steps=0, config=dict(TINY, encoder_residual=True),
                                      batch_size=8, windows=windows, rest_joints=REST, log_every=10, init_weights=path,
                                      init_denoise=True, train_generative=False, lr=1e-2, encoder_point_weight=400.0,
                                      encoder_root_marker_m=1.5)
    assert model.encoder_residual and record["config"]["encoder_residual"] is True
    assert record["phase_dvae"]["root_marker_m"] == 1.5
    assert model.encoder.res_mean.weight.abs().sum() > 0  # trained from zero
    with pytest.raises(ValueError, match="encoder-only"):
        train_motion_dvae(None, steps=1, denoise_steps=0, config=TINY, windows=windows, rest_joints=REST,
                          encoder_root_marker_m=1.0)
    # a residual encoder is not silently dropped into a config without it
    path = training.save_checkpoint(tmp_path / "res.pt", model.state_dict(), model.config)
    with pytest.raises(ValueError, match="have no place in config"):
        train_motion_dvae(None, steps=1, denoise_steps=0, config=dict(TINY, encoder_residual=False), batch_size=8,
                          windows=windows, rest_joints=REST, init_weights=path, train_generative=False)
