"""Sequential latent primitives (Marsot et al. 2022): network, decoder properties, adapter, training, export."""

import math

import pytest
import roma
import torch

from benchmark.core.frames import sixd_columns_to_matrix as gram_schmidt, yaw_matrix
from benchmark.core.skeleton import SMPL_LIKE_REST_JOINTS
from priors import training
from priors.base import FitBatch
from priors.sequential_primitives import SequentialPrimitivesPrior
from priors.sequential_primitives.model import (
    EMBEDDED_CONFIG,
    MODEL_JOINTS,
    SequentialPrimitives,
    canonicalise,
)
from priors.sequential_primitives.train import WindowBank, primitives_loss, train_sequential_primitives

TINY = dict(EMBEDDED_CONFIG, latent=16, d_model=32, heads=2, enc_layers=1, dec_layers=1, ff=64, mlp_hidden=32,
            mlp_layers=2, seg_layers=1, time_freqs=4, point_hidden=[16])
REST = torch.tensor(SMPL_LIKE_REST_JOINTS)


def toy_windows(n=6, frames=60, seed=0):
    """(n, frames, 69) smooth motions: small sinusoidal joint rotations, a turning walk."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(frames) / 30.0
    freq = 0.5 + torch.rand(n, 1, 22, 3, generator=g)
    phase = torch.rand(n, 1, 22, 3, generator=g) * 2 * math.pi
    aa = 0.25 * torch.sin(2 * math.pi * freq * t[None, :, None, None] + phase)
    heading = torch.rand(n, 1, generator=g) * 2 * math.pi + 0.3 * t[None]
    aa[:, :, 0] = aa[:, :, 0] * 0.3 + torch.stack([torch.zeros_like(heading), heading, torch.zeros_like(heading)], -1)
    speed = 1.0 + torch.rand(n, 1, generator=g)
    trans = torch.stack([torch.cumsum(torch.sin(heading), 1), 0.02 * torch.sin(5 * t).expand(n, -1),
                         torch.cumsum(torch.cos(heading), 1)], -1) * speed[..., None] / 30.0
    return torch.cat([aa.flatten(-2), trans], -1)


@pytest.fixture(scope="module")
def tiny_weights(tmp_path_factory):
    """A tiny network trained for a few steps (no point phase), saved in the project format."""
    torch.manual_seed(0)
    out = tmp_path_factory.mktemp("lp")
    net, record = train_sequential_primitives(out, steps=2, point_steps=0, config=TINY, windows=toy_windows(),
                                              rest_joints=REST, batch_size=4, log_every=1)
    return out / "sequential_primitives.pt", net, record


@pytest.fixture
def adapter(tiny_weights):
    return SequentialPrimitivesPrior(size="embedded", weights=str(tiny_weights[0])).eval()


def toy_batch(B=2, n=9, N=50, window_s=3.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(B, n, N, 3, generator=g) * torch.tensor([0.2, 0.5, 0.1]) + torch.tensor([0.0, 0.9, 0.0])
    lengths = torch.full((B, n), N, dtype=torch.long)
    lengths[0, 1] = 20
    pts[0, 1, 20:] = 0
    ts = (torch.arange(n, dtype=torch.float64) * 0.3).expand(B, n).clone()
    out_t = (torch.arange(int(window_s * 30), dtype=torch.float64) / 30).expand(B, -1)
    return FitBatch(points=pts, lengths=lengths, timestamps=ts, window_s=window_s, output_timestamps=out_t)


def test_network_shapes_and_parameter_counts():
    torch.manual_seed(0)
    net = SequentialPrimitives(**TINY)
    B, n = 3, 20
    R = roma.random_rotmat(B * n * 22).view(B, n, 22, 3, 3)
    mu, logvar = net.encode(R, torch.randn(B, n, 3), torch.rand(B, n).sort(-1).values)
    assert mu.shape == logvar.shape == (B, 8, 16)
    out = net.decoder(mu, torch.rand(B, 6), torch.rand(B, 7), with_segments=True)
    assert out["rotations"].shape == (B, 7, 22, 3, 3) and out["trans"].shape == (B, 7, 3)
    assert out["seg_sixd"].shape == (B, 8, 7, 20, 6) and out["masks"].shape == (B, 8, 7)
    eye = torch.eye(3).expand(B, 7, 2, 3, 3)
    assert torch.allclose(out["rotations"][:, :, [10, 11]], eye)  # feet are not modelled
    Rt = out["rotations"]
    assert torch.allclose(Rt @ Rt.transpose(-1, -2), torch.eye(3).expand_as(Rt), atol=1e-5)
    paper = SequentialPrimitivesPrior.paper_network()
    assert paper.latent == 256 and paper.primitives == 8 and paper.shape_dim == 8
    n_paper = sum(p.numel() for p in paper.parameters())
    n_emb = sum(p.numel() for p in SequentialPrimitives(**EMBEDDED_CONFIG).parameters())
    assert n_paper > 5 * n_emb > 0
    assert len(MODEL_JOINTS) == 20 and 10 not in MODEL_JOINTS and 11 not in MODEL_JOINTS


def test_durations_and_masks():
    torch.manual_seed(1)
    net = SequentialPrimitives(**TINY)
    with torch.no_grad():
        net.decoder.seg_mlp[-1].bias[0] = 0.0
        net.decoder.seg_mlp[-1].weight[0].normal_(0, 1.0)  # uneven durations
    z, shape = torch.randn(4, 8, 16), torch.rand(4, 6)
    tau = torch.linspace(0, 1, 201).expand(4, -1)
    out = net.decoder(z, shape, tau, with_segments=True)
    delta, start = out["delta"], out["start"]
    assert (delta > 0).all()
    assert torch.allclose(delta.sum(-1), torch.ones(4), atol=1e-6)
    assert torch.allclose(start[:, 0], torch.zeros(4)) and torch.allclose(start[:, 1:], torch.cumsum(delta, -1)[:, :-1], atol=1e-6)
    # G_i(tau) = exp(-((tau - (Delta_i + delta_i/2)) / (delta_i/2))^2): 1 at the centre, e^-1 at the edges
    centre = start + delta / 2
    G = out["masks"]
    i = 3
    at_centre = net.decoder(z, shape, centre[:, i:i + 1], with_segments=True)["masks"][:, i, 0]
    at_edge = net.decoder(z, shape, start[:, i:i + 1], with_segments=True)["masks"][:, i, 0]
    assert torch.allclose(at_centre, torch.ones(4), atol=1e-4) and torch.allclose(at_edge, torch.full((4,), math.exp(-1)), atol=1e-4)
    # every tau in [0, 1] lies in one segment, so the masks never all vanish
    assert (G.amax(1) >= math.exp(-1) - 1e-4).all()


def test_rigid_transform_and_combination():
    torch.manual_seed(0)
    """The combined 6D is the mask-weighted mean of the rho-transformed segment 6D (Eq. 1)."""
    net = SequentialPrimitives(**TINY)
    z, shape, tau = torch.randn(2, 8, 16), torch.rand(2, 6), torch.rand(2, 5)
    out = net.decoder(z, shape, tau, with_segments=True)
    G = out["masks"]
    expect = (G[..., None, None] * out["seg_sixd"]).sum(1) / G.sum(1)[..., None, None]
    assert torch.allclose(out["sixd"], expect, atol=1e-5)
    expect_g = (G[..., None] * out["seg_gamma"]).sum(1) / G.sum(1)[..., None]
    assert torch.allclose(out["gamma"], expect_g, atol=1e-5)


def test_canonicalise_and_gram_schmidt():
    torch.manual_seed(0)
    R = roma.random_rotmat(2 * 5 * 22).view(2, 5, 22, 3, 3)
    tr = torch.randn(2, 5, 3)
    Rc, tc, yaw, mean = canonicalise(R, tr)
    f = Rc[:, 0, 0, :, 2]
    assert torch.allclose(f[:, 0], torch.zeros(2), atol=1e-5) and (f[:, 2] >= 0).all()  # heading +z at frame 0
    assert torch.allclose(tc.mean(1), torch.zeros(2, 3), atol=1e-5)
    # decode's "heading" / "offset" undo it (what encode_motion returns)
    Y = yaw_matrix(yaw)[:, None]
    assert torch.allclose(Y @ Rc[:, :, 0], R[:, :, 0], atol=1e-5) and torch.equal(Rc[:, :, 1:], R[:, :, 1:])
    assert torch.allclose((Y @ tc[..., None])[..., 0] + mean[:, None], tr, atol=1e-5)
    assert torch.allclose(gram_schmidt(torch.cat([R[..., :, 0], R[..., :, 1]], -1)), R, atol=1e-5)


def test_decode_is_continuous_in_time(adapter):
    batch = toy_batch()
    lat = adapter.init_latents(batch, torch.Generator().manual_seed(0))
    t = torch.tensor([[0.5, 0.5 + 1e-4, 1.7, 1.7 + 1e-4]], dtype=torch.float64).expand(2, -1)
    dec = adapter.decode(lat, t, torch.full((2, 6), 0.5))
    assert dec.rotations.shape == (2, 4, 22, 3, 3) and dec.trans.shape == (2, 4, 3)
    assert (dec.rotations[:, 1] - dec.rotations[:, 0]).abs().max() < 1e-2
    assert (dec.trans[:, 3] - dec.trans[:, 2]).abs().max() < 1e-3
    # arbitrary, irregular timestamps (continuous window kind)
    irregular = torch.tensor([[0.0, 0.0137, 0.5, 1.234, 2.999]], dtype=torch.float64).expand(2, -1)
    assert adapter.decode(lat, irregular, None).rotations.shape == (2, 5, 22, 3, 3)


def test_init_encoder_and_prior_term(adapter):
    batch = toy_batch()
    lat = adapter.init_latents(batch, torch.Generator().manual_seed(0))
    assert set(lat) == {"z"} and lat["z"].shape == (2, 8, 16) and torch.isfinite(lat["z"]).all()
    again = adapter.init_latents(batch, torch.Generator().manual_seed(5))
    assert torch.equal(lat["z"], again["z"])  # deterministic encoder
    z = lat["z"].clone().requires_grad_(True)
    prior = adapter.prior_term({"z": z})
    assert prior.shape == (2,) and torch.allclose(prior, torch.zeros(2))
    moved = {"z": z + 0.1}
    assert torch.allclose(adapter.prior_term(moved), torch.full((2,), 0.01 * 8 * 16), rtol=1e-4)
    # padding points beyond lengths must not matter
    b2 = toy_batch()
    b2.points[0, 1, 20:] = 100.0
    assert torch.allclose(adapter.init_latents(b2, None)["z"], lat["z"], atol=1e-5)
    with pytest.raises(ValueError, match="init_latents"):
        adapter.prior_term({"z": torch.zeros(3, 8, 16)})


def test_gradients_reach_latents_and_shape(adapter):
    batch = toy_batch()
    lat = {k: v.clone().requires_grad_(True) for k, v in adapter.init_latents(batch, None).items()}
    shape = torch.full((2, 6), 0.5, requires_grad=True)
    dec = adapter.decode(lat, batch.timestamps, shape)
    (dec.rotations.sum() + dec.trans.square().sum() + adapter.prior_term(lat).sum()).backward()
    assert lat["z"].grad.abs().sum() > 0 and shape.grad.abs().sum() > 0
    assert all(p.grad is None for p in adapter.parameters())


def test_encode_motion_round_trip_frame(adapter):
    w = toy_windows(2, 90)
    poses, trans = training.unpack_windows(w)
    R = roma.rotvec_to_rotmat(poses)
    ts = (torch.arange(90, dtype=torch.float64) / 30).expand(2, -1)
    lat = adapter.encode_motion(R, trans, ts)
    assert lat["z"].shape == (2, 8, 16) and lat["heading"].shape == (2, 1) and lat["offset"].shape == (2, 3)
    assert adapter._window_s == pytest.approx(3.0)
    assert torch.allclose(lat["offset"], trans.mean(1), atol=1e-5)
    dec = adapter.decode(lat, ts, None)
    assert dec.rotations.shape == (2, 90, 22, 3, 3)
    assert torch.allclose(adapter.prior_term({"z": lat["z"]}), torch.zeros(2))


def test_tiny_training_decreases_loss():
    w = toy_windows(8, 60, seed=1)
    torch.manual_seed(0)
    _, rec = train_sequential_primitives(None, steps=24, point_steps=0, config=TINY, windows=w, val_windows=w[:4],
                                         rest_joints=REST, batch_size=4, lr=3e-3, log_every=6)
    h = rec["history"]  # lambda_3D is 0 for steps 1-12 and 1 for 13-24
    assert h[1]["global"] < h[0]["global"]
    assert h[3]["joints"] < h[2]["joints"]
    assert rec["final_val"] is not None and math.isfinite(rec["final_val"]["loss"])
    assert rec["config"]["format"] == "sequential-primitives/project-v1"


def test_primitives_loss_parts():
    net = SequentialPrimitives(**TINY)
    bank = WindowBank.from_windows(toy_windows(4, 60), None, 6)
    g = torch.Generator().manual_seed(0)
    R, tr, tau, shape = bank.sample(bank.starts, g, n=100)
    assert R.shape == (4, 100, 22, 3, 3) and (tau >= 0).all() and (tau < 1).all()
    assert (tau[:, 1:] >= tau[:, :-1]).all()
    parts0 = primitives_loss(net, R, tr, tau, shape, REST, 0.0, sample=False)
    parts1 = primitives_loss(net, R, tr, tau, shape, REST, 1.0, sample=False)
    assert torch.allclose(parts1["global"] - parts0["global"], parts0["joints"] * 6890 / 22, rtol=1e-4)
    total = parts0["global"] + parts0["segment"] + 1e-4 * parts0["kl"] + 0.01 * parts0["reg"]
    assert torch.allclose(parts0["loss"], total)


def test_point_phase_runs_on_the_body(anny_body):
    w = toy_windows(3, 40, seed=2)
    torch.manual_seed(0)
    net, rec = train_sequential_primitives(None, steps=1, point_steps=2, config=TINY, windows=w, rest_joints=REST,
                                           body=anny_body, batch_size=2, point_batch_size=2, log_every=1)
    assert len(rec["point_history"]) == 2 and math.isfinite(rec["point_final_train"]["latent_mse"])


def test_official_weights_errors(tmp_path, tiny_weights):
    with pytest.raises(ValueError, match="not public"):
        SequentialPrimitivesPrior(size="paper")
    bogus = tmp_path / "official.pth"
    torch.save({"model": {"encoder.weight": torch.zeros(2)}}, bogus)
    with pytest.raises(ValueError, match="decoder.seg_mlp"):
        SequentialPrimitivesPrior(size="paper", weights=str(bogus))
    with pytest.raises(ValueError, match="not a paper-size checkpoint"):
        SequentialPrimitivesPrior(size="paper", weights=str(tiny_weights[0]))
    with pytest.raises(FileNotFoundError, match="no such file; check the path given with --weights"):
        SequentialPrimitivesPrior(size="embedded", weights=str(tmp_path / "missing.pt"))
    ckpt = torch.load(tiny_weights[0], weights_only=True)
    del ckpt["state_dict"]["decoder.in_t.weight"]
    torch.save(ckpt, tmp_path / "broken.pt")
    with pytest.raises(KeyError, match="decoder.in_t.weight"):
        SequentialPrimitivesPrior(size="embedded", weights=str(tmp_path / "broken.pt"))


def test_train_embedded_refuses_overwrite(tmp_path):
    (tmp_path / "sequential_primitives.pt").write_bytes(b"x")
    with pytest.raises(FileExistsError, match="--force"):
        SequentialPrimitivesPrior.train_embedded(out_dir=tmp_path)


def test_onnx_parity(adapter, tmp_path):
    ort = pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    spec = adapter.export_decoder()
    path = tmp_path / "sp.onnx"
    names = spec.input_names + spec.output_names
    torch.onnx.export(spec.module, spec.example_inputs, str(path), input_names=spec.input_names,
                      output_names=spec.output_names, dynamic_axes={n: {0: "batch"} for n in names},
                      opset_version=17, dynamo=False)
    g = torch.Generator().manual_seed(3)
    z, shape = torch.randn(5, 8, 16, generator=g), torch.rand(5, 6, generator=g)
    tau = torch.rand(5, spec.example_inputs[2].shape[1], generator=g).sort(-1).values
    with torch.no_grad():
        ref = spec.module(z, shape, tau)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"z": z.numpy(), "shape": shape.numpy(), "tau": tau.numpy()})
    for r, o in zip(ref, got):
        assert o.shape == tuple(r.shape)
        torch.testing.assert_close(torch.from_numpy(o), r, rtol=1e-3, atol=1e-5)
