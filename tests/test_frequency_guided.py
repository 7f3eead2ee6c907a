"""Xu et al.'s frequency-guided motion prior: networks, strict official loaders, adapter, features, export, training."""

import math

import numpy as np
import pytest
import roma
import torch

from benchmark.core.frames import heading as heading_angle, yaw_matrix
from benchmark.core.rotations import sixd_to_matrix
from benchmark.core.skeleton import SMPL_LIKE_REST_JOINTS
from priors import training
from priors.base import FitBatch
from priors.frequency_guided import FrequencyGuidedPrior
from priors.frequency_guided.adapter import n_windows_for
from priors.frequency_guided.checkpoint import DEFAULT_WEIGHTS, load_motion_prior_state, resolve_paper_weights
from priors.frequency_guided.model import (
    PAPER_CONFIG,
    XU17_FROM_SMPL22,
    FrequencyGuidedNetwork,
    MotionPrior,
    dct_matrix,
    frequency_features,
    window_features,
    xu17_joints,
)
from priors.frequency_guided.train import motion_prior_loss, prepare_windows, train_frequency_guided
from priors.vposer.checkpoint import load_vposer_v1_state
from priors.vposer.model import VPoserV1, sixd_interleaved_to_matrix

TINY_CONFIG = {
    "num_neurons": 32, "latent": 16, "latent_t": 8, "frames": 128, "dense_freq": True,
    "channels": [8, 8, 16], "dct_hidden": 16, "pose_code": 32, "unused_layers": False,
    "vposer": {"hidden": 32, "latent": 32},
}

