"""VPoser V02_05 network, its strict checkpoint loader, the VPoser+SLERP adapter and its training."""

import math
import os
import pickle
import sys
import types
from pathlib import Path

import pytest
import roma
import torch
import torch.nn.functional as F

from benchmark.core.skeleton import SMPL_LIKE_REST_JOINTS
from priors import training
from priors.base import FitBatch
from priors.vposer import VPoserSlerp
from priors.vposer import checkpoint
from priors.vposer.checkpoint import DEFAULT_WEIGHTS, resolve_checkpoint
from priors.vposer.model import ContinousRotReprDecoder, VPoser
from priors.vposer.train import train_vposer

PAPER_KEYS_26 = [
    f"encoder_net.1.{s}" for s in ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
] + ["encoder_net.2.weight", "encoder_net.2.bias"] + [
    f"encoder_net.4.{s}" for s in ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
] + [
    f"{m}.{s}"
    for m in ("encoder_net.6", "encoder_net.7", "encoder_net.8.mu", "encoder_net.8.logvar", "decoder_net.0", "decoder_net.3", "decoder_net.5")
    for s in ("weight", "bias")
]


def _randomise(model: VPoser, seed: int) -> VPoser:
    """Non-default weights and BatchNorm statistics, so a round trip proves something."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for k, t in model.state_dict().items():
            if t.is_floating_point():
                t.copy_(torch.rand(t.shape, generator=g) * 0.5 + (0.5 if "running_var" in k else -0.25))
            else:
                t.fill_(seed + 7)
    return model.eval()


def _official_ckpt(model: VPoser) -> dict:
    """A PyTorch-Lightning checkpoint in the V02_05 layout: vp_model.* keys, bm_train.* extras, bookkeeping."""
    sd = {f"vp_model.{k}": v.clone() for k, v in model.state_dict().items()}
    sd["bm_train.v_template"] = torch.zeros(10475, 3)
    sd["bm_train.shapedirs"] = torch.zeros(10, 3, 4)
    sd["bm_train.f"] = torch.zeros(20, 3, dtype=torch.int64)
    return {
        "epoch": 13,
        "global_step": 12345,
        "pytorch-lightning_version": "1.2.4",
        "state_dict": sd,
        "callbacks": {},
        "optimizer_states": [{"state": {}, "param_groups": [{"lr": 1e-3}]}],
        "lr_schedulers": [],
    }


def _write_official_folder(tmp_path, models_by_epoch: dict) -> str:
    snap = tmp_path / "V02_05" / "snapshots"
    snap.mkdir(parents=True)
    for i, (epoch, model) in enumerate(sorted(models_by_epoch.items(), reverse=True)):
        f = snap / f"V02_05_epoch={epoch:02d}_val_loss=0.03.ckpt"
        torch.save(_official_ckpt(model), f)
        os.utime(f, (1_000_000 + i, 1_000_000 + i))  # lower epochs are newer: mtime would pick wrongly
    return str(tmp_path / "V02_05")


def _batch(B: int, n: int) -> FitBatch:
    return FitBatch(
        points=torch.zeros(B, n, 5, 3),
        lengths=torch.full((B, n), 5),
        timestamps=torch.arange(n, dtype=torch.float32).expand(B, n) * 0.2,
        window_s=4.0,
        output_timestamps=torch.arange(120, dtype=torch.float32).expand(B, 120) / 30,
    )


# -- network ---------------------------------------------------------------------------------
def test_paper_size_parameter_count_and_keys():
    model = VPoser(hidden=512, latent=32)
    assert sum(p.numel() for p in model.parameters()) == 936_252
    assert sorted(model.state_dict()) == sorted(PAPER_KEYS_26)
    shapes = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert shapes["encoder_net.2.weight"] == (512, 63)
    assert shapes["encoder_net.8.mu.weight"] == (32, 512)
    assert shapes["decoder_net.5.weight"] == (126, 512)


def test_interleaved_6d_hand_example():
    dec = ContinousRotReprDecoder()
    # a1 = elements (0, 2, 4) = (0, 1, 0), a2 = elements (1, 3, 5) = (-1, 0, 0): R = Rz(+90 deg).
    x = torch.zeros(1, 126)
    x[0, :6] = torch.tensor([0.0, -1.0, 1.0, 0.0, 0.0, 0.0])
    x[0, 6:] = torch.tensor([1.0, 0.0, 0.0, 1.0, 0.0, 0.0]).repeat(20)  # identity in this layout
    R = dec(x)
    assert R.shape == (21, 3, 3)
    expected = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    torch.testing.assert_close(R[0], expected)
    torch.testing.assert_close(R[1:], torch.eye(3).expand(20, 3, 3))
    # Unnormalised, non-orthogonal input: b1 = a1/|a1|, b2 = a2 minus its b1 part, normalised.
    x[0, :6] = torch.tensor([2.0, 1.0, 0.0, 3.0, 0.0, 0.0])  # a1 = (2,0,0), a2 = (1,3,0)
    torch.testing.assert_close(dec(x)[0], torch.eye(3))


def test_6d_decoder_matches_the_official_formula():
    def official(module_input):  # human_body_prior V02_05 ContinousRotReprDecoder, restated
        reshaped = module_input.view(-1, 3, 2)
        b1 = F.normalize(reshaped[:, :, 0], dim=1)
        dot = torch.sum(b1 * reshaped[:, :, 1], dim=1, keepdim=True)
        b2 = F.normalize(reshaped[:, :, 1] - dot * b1, dim=-1)
        b3 = torch.cross(b1, b2, dim=1)
        return torch.stack([b1, b2, b3], dim=-1)

    x = torch.randn(4, 126, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(ContinousRotReprDecoder()(x), official(x))


# -- loader ----------------------------------------------------------------------------------
def test_loader_round_trip_picks_highest_epoch_and_lists_ignored(tmp_path, caplog):
    m13 = _randomise(VPoser(), 13)
    m8 = _randomise(VPoser(), 8)
    folder = _write_official_folder(tmp_path, {8: m8, 13: m13})
    file, why = resolve_checkpoint(folder)
    assert file.name == "V02_05_epoch=13_val_loss=0.03.ckpt" and "highest epoch (13)" in why
    with caplog.at_level("INFO", logger="priors.vposer"):
        loaded, report = checkpoint.load(folder, "paper")
    assert report.format == "official-lightning" and report.file == file
    assert report.loaded == sorted(PAPER_KEYS_26)
    assert {"bm_train.v_template", "bm_train.shapedirs", "bm_train.f"} <= set(report.ignored)
    assert "<top level>/optimizer_states" in report.ignored and "<top level>/epoch" in report.ignored
    assert "bm_train.v_template" in caplog.text
    for k, v in m13.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v), k
    # the adapter at paper size goes through the same loader
    adapter = VPoserSlerp(size="paper", weights=folder)
    assert adapter.checkpoint.file == file
    torch.testing.assert_close(adapter.vposer.decoder_net[5].weight, m13.decoder_net[5].weight)


def test_loader_without_num_batches_tracked_and_with_unimportable_hparams(tmp_path, caplog):
    model = _randomise(VPoser(), 1)
    ckpt = _official_ckpt(model)
    for k in [k for k in ckpt["state_dict"] if k.endswith("num_batches_tracked")]:
        del ckpt["state_dict"][k]
    # Lightning pickles hyper-parameters (e.g. OmegaConf objects) and, in 1.x, callback classes as
    # keys of 'callbacks'; the reader may not have those modules. They are read as inert stand-ins.
    fakes = {n: types.ModuleType(n) for n in ("omegaconf", "omegaconf.dictconfig", "pytorch_lightning",
                                               "pytorch_lightning.callbacks", "pytorch_lightning.callbacks.model_checkpoint")}
    assert not any(n in sys.modules for n in fakes), "the real omegaconf / pytorch_lightning are installed"

    class DictConfig:
        def __init__(self, d):
            self.d = d

    class ModelCheckpoint:
        pass

    for cls, module in ((DictConfig, "omegaconf.dictconfig"), (ModelCheckpoint, "pytorch_lightning.callbacks.model_checkpoint")):
        cls.__module__, cls.__qualname__ = module, cls.__name__
        setattr(fakes[module], cls.__name__, cls)
    sys.modules.update(fakes)
    try:
        ckpt["hyper_parameters"] = DictConfig({"model_params": {"num_neurons": 512, "latentD": 32}})
        ckpt["callbacks"] = {ModelCheckpoint: {"best_model_score": torch.tensor(0.03), "dirpath": "snapshots"}}
        f = tmp_path / "V02_05_epoch=13_val_loss=0.03.ckpt"
        torch.save(ckpt, f)
    finally:
        for n in fakes:
            del sys.modules[n]
    with caplog.at_level("WARNING", logger="priors.vposer"):
        loaded, report = checkpoint.load(f, "paper")
    assert "weights_only=True" in caplog.text and "omegaconf.dictconfig.DictConfig" in caplog.text  # read as stand-ins
    assert "pytorch_lightning.callbacks.model_checkpoint.ModelCheckpoint" in caplog.text
    assert "<top level>/hyper_parameters" in report.ignored and "<top level>/callbacks" in report.ignored
    assert report.chosen_because == "file given" and len(report.loaded) == 24
    torch.testing.assert_close(loaded.encoder_net[1].running_var, model.encoder_net[1].running_var)


def test_loader_errors_name_file_key_and_shapes(tmp_path):
    model = _randomise(VPoser(), 2)
    missing = _official_ckpt(model)
    del missing["state_dict"]["vp_model.decoder_net.5.weight"]
    f_missing = tmp_path / "missing.ckpt"
    torch.save(missing, f_missing)
    with pytest.raises(KeyError) as err:
        checkpoint.load(f_missing, "paper")
    assert str(f_missing) in str(err.value) and "vp_model.decoder_net.5.weight" in str(err.value)
    assert "(126, 512)" in str(err.value)

    wrong = _official_ckpt(model)
    wrong["state_dict"]["vp_model.encoder_net.8.mu.weight"] = torch.zeros(16, 512)
    f_wrong = tmp_path / "wrong.ckpt"
    torch.save(wrong, f_wrong)
    with pytest.raises(ValueError) as err:
        checkpoint.load(f_wrong, "paper")
    msg = str(err.value)
    assert str(f_wrong) in msg and "vp_model.encoder_net.8.mu.weight" in msg and "(16, 512)" in msg and "(32, 512)" in msg

    # paper-size tensors in a project file whose config says a smaller network: a shape error too
    small = tmp_path / "vposer.pt"
    torch.save({"state_dict": model.state_dict(), "config": {"hidden": 256, "latent": 32}}, small)
    with pytest.raises(ValueError, match="encoder_net"):
        checkpoint.load(small, "embedded")
    # the official release read as the embedded size: pointed to size 'paper'
    with pytest.raises(ValueError, match="size='paper'"):
        checkpoint.load(_write_official_folder(tmp_path, {13: model}), "embedded")

    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="snapshots"):
        resolve_checkpoint(empty)
    (empty / "last.ckpt").write_bytes(b"")
    with pytest.raises(ValueError, match="epoch=NN"):
        resolve_checkpoint(empty)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        resolve_checkpoint(tmp_path / "nowhere")


def test_paper_size_without_weights_says_where_to_get_them():
    with pytest.raises(ValueError) as err:
        VPoserSlerp(size="paper")
    assert "V02_05" in str(err.value) and "--weights vposer-slerp=" in str(err.value)
    with pytest.raises(ValueError, match="unknown size"):
        VPoserSlerp(size="huge")


# -- adapter ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_weights(tmp_path_factory):
    """A tiny VPoser written in the project format (priors/weights/vposer.pt layout)."""
    model = _randomise(VPoser(hidden=32, latent=8), 5)
    path = tmp_path_factory.mktemp("w") / "vposer.pt"
    training.save_checkpoint(path, model.state_dict(), model.config)
    return path, model


def test_adapter_declarations_and_frozen_eval(small_weights):
    path, model = small_weights
    a = VPoserSlerp(size="embedded", weights=str(path))
    assert a.name == "vposer-slerp" and a.window.kind == "per-frame" and a.has_encoder
    assert not a.encodes_translation and not a.encodes_root_orientation
    assert a.joints == tuple(range(1, 22)) and a.sixd_layout == "interleaved"
    assert a.checkpoint.format == "project" and a.checkpoint.ignored == []
    assert all(not p.requires_grad for p in a.parameters())
    a.train()
    assert not a.vposer.training  # the prior never trains dropout/BatchNorm
    z = torch.randn(2, 3, 8)
    r1 = a.decode({"z": z}, torch.zeros(2, 3)).rotations
    r2 = a.decode({"z": z}, torch.zeros(2, 3)).rotations
    assert torch.equal(r1, r2)
    torch.testing.assert_close(r1[:, :, 1:].reshape(6, 21, 3, 3), model.decode(z.reshape(6, 8)))


def test_decode_shapes_orthonormal_root_identity_and_gradients(small_weights):
    a = VPoserSlerp(size="embedded", weights=str(small_weights[0]))
    B, n = 2, 5
    z = torch.randn(B, n, 8, generator=torch.Generator().manual_seed(0), requires_grad=True)
    dec = a.decode({"z": z}, torch.rand(B, n))
    R = dec.rotations
    assert R.shape == (B, n, 22, 3, 3) and dec.trans is None
    torch.testing.assert_close(R[:, :, 0], torch.eye(3).expand(B, n, 3, 3))
    torch.testing.assert_close(R.transpose(-1, -2) @ R, torch.eye(3).expand_as(R), atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(B, n, 22), atol=1e-5, rtol=0)
    (R[..., 0, 1].sum() + a.prior_term({"z": z}).sum()).backward()
    assert z.grad is not None and torch.isfinite(z.grad).all() and z.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="per-frame"):
        a.decode({"z": z}, torch.rand(B, n + 1))


def test_init_latents_seeded_and_prior_term(small_weights):
    a = VPoserSlerp(size="embedded", weights=str(small_weights[0]))
    batch = _batch(3, 7)
    z1 = a.init_latents(batch, torch.Generator().manual_seed(42))["z"]
    z2 = a.init_latents(batch, torch.Generator().manual_seed(42))["z"]
    z3 = a.init_latents(batch, torch.Generator().manual_seed(43))["z"]
    assert z1.shape == (3, 7, 8) and torch.equal(z1, z2) and not torch.equal(z1, z3)
    assert abs(float(z1.mean())) < 0.5 and 0.5 < float(z1.std()) < 1.5  # N(0, I)
    naive = torch.tensor([sum(float((z1[b, i] ** 2).sum()) for i in range(7)) / 7 for b in range(3)])
    torch.testing.assert_close(a.prior_term({"z": z1}), naive)


def test_encode_poses_is_the_encoder_mean(small_weights):
    path, model = small_weights
    a = VPoserSlerp(size="embedded", weights=str(path))
    aa = torch.randn(2, 4, 21, 3, generator=torch.Generator().manual_seed(1)) * 0.5
    z = a.encode_poses(roma.rotvec_to_rotmat(aa))
    assert z.shape == (2, 4, 8)
    torch.testing.assert_close(z.reshape(8, 8), model.encode(aa.reshape(8, 21, 3)).mean, atol=1e-5, rtol=1e-4)


# -- the shipped embedded weights --------------------------------------------------------------
@pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason=f"embedded weights {DEFAULT_WEIGHTS} absent: run priors.vposer.train.train_vposer")
def test_embedded_weights_load_decode_and_reconstruct():
    a = VPoserSlerp()  # size "embedded", priors/weights/vposer.pt
    assert a.checkpoint.format == "project" and a.checkpoint.ignored == []
    assert a.parameter_count() < 2_600_000  # < 10 MB of float32
    z = torch.randn(1, 64, a.latent_dim, generator=torch.Generator().manual_seed(0))
    R = a.decode({"z": z}, torch.zeros(1, 64)).rotations
    assert R.shape == (1, 64, 22, 3, 3) and torch.isfinite(R).all()
    # prior samples decode to distinct poses (not a collapsed decoder) ...
    spread = roma.rotmat_geodesic_distance(R[0, :32, 1:], R[0, 32:, 1:]).mean()
    assert float(spread) > math.radians(5)
    # ... that the encoder maps back near their codes: encode -> decode reconstructs them
    # (measured 1.4-1.7 degrees mean over joints with the shipped weights)
    rt = a.decode({"z": a.encode_poses(R[:, :, 1:])}, torch.zeros(1, 64)).rotations
    err = roma.rotmat_geodesic_distance(rt[:, :, 1:], R[:, :, 1:]).mean()
    assert float(err) < math.radians(5)


# -- training --------------------------------------------------------------------------------
def test_tiny_training_run_decreases_the_loss_and_writes_outputs(tmp_path, monkeypatch):
    skel = torch.tensor(SMPL_LIKE_REST_JOINTS)
    monkeypatch.setattr(training, "fixed_rest_skeleton", lambda: (skel, "test skeleton"))
    g = torch.Generator().manual_seed(0)
    base = torch.randn(8, 22, 3, generator=g) * 0.4  # a few "poses" plus noise: learnable structure
    poses = base[torch.randint(0, 8, (1200,), generator=g)] + 0.05 * torch.randn(1200, 22, 3, generator=g)
    model, rec = train_vposer(tmp_path, steps=120, seed=0, hidden=64, latent=8, batch_size=128,
                              poses=poses[:1000], val_poses=poses[1000:], log_every=20)
    hist = [h["loss"] for h in rec["history"]]
    assert hist[-1] < 0.7 * hist[0], hist
    assert rec["final_val"]["loss"] < hist[0]
    assert rec["steps"] == 120 and rec["seed"] == 0 and rec["config"] == {"hidden": 64, "latent": 8}
    assert (tmp_path / "vposer.pt").exists() and (tmp_path / "vposer.json").exists()
    a = VPoserSlerp(size="embedded", weights=str(tmp_path / "vposer.pt"))
    z = torch.randn(1, 2, 8)
    torch.testing.assert_close(a.decode({"z": z}, torch.zeros(1, 2)).rotations[0, :, 1:], model.decode(z[0]))
    # same seed, same result
    model2, _ = train_vposer(None, steps=20, seed=0, hidden=64, latent=8, batch_size=128, poses=poses[:1000])
    model3, _ = train_vposer(None, steps=20, seed=0, hidden=64, latent=8, batch_size=128, poses=poses[:1000])
    for (k, v2), v3 in zip(model2.state_dict().items(), model3.state_dict().values()):
        assert torch.equal(v2, v3), k


def test_wrong_embedded_files_are_named_for_what_they_are(tmp_path):
    """Another prior's checkpoint, a config that is not numbers, an empty folder: each says what it
    is and what to give instead (they said to retrain with a Python function, or called an empty
    folder the official release)."""
    from priors.vposer import checkpoint

    root = Path(checkpoint.DEFAULT_WEIGHTS).parent
    with pytest.raises(ValueError, match=r"hmvae\.pt: not a VPoser checkpoint of this project .*another prior's weights"):
        checkpoint.load(root / "hmvae.pt", "embedded")
    ckpt = torch.load(checkpoint.DEFAULT_WEIGHTS, weights_only=True)
    ckpt["config"]["hidden"] = "abc"
    torch.save(ckpt, tmp_path / "vposer.pt")
    with pytest.raises(ValueError, match=r"'hidden' and 'latent' as positive integers, got hidden='abc'"):
        checkpoint.load(tmp_path / "vposer.pt", "embedded")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match=r"empty: a folder with no VPoser checkpoint in it"):
        checkpoint.load(tmp_path / "empty", "embedded")


def test_a_file_with_none_of_vposers_keys_says_what_it_holds(tmp_path):
    """Another prefix ('model.vp_model.') or another prior's file: the error lists the file's own keys
    and, where they end in VPoser's, the prefix to strip (it listed only the 24 missing keys)."""
    ckpt = _official_ckpt(_randomise(VPoser(), 3))
    prefixed = tmp_path / "prefixed.ckpt"
    torch.save({"state_dict": {f"model.{k}": v for k, v in ckpt["state_dict"].items()}}, prefixed)
    with pytest.raises(ValueError, match=r"prefixed\.ckpt: holds none of VPoser's weights .* its keys: \['model\..*"
                                         r"after the prefix 'model\.vp_model\.'"):
        checkpoint.load(prefixed, "paper")
    other = tmp_path / "gen_00250000.pt"
    torch.save({"state_dict": {"enc.layers.0.weight": torch.zeros(2)}}, other)
    with pytest.raises(ValueError, match=r"its keys: \['enc\.layers\.0\.weight'\]; is it another prior's checkpoint\?"):
        checkpoint.load(other, "paper")