# the official MotionPrior keys and shapes, after stripping "module." (docs/priors.md)
PAPER_SHAPES = {
    "dct_att.weight": (128, 32640), "dct_att.bias": (128,),
    "bodyprior_enc_fc0_1.weight_g": (64, 1, 1), "bodyprior_enc_fc0_1.weight_v": (64, 158, 3), "bodyprior_enc_fc0_1.bias": (64,),
    "bodyprior_enc_fc0_2.weight_v": (64, 64, 3), "bodyprior_enc_fc0_3.weight_v": (64, 64, 3),
    "pool1_1.weight_v": (64, 64, 3), "bodyprior_enc_fc1_1.weight_v": (64, 64, 3), "bodyprior_enc_fc1_2.weight_v": (64, 64, 3),
    "pool2_1.weight_v": (128, 64, 3), "bodyprior_enc_fc2_1.weight_v": (128, 128, 3), "bodyprior_enc_fc2_2.weight_v": (128, 128, 3),
    "bodyprior_enc_bn0_1.running_mean": (64,), "bodyprior_enc_bn2_2.weight": (128,),
    "bodyprior_enc_dct.weight_g": (512, 1), "bodyprior_enc_dct.weight_v": (512, 1020),
    "bodyprior_enc_mu_local.weight": (256, 8704), "bodyprior_enc_logvar_local.weight": (256, 8704),
    "bodyprior_enc_mu_global.weight": (8, 8192), "bodyprior_enc_logvar_global.weight": (8, 8192),
    "bodyprior_dec_fc0.weight": (512, 256), "bodyprior_dec_fc1.weight": (512, 512), "bodyprior_dec_fc2.weight": (512, 512),
    "bodyprior_dec_pose.weight": (4096, 768), "bodyprior_dec_orient.weight": (768, 768), "bodyprior_dec_trans.weight": (384, 520),
}
VPOSER_V1_KEYS = sorted(
    [f"bodyprior_enc_bn{i}.{s}" for i in (1, 2) for s in ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")]
    + [f"{m}.{s}" for m in ("bodyprior_enc_fc1", "bodyprior_enc_fc2", "bodyprior_enc_mu", "bodyprior_enc_logvar",
                            "bodyprior_dec_fc1", "bodyprior_dec_fc2", "bodyprior_dec_out") for s in ("weight", "bias")]
)


def _randomise(module: torch.nn.Module, seed: int) -> dict:
    g = torch.Generator().manual_seed(seed)
    sd = {}
    for k, t in module.state_dict().items():
        if t.is_floating_point():
            sd[k] = torch.rand(t.shape, generator=g) * 0.2 + (0.5 if "running_var" in k else -0.1)
        else:
            sd[k] = torch.full_like(t, 3)
    return sd


def _fake_motion(B, T, fps, seed=0):
    """Smooth random motions: rotations (B, T, 22, 3, 3), trans (B, T, 3), timestamps (B, T)."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T) / fps
    freq = torch.rand(B, 1, 22, 3, generator=g) * 1.5
    ph = torch.rand(B, 1, 22, 3, generator=g) * 6.28
    amp = torch.rand(B, 1, 22, 3, generator=g) * 0.4
    aa = amp * torch.sin(2 * math.pi * freq * t[None, :, None, None] + ph)
    aa[:, :, 0, 1] += torch.rand(B, 1, generator=g) * 6.28 + 0.3 * t
    trans = torch.cumsum(torch.randn(B, T, 3, generator=g) * 0.01, 1)
    return roma.rotvec_to_rotmat(aa), trans, t.expand(B, T).clone()


def _fake_windows(N, seed=0):
    R, trans, _ = _fake_motion(N, 128, 30.0, seed)
    return torch.cat([roma.rotmat_to_rotvec(R).reshape(N, 128, 66), trans], -1)


# -- official files and adapters (built once) -----------------------------------------------
@pytest.fixture(scope="module")
def official(tmp_path_factory):
    """A folder in the official layout with random weights, and the state dicts written."""
    root = tmp_path_factory.mktemp("xu_release")
    net = FrequencyGuidedNetwork(PAPER_CONFIG)
    mp = _randomise(net.motion_prior, 1)
    vp = _randomise(net.vposer, 2)
    torch.save({f"module.{k}": v for k, v in mp.items()}, root / "pretrained_priorD.pth")
    (root / "vposer_v1_0" / "snapshots").mkdir(parents=True)
    torch.save(vp, root / "vposer_v1_0" / "snapshots" / "TR00_E096.pt")
    return {"folder": root, "mp": mp, "vp": vp, "prior_file": root / "pretrained_priorD.pth",
            "vposer_file": root / "vposer_v1_0" / "snapshots" / "TR00_E096.pt"}


@pytest.fixture(scope="module")
def paper_adapter(official):
    return FrequencyGuidedPrior(size="paper", weights=str(official["folder"]))


@pytest.fixture(scope="module")
def tiny_adapter(tmp_path_factory):
    """An embedded adapter loaded from a project checkpoint of a tiny random network."""
    path = tmp_path_factory.mktemp("fg_tiny") / "frequency_guided.pt"
    torch.manual_seed(0)
    net = FrequencyGuidedNetwork(TINY_CONFIG)
    training.save_checkpoint(path, net.state_dict(), net.config)
    return FrequencyGuidedPrior(size="embedded", weights=str(path))


# -- network structure ------------------------------------------------------------------------
def test_paper_network_keys_shapes_and_counts():
    net = FrequencyGuidedPrior.paper_network()
    sd = net.motion_prior.state_dict()
    for k, shape in PAPER_SHAPES.items():
        assert tuple(sd[k].shape) == shape, k
    assert sorted(net.vposer.state_dict()) == VPOSER_V1_KEYS
    assert tuple(net.vposer.state_dict()["bodyprior_enc_bn1.weight"].shape) == (63,)
    assert tuple(net.vposer.state_dict()["bodyprior_dec_out.weight"].shape) == (126, 512)
    counts = net.parameter_counts()
    assert counts["motion_prior"] == 14_104_080  # docs/priors.md: 14,104,080
    assert counts["motion_prior_decoder"] == 4_397_312  # docs/priors.md: 4,397,312
    assert counts["vposer_v1"] == 673_596  # docs/priors.md, VPoser v1.0
    assert counts["total"] == 14_777_676
    assert not any(k.startswith("decoder.") for k in net.state_dict())


def test_dct_matches_scipy_and_is_orthonormal():
    from scipy.fft import dct

    for n in (5, 8, 128):
        C = dct_matrix(n, torch.float64)
        assert torch.allclose(C, torch.from_numpy(dct(np.eye(n), norm="ortho", axis=0)), atol=1e-12)
        assert torch.allclose(C @ C.T, torch.eye(n, dtype=torch.float64), atol=1e-12)


def test_dense_frequency_block_matches_naive_loop():
    g = torch.Generator().manual_seed(0)
    p3 = torch.randn(2, 128, 51, generator=g)
    basis, block = dct_matrix(128)[:20], dct_matrix(5)
    freq, fb = frequency_features(p3, basis, block, dense=True)
    assert freq.shape == (2, 1020) and fb.shape == (2, 128 * 5 * 51)
    assert torch.allclose(freq.reshape(2, 20, 51), basis @ p3, atol=1e-5)
    pad = torch.cat([p3[:, :1], p3[:, :1], p3, p3[:, -1:], p3[:, -1:]], 1)
    naive = torch.stack([block @ pad[:, i : i + 5] for i in range(128)], 1)  # (2, 128, 5, 51)
    assert torch.allclose(fb, naive.reshape(2, -1), atol=1e-5)
    _, fb8 = frequency_features(p3, basis, dct_matrix(8), dense=False)
    assert torch.allclose(fb8.reshape(2, 16, 8, 51)[:, 3], dct_matrix(8) @ p3[:, 24:32], atol=1e-5)


def test_heading_is_scipy_zxy_yaw_and_normalises():
    from scipy.spatial.transform import Rotation

    g = torch.Generator().manual_seed(1)
    R = roma.random_rotmat(16, generator=g).double()
    yaw = torch.from_numpy(Rotation.from_matrix(R.numpy()).as_euler("zxy")[:, 2])
    assert torch.allclose(heading_angle(R), yaw, atol=1e-9)
    Rn = yaw_matrix(-heading_angle(R)) @ R
    assert torch.allclose(heading_angle(Rn), torch.zeros(16, dtype=torch.float64), atol=1e-9)
    assert torch.allclose(Rn[:, 0, 2], torch.zeros(16, dtype=torch.float64), atol=1e-9)  # local +z in the y-z plane


def test_sixd_matches_benchmark_interleaved():
    x = torch.randn(7, 6)
    assert torch.allclose(sixd_interleaved_to_matrix(x), sixd_to_matrix(x, "interleaved"), atol=1e-6)
    assert sixd_interleaved_to_matrix(torch.randn(2, 3, 6)).shape == (2, 3, 3, 3)


def test_xu17_joint_mapping():
    from benchmark.body.lbs import forward_kinematics

    rest = torch.tensor(SMPL_LIKE_REST_JOINTS)

    g, j = forward_kinematics(torch.eye(3).expand(1, 22, 3, 3), rest)
    p = xu17_joints(g, j)[0]
    assert p.shape == (17, 3)
    for i, s in enumerate(XU17_FROM_SMPL22):
        if s >= 0:
            assert torch.equal(p[i], j[0, s])
    assert torch.allclose(p[10] - j[0, 15], torch.tensor([0.0, 0.116, 0.0]))
    assert p[1, 0] < 0 < p[4, 0]  # right hip at -x, left at +x (body facing +z)


# -- strict loading of the official files -----------------------------------------------------
def test_paper_weights_load_strictly_from_folder_and_pairs(official, paper_adapter):
    for k, v in official["mp"].items():
        if not k.endswith("num_batches_tracked"):
            assert torch.equal(paper_adapter.network.motion_prior.state_dict()[k], v), k
    for k, v in official["vp"].items():
        assert torch.equal(paper_adapter.network.vposer.state_dict()[k], v), k
    assert len(paper_adapter.checkpoint.parts["motion_prior"].loaded) == len(official["mp"])
    assert paper_adapter.checkpoint.files == [official["prior_file"], official["vposer_file"]]
    # a pair, in either order, as "a,b" or a tuple: each file is recognised by its keys
    a = FrequencyGuidedPrior(size="paper", weights=f"{official['vposer_file']},{official['prior_file']}")
    assert torch.equal(a.network.motion_prior.dct_att.weight, official["mp"]["dct_att.weight"])
    assert resolve_paper_weights((official["prior_file"], official["vposer_file"])) == (official["prior_file"], official["vposer_file"])
    assert resolve_paper_weights(str(official["folder"])) == (official["prior_file"], official["vposer_file"])
    assert not any(p.requires_grad for p in paper_adapter.parameters())
    assert not paper_adapter.train().network.training


def test_corrupted_official_files_fail_clearly(official, tmp_path):
    mp = {f"module.{k}": v for k, v in official["mp"].items()}
    model = MotionPrior(**{k: v for k, v in PAPER_CONFIG.items() if k != "vposer"})
    missing = {k: v for k, v in mp.items() if k != "module.bodyprior_dec_orient.bias"}
    with pytest.raises(KeyError, match=r"bad\.pth.*missing keys \['module\.bodyprior_dec_orient\.bias'\]"):
        load_motion_prior_state(missing, model, "bad.pth")
    extra = {**mp, "module.bodyprior_dec_extra.weight": torch.zeros(1)}
    with pytest.raises(KeyError, match="unexpected keys.*bodyprior_dec_extra.weight"):
        load_motion_prior_state(extra, model, "bad.pth")
    wrong = {**mp, "module.bodyprior_dec_pose.weight": torch.zeros(4096, 512)}
    with pytest.raises(ValueError, match=r"module\.bodyprior_dec_pose\.weight: file \(4096, 512\), expected \(4096, 768\)"):
        load_motion_prior_state(wrong, model, "bad.pth")
    vp = dict(official["vp"])
    vp.pop("bodyprior_dec_out.weight")
    with pytest.raises(KeyError, match=r"v1\.pt.*missing keys \['bodyprior_dec_out\.weight'\]"):
        load_vposer_v1_state(vp, VPoserV1(), "v1.pt")
    with pytest.raises(KeyError, match="V02_05"):
        load_vposer_v1_state({"encoder_net.1.weight": torch.zeros(63)}, VPoserV1(), "v2.ckpt")
    # through the adapter: a truncated VPoser file names the file and the key
    bad = tmp_path / "TR00_E096.pt"
    vp2 = dict(official["vp"])
    vp2["bodyprior_enc_fc1.weight"] = torch.zeros(512, 60)
    torch.save(vp2, bad)
    with pytest.raises(ValueError, match=r"TR00_E096\.pt.*bodyprior_enc_fc1\.weight: file \(512, 60\), expected \(512, 63\)"):
        FrequencyGuidedPrior(size="paper", weights=f"{official['prior_file']},{bad}")
    with pytest.raises(ValueError, match="needs the official weights"):
        FrequencyGuidedPrior(size="paper")
    with pytest.raises(FileNotFoundError, match="no pretrained_priorD.pth"):
        FrequencyGuidedPrior(size="paper", weights=str(tmp_path))
    with pytest.raises(FileNotFoundError, match=r"nothing\.pt: no such file; check the path given with --weights"):
        FrequencyGuidedPrior(size="embedded", weights=str(tmp_path / "nothing.pt"))


# -- the adapter ------------------------------------------------------------------------------
def test_adapter_declarations():
    a = FrequencyGuidedPrior
    assert (a.window.kind, a.window.frames, a.window.fps) == ("fixed", 128, 30.0)
    assert a.encodes_root_orientation and a.heading_normalised and not a.encodes_translation
    assert a.joints == tuple(range(22)) and a.sixd_layout == "interleaved" and a.has_encoder
    assert DEFAULT_WEIGHTS.name == "frequency_guided.pt"
    assert [n_windows_for(s) for s in (4.0, 128 / 30, 4.3, 10.0)] == [1, 1, 2, 3]


def _batch(B, window_s):
    n = 5
    return FitBatch(points=torch.zeros(B, n, 4, 3), lengths=torch.full((B, n), 4),
                    timestamps=torch.linspace(0, window_s, n).expand(B, n), window_s=window_s,
                    output_timestamps=torch.linspace(0, window_s, 30).expand(B, 30))


@pytest.mark.parametrize("window_s,n", [(4.0, 1), (5.0, 2)])
def test_decode_shapes_and_rotations(tiny_adapter, window_s, n):
    a = tiny_adapter
    lat = a.init_latents(_batch(3, window_s), torch.Generator().manual_seed(0))
    assert lat["z"].shape == (3, n, 16)
    assert torch.allclose(a.prior_term(lat), lat["z"].square().sum(dim=(1, 2)))
    grid = (torch.arange(n * 128) / 30.0).expand(3, -1)
    R = a.decode(lat, grid).rotations
    assert R.shape == (3, n * 128, 22, 3, 3)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3).expand_as(R), atol=1e-5)
    assert torch.allclose(torch.linalg.det(R), torch.ones(R.shape[:-2]), atol=1e-5)
    with pytest.raises(ValueError, match="grid"):
        a.decode(lat, grid[:, :100])


def test_paper_decode_and_encode(paper_adapter):
    rot, trans, ts = _fake_motion(2, 200, 50.0)  # 4 s at 50 fps -> one window
    z = paper_adapter.encode_motion(rot, trans, ts)["z"]
    assert z.shape == (2, 1, 256) and torch.isfinite(z).all()
    R = paper_adapter.decode({"z": z}, (torch.arange(128) / 30.0).expand(2, -1)).rotations
    assert R.shape == (2, 128, 22, 3, 3) and torch.isfinite(R).all()


def test_encode_motion_is_heading_and_offset_invariant(tiny_adapter):
    rot, trans, ts = _fake_motion(2, 150, 30.0)
    z = tiny_adapter.encode_motion(rot, trans, ts)["z"]
    assert z.shape == (2, 2, 16)  # 150 frames at 30 fps need two 128-frame windows
    Y = yaw_matrix(torch.tensor(1.1))
    rot2 = rot.clone()
    rot2[:, :, 0] = Y @ rot[:, :, 0]
    trans2 = (Y @ trans[..., None])[..., 0] + torch.tensor([0.5, 0.1, -2.0])
    z2 = tiny_adapter.encode_motion(rot2, trans2, ts)["z"]
    assert torch.allclose(z, z2, atol=1e-4)
    assert tiny_adapter.encode_motion(rot[:, :100], trans[:, :100], ts[:, :100])["z"].shape == (2, 1, 16)
    # decode of the encoding runs and its first root is heading-normalised (facing +z)
    R = tiny_adapter.decode({"z": z}, (torch.arange(256) / 30.0).expand(2, -1)).rotations
    assert R.shape == (2, 256, 22, 3, 3)


def test_window_features_heading_normalised():
    rot, trans, _ = _fake_motion(2, 128, 30.0)
    f = window_features(rot, trans, torch.tensor(SMPL_LIKE_REST_JOINTS))
    assert torch.allclose(heading_angle(f["root_norm"][:, 0]), torch.zeros(2), atol=1e-5)
    assert torch.allclose(f["trans_norm"][:, 0], torch.zeros(2, 3))
    assert f["p3ds_norm"].shape == (2, 128, 51) and torch.allclose(f["p3ds_norm"][..., :3], torch.zeros(2, 128, 3))


def test_onnx_export_parity(tiny_adapter, tmp_path):
    ort = pytest.importorskip("onnxruntime")
    spec = tiny_adapter.export_decoder()
    path = tmp_path / "fg.onnx"
    dyn = {n: {0: "batch"} for n in spec.input_names + spec.output_names}
    torch.onnx.export(spec.module, spec.example_inputs, str(path), input_names=spec.input_names,
                      output_names=spec.output_names, dynamic_axes=dyn, opset_version=17, dynamo=False)
    z = torch.randn(3, 16, generator=torch.Generator().manual_seed(5))
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (got,) = sess.run(None, {"z": z.numpy()})
    with torch.no_grad():
        (want,) = spec.module(z)
    assert got.shape == (3, 128, 22, 3, 3)
    np.testing.assert_allclose(got, want.numpy(), rtol=1e-3, atol=1e-5)


# -- training -------------------------------------------------------------------------------
def test_tiny_training_decreases_loss_and_writes(tmp_path):
    windows = _fake_windows(8)
    cfg = {**TINY_CONFIG, "dense_freq": False}  # the 8-frame block variant: a 100x smaller attention gate, faster steps
    net, rec = train_frequency_guided(
        tmp_path, steps=20, vposer_steps=5, config=cfg, windows=windows, val_windows=windows[:2],
        batch_size=4, vposer_batch_size=128, lr=5e-3, log_every=1, loss_frames=16,
        rest_joints=torch.tensor(SMPL_LIKE_REST_JOINTS),
    )
    assert len(rec["history"]) == 20
    # the same initial motion prior (same seed) with the trained VPoser v1, in eval mode on the same windows
    training.seed_everything(0)
    net0 = FrequencyGuidedNetwork(cfg, rest_joints=net.rest_joints)
    net0.vposer.load_state_dict(net.vposer.state_dict())
    net0.eval()
    with torch.no_grad():
        before = motion_prior_loss(net0, prepare_windows(net0, windows[:2]))["loss"]
    assert rec["final_val"]["loss"] < 0.95 * float(before)
    assert rec["final_val"]["rec_mm"] > 0 and rec["vposer_final_val"] is not None
    assert rec["parameters"]["total"] == sum(p.numel() for p in net.parameters())
    assert (tmp_path / "frequency_guided.json").exists()
    a = FrequencyGuidedPrior(size="embedded", weights=str(tmp_path / "frequency_guided.pt"))
    # the checkpoint stores float16 (halves the embedded file); loading casts back to float32
    assert torch.load(tmp_path / "frequency_guided.pt", weights_only=True)["state_dict"]["rest_joints"].dtype == torch.float16
    assert torch.allclose(a.network.rest_joints, net.rest_joints, atol=1e-3)
    with pytest.raises(FileExistsError, match="--force"):
        FrequencyGuidedPrior.train_embedded(out_dir=tmp_path)


def test_vposer_v02_05_given_for_v1_is_named_not_called_unsafe(official, tmp_path, monkeypatch):
    """VPoser V02_05's Lightning checkpoint (with its pickled callback class) in place of v1.0's
    TR00_E096.pt: the error says what the file is, not that it is unsafe to open."""
    import sys
    import types

    from priors.frequency_guided import checkpoint

    module = types.ModuleType("pytorch_lightning.callbacks.model_checkpoint")

    class ModelCheckpoint:
        pass

    ModelCheckpoint.__module__, ModelCheckpoint.__qualname__ = module.__name__, "ModelCheckpoint"
    module.ModelCheckpoint = ModelCheckpoint
    for name in ("pytorch_lightning", "pytorch_lightning.callbacks", module.__name__):
        monkeypatch.setitem(sys.modules, name, module if name == module.__name__ else types.ModuleType(name))
    v2 = tmp_path / "V02_05_epoch=13_val_loss=0.03.ckpt"
    torch.save({"state_dict": {"vp_model.encoder_net.1.weight": torch.zeros(3)}, "callbacks": {ModelCheckpoint: {}}}, v2)
    for name in ("pytorch_lightning", "pytorch_lightning.callbacks", module.__name__):
        monkeypatch.delitem(sys.modules, name)
    with pytest.raises(KeyError, match=r"this is VPoser V02_05: Xu et al.'s prior needs VPoser v1.0, TR00_E096.pt"):
        checkpoint._load_paper(f"{official['prior_file']},{v2}")
