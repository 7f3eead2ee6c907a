"""HM-VAE: skeleton topology, paper-size keys, official-format loading, adapters, ONNX, training."""

import math
from collections import deque

import numpy as np
import pytest
import torch

from benchmark.core.frames import matrix_to_sixd_columns, sixd_columns_to_matrix
from benchmark.core.rotations import sixd_to_matrix
from benchmark.core.skeleton import SMPL_LIKE_REST_JOINTS
from priors import training
from priors.base import FitBatch
from priors.hmvae import HMVAEPrior, HMVAETrajectoryPrior
from priors.hmvae.checkpoint import learnable_state_dict, save_official_format
from priors.hmvae.model import (
    PAPER_CONFIG,
    HMVAE,
    HMVAEConfig,
    official_state_dict,
    parameter_summary,
)
from priors.hmvae.skeleton import (
    PARENTS24,
    SkeletonPool,
    SkeletonUnpool,
    conv_mask,
    edges24,
    neighbour_lists,
    topology_levels,
)
from priors.hmvae.train import rest_skeleton24, train_hmvae, train_trajectory
from priors.hmvae.trajectory import TrajectoryConfig, TrajectoryModel

TINY = HMVAEConfig(kernel_size=3, channels=(6, 4, 4, 8, 8), world_up="y")
TINY_TRAJ = TrajectoryConfig(kernel_size=5, channels=(3, 4, 4, 4, 4), world_up="y")
LEVEL0_GROUPS = [[0], [1, 4], [7, 10], [2, 5], [8, 11], [3], [6, 9], [12, 15], [13], [16, 18], [20, 22], [14],
                 [17, 19], [21, 23]]


# -- helpers ---------------------------------------------------------------------------------
def _randomise(module: torch.nn.Module, seed: int) -> torch.nn.Module:
    """Non-default learnable weights (frozen masks/pool matrices kept), so round trips prove something."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            if p.requires_grad:
                p.copy_(torch.randn(p.shape, generator=g) * 0.1)
    return module.eval()


def _windows(n: int, frames: int, seed: int = 0) -> torch.Tensor:
    """(n, frames, 69) smooth random motions: sinusoidal axis-angles and a drifting translation."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(frames, dtype=torch.float32)[None, :, None, None] / 30.0
    amp = torch.rand(n, 1, 22, 3, generator=g) * 0.5
    freq = torch.rand(n, 1, 22, 3, generator=g) * 2 + 0.5
    phase = torch.rand(n, 1, 22, 3, generator=g) * 6.28
    poses = amp * torch.sin(2 * math.pi * freq * t + phase)
    speed = torch.randn(n, 1, 3, generator=g) * 0.03
    trans = speed * torch.arange(frames, dtype=torch.float32)[None, :, None] + torch.randn(n, 1, 3, generator=g)
    return torch.cat([poses.flatten(2), trans], dim=-1)


def _write_embedded(tmp_path, with_trajectory=True):
    torch.manual_seed(0)
    vae = _randomise(HMVAE(TINY), 1)
    rest24 = rest_skeleton24(torch.tensor(SMPL_LIKE_REST_JOINTS))
    training.save_checkpoint(tmp_path / "hmvae.pt", learnable_state_dict(vae),
                             {"kind": "hmvae", "model": TINY.to_dict(), "rest_skeleton": rest24.tolist()})
    traj = None
    if with_trajectory:
        traj = _randomise(TrajectoryModel(TINY_TRAJ), 2)
        traj.set_statistics(torch.zeros(72), torch.full((72,), 0.3), torch.zeros(3), torch.full((3,), 0.02), rest24)
        training.save_checkpoint(tmp_path / "hmvae_trajectory.pt", learnable_state_dict(traj),
                                 {"kind": "hmvae-trajectory", "model": TINY_TRAJ.to_dict(), "statistics": traj.statistics()})
    return vae, traj


def _batch(B: int, window_s: float) -> FitBatch:
    n = 5
    return FitBatch(points=torch.zeros(B, n, 4, 3), lengths=torch.full((B, n), 4),
                    timestamps=torch.linspace(0, window_s, n).expand(B, n), window_s=window_s,
                    output_timestamps=torch.linspace(0, window_s, 10).expand(B, 10))


# -- topology --------------------------------------------------------------------------------
def test_edge_topology_and_pooling_levels():
    edges = edges24()
    assert edges[0] == (0, 24) and len(edges) == 24
    assert all(edges[j] == (PARENTS24[j], j) for j in range(1, 24))
    levels, groups = topology_levels()
    assert [len(lv) for lv in levels[:4]] == [24, 14, 9, 7] and levels[4] == []
    assert [len(g) for g in groups] == [14, 9, 7, 7]
    assert groups[0] == LEVEL0_GROUPS
    assert groups[3] == [[i] for i in range(7)]  # the last pooling is the identity
    assert levels[3] == [(0, 24), (0, 10), (0, 11), (0, 9), (9, 15), (9, 22), (9, 23)]
    for lvl, g in enumerate(groups):  # every input edge is pooled exactly once
        assert sorted(e for grp in g for e in grp) == list(range(len(levels[lvl])))


def test_pool_and_unpool_gathers_equal_the_official_matrices():
    levels, groups = topology_levels()
    g = torch.Generator().manual_seed(0)
    for lvl in range(4):
        E, G, C = len(levels[lvl]), len(groups[lvl]), 3
        pool, unpool = SkeletonPool(groups[lvl], E, C), SkeletonUnpool(groups[lvl], C)
        x, y = torch.randn(2, E * C, 5, generator=g), torch.randn(2, G * C, 5, generator=g)
        assert torch.allclose(pool(x), pool.weight @ x, atol=1e-6)  # dense reference = the stored matrix
        assert torch.allclose(unpool(y), unpool.weight @ y, atol=1e-6)
        assert torch.allclose(pool.weight @ unpool.weight, torch.eye(G * C))  # unpool then pool is the identity


def _bfs_edge_distance(edges, i):
    """Reference: BFS over the line graph (edges adjacent when they share a joint)."""
    dist = {i: 0}
    q = deque([i])
    while q:
        a = q.popleft()
        for b in range(len(edges)):
            if b not in dist and set(edges[a]) & set(edges[b]):
                dist[b] = dist[a] + 1
                q.append(b)
    return dist


def test_mask_keeps_exactly_edges_within_distance_two():
    levels, _ = topology_levels()
    for edges in levels[:4]:
        E = len(edges)
        m = conv_mask(neighbour_lists(edges, 2), 2, 3, 5)
        assert m.shape == (E * 3, E * 2, 5)
        for i in range(E):
            d = _bfs_edge_distance(edges, i)
            for j in range(E):
                block = m[i * 3:(i + 1) * 3, j * 2:(j + 1) * 2]
                assert bool((block == (1.0 if d.get(j, 99) <= 2 else 0.0)).all()), (E, i, j)
    assert neighbour_lists(levels[0])[0] == [0, 1, 2, 3, 4, 5, 6]  # the root edge sees hips, spine1 and their children
    assert neighbour_lists(levels[3]) == [list(range(7))] * 7


# -- paper size ------------------------------------------------------------------------------
def test_paper_size_keys_shapes_and_counts():
    model = HMVAE(PAPER_CONFIG)
    sd = model.state_dict()
    expect = {
        "enc.layers.0.0.weight": (288, 144, 15), "enc.layers.0.0.mask": (288, 144, 15), "enc.layers.0.0.bias": (288,),
        "enc.layers.0.1.weight": (168, 288), "enc.layers.3.0.weight": (672, 336, 15), "enc.layers.3.1.weight": (672, 672),
        "enc.latent_enc_layers.0.weight": (24, 384), "enc.latent_enc_layers.1.weight": (48, 384),
        "enc.latent_enc_layers.3.weight": (48, 384), "dec.layers.0.1.weight": (672, 672),
        "dec.layers.0.2.weight": (336, 672, 15), "dec.layers.0.2.bias": (336,), "dec.layers.3.2.weight": (144, 576, 15),
        "dec.layers.3.2.bias": (144,), "dec.unpools.3.weight": (576, 336), "dec.latent_dec_layers.0.weight": (384, 24),
        "dec.latent_dec_layers.3.weight": (384, 12),
    }
    for k, shape in expect.items():
        assert tuple(sd[k].shape) == shape, k
    assert "dec.layers.1.2.bias" not in sd and "dec.layers.2.2.bias" not in sd  # middle decoder convs have no bias
    assert torch.equal(sd["dec.unpools.2.weight"], sd["dec.layers.2.1.weight"])
    off = official_state_dict(model)
    assert set(off) == set(sd) | {"dec." + k for k in sd if k.startswith("enc.")}
    s = parameter_summary(model)
    assert s["weights"] == 13_233_480  # docs/priors.md: the 13.2 M dense-equivalent
    assert s["parameters_total"] == s["weights"] + s["frozen_fixed"]
    assert s["weights_effective"] < s["weights"]
    traj = TrajectoryModel()
    tsd = traj.state_dict()
    assert tuple(tsd["enc.layers.0.0.weight"].shape) == (144, 72, 31)
    assert tuple(tsd["fc_mapping.weight"].shape) == (3, 336)
    assert not any(k.endswith(("pos_mean", "rest_joints")) for k in tsd)  # statistics are not in the official state dict


def test_sixd_columns_conversion_matches_benchmark():
    x = torch.randn(50, 6)
    assert torch.allclose(sixd_columns_to_matrix(x), sixd_to_matrix(x, "columns"), atol=1e-5)
    R = sixd_to_matrix(x, "columns")
    assert torch.allclose(sixd_columns_to_matrix(matrix_to_sixd_columns(R)), R, atol=1e-5)


def _official_folder(tmp_path, seed=3):
    torch.manual_seed(seed)
    vae = _randomise(HMVAE(PAPER_CONFIG), seed)
    folder = tmp_path / "hmvae_official"
    save_official_format(folder / "gen_00250000.pt", official_state_dict(vae))
    return vae, folder


def test_official_legacy_checkpoint_loads_strictly_at_paper_size(tmp_path):
    vae, folder = _official_folder(tmp_path)
    save_official_format(folder / "gen_00005000.pt", {"bogus": torch.zeros(1)})  # an older snapshot: not chosen
    prior = HMVAEPrior(size="paper", weights=str(folder))
    assert prior.checkpoint.file.name == "gen_00250000.pt" and prior.checkpoint.format == "official-legacy"
    assert len(prior.checkpoint.parts["vae"].ignored) == sum(1 for k in vae.state_dict() if k.startswith("enc."))
    loaded = prior.vae.state_dict()
    assert set(loaded) == set(vae.state_dict())
    assert all(torch.equal(loaded[k], v) for k, v in vae.state_dict().items())
    assert prior.vae.config.world_up == "z" and prior.latent_shapes == {"z_g": (7, 24), "z_l": (14, 12)}
    z = prior.init_latents(_batch(1, 2.0), torch.Generator().manual_seed(0))
    with torch.no_grad():
        rot = prior.decode(z, torch.arange(64).expand(1, 64) / 30.0).rotations
        ref = sixd_to_matrix(vae.decode(z["z_g"][:, 0], z["z_l"][:, 0]), "columns")
    up = torch.tensor([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # AMASS z-up -> y-up
    assert torch.allclose(rot[0, :, 0], up @ ref[0, :, 0], atol=1e-5)
    assert torch.allclose(rot[0, :, 1:], ref[0, :, 1:22], atol=1e-5)

    # the trajectory variant: VAE,TRAJ plus the two official .npy files beside TRAJ
    traj = _randomise(TrajectoryModel(), 4)
    tdir = tmp_path / "traj"
    save_official_format(tdir / "gen_00100000.pt", traj.state_dict())
    np.save(tdir / "all_amass_data_mean_std.npy", np.stack([np.zeros(579), np.ones(579)]))
    np.save(tdir / "skeleton_offsets.npy", np.full((24, 3), 0.05, dtype=np.float32))
    tp = HMVAETrajectoryPrior(size="paper", weights=f"{folder},{tdir}")
    with torch.no_grad():
        dec = tp.decode(z, torch.arange(64).expand(1, 64) / 30.0)
    assert dec.trans.shape == (1, 64, 3) and torch.all(dec.trans[:, 0] == 0)


def test_official_checkpoint_errors_are_clear(tmp_path, monkeypatch):
    from priors.hmvae import checkpoint

    torch.manual_seed(5)
    sd = official_state_dict(HMVAE(PAPER_CONFIG))
    served = {}
    monkeypatch.setattr(checkpoint, "_torch_load", lambda file: {"state_dict": served[file.name]})  # no 160 MB writes

    def load(name, state_dict):
        served[name] = state_dict
        (tmp_path / name).touch()
        return HMVAEPrior(size="paper", weights=str(tmp_path / name))

    bad = dict(sd)
    bad["enc.layers.0.0.weight_renamed"] = bad.pop("enc.layers.0.0.weight")
    bad.pop("dec.enc.layers.0.0.weight")
    with pytest.raises(KeyError, match=r"gen_00000001\.pt.*enc\.layers\.0\.0\.weight"):
        load("gen_00000001.pt", bad)
    bad = dict(sd)
    bad.pop("dec.layers.3.2.bias")
    with pytest.raises(KeyError, match=r"missing keys \['dec\.layers\.3\.2\.bias'\]"):
        load("missing.pt", bad)
    bad = dict(sd)
    bad["dec.enc.latent_enc_layers.0.bias"] = bad["dec.enc.latent_enc_layers.0.bias"] + 1
    with pytest.raises(ValueError, match=r"dec\.enc\.latent_enc_layers\.0\.bias.*differs"):
        load("dup.pt", bad)
    bad = dict(sd)
    bad["enc.layers.1.0.mask"] = torch.ones_like(bad["enc.layers.1.0.mask"])
    bad["dec.enc.layers.1.0.mask"] = bad["enc.layers.1.0.mask"]
    with pytest.raises(ValueError, match="enc.layers.1.0.mask"):
        load("mask.pt", bad)
    bad = dict(sd)
    bad["dec.layers.0.2.weight"] = bad["dec.layers.0.2.weight"][:, :, :7]
    with pytest.raises(ValueError, match=r"dec\.layers\.0\.2\.weight.*shape"):
        load("shape.pt", bad)
    with pytest.raises(ValueError, match="no published weights"):
        HMVAEPrior(size="paper", weights=None)
    served["gen.pt"] = sd
    (tmp_path / "gen.pt").touch()
    with pytest.raises(FileNotFoundError, match="trajectory"):
        HMVAETrajectoryPrior(size="paper", weights=str(tmp_path))
    (tmp_path / "traj.pt").touch()
    with pytest.raises(FileNotFoundError, match="all_amass_data_mean_std.npy"):
        HMVAETrajectoryPrior(size="paper", weights=str(tmp_path))


# -- adapters (tiny embedded weights written by the test) ------------------------------------
def test_decode_shapes_orthonormality_prior_term(tmp_path):
    _write_embedded(tmp_path)
    prior = HMVAETrajectoryPrior(size="embedded", weights=str(tmp_path))
    assert prior.window.frames == 64 and prior.window.fps == 30.0 and prior.joints == tuple(range(22))
    z = prior.init_latents(_batch(2, 4.0), torch.Generator().manual_seed(0))
    assert z["z_g"].shape == (2, 2, 7, 24) and z["z_l"].shape == (2, 2, 14, 12)
    assert prior.init_latents(_batch(1, 2.0), torch.Generator())["z_g"].shape[1] == 1
    grid = (torch.arange(128) / 30.0).expand(2, 128)
    dec = prior.decode(z, grid)
    R = dec.rotations
    assert R.shape == (2, 128, 22, 3, 3) and dec.trans.shape == (2, 128, 3)
    assert torch.allclose(R.transpose(-1, -2) @ R, torch.eye(3).expand_as(R), atol=1e-5)
    assert torch.allclose(torch.linalg.det(R), torch.ones(R.shape[:-2]), atol=1e-5)
    assert torch.all(dec.trans[:, 0] == 0) and dec.trans[:, 64:].abs().sum() > 0  # one trajectory across windows
    pt = prior.prior_term(z)
    assert pt.shape == (2,) and torch.allclose(pt, z["z_g"].square().sum((1, 2, 3)) + z["z_l"].square().sum((1, 2, 3)))
    with pytest.raises(ValueError, match="grid"):
        prior.decode(z, grid[:, :120])
    plain = HMVAEPrior(size="embedded", weights=str(tmp_path / "hmvae.pt"))
    assert plain.decode(z, grid).trans is None and not plain.encodes_translation
    assert "learnable weights" in plain.describe() and plain.parameter_count() == parameter_summary(plain.vae)["weights"]


def test_encode_motion_pads_and_matches_the_encoder(tmp_path):
    vae, _ = _write_embedded(tmp_path, with_trajectory=False)
    prior = HMVAEPrior(size="embedded", weights=str(tmp_path / "hmvae.pt"))
    T = 100
    aa = _windows(2, T)[..., :66].unflatten(-1, (22, 3))
    import roma
    rot = roma.rotvec_to_rotmat(aa)
    ts = (torch.arange(T) / 30.0).expand(2, T)
    z = prior.encode_motion(rot, torch.zeros(2, T, 3), ts)
    assert z["z_g"].shape == (2, 2, 7, 24) and z["z_l"].shape == (2, 2, 14, 12)
    padded = torch.cat([rot, rot[:, -1:].expand(2, 128 - T, 22, 3, 3)], 1)
    full = torch.cat([padded, torch.eye(3).expand(2, 128, 2, 3, 3)], 2)
    with torch.no_grad():
        q = vae.encode(matrix_to_sixd_columns(full).reshape(4, 64, 24, 6))
    assert torch.allclose(z["z_g"].reshape(4, 7, 24), q["mu_g"], atol=1e-4)
    assert torch.allclose(z["z_l"].reshape(4, 14, 12), q["mu_l"], atol=1e-4)
    dec = prior.decode(z, (torch.arange(128) / 30.0).expand(2, 128))
    assert dec.rotations.shape == (2, 128, 22, 3, 3)


def test_onnx_export_parity(tmp_path):
    ort = pytest.importorskip("onnxruntime")
    _write_embedded(tmp_path)
    prior = HMVAETrajectoryPrior(size="embedded", weights=str(tmp_path))
    spec = prior.export_decoder()
    assert spec.output_names == ["rotations", "trans"]
    path = tmp_path / "hmvae.onnx"
    torch.onnx.export(spec.module, spec.example_inputs, str(path), input_names=spec.input_names,
                      output_names=spec.output_names, dynamic_axes={n: {0: "batch"} for n in spec.input_names + spec.output_names},
                      opset_version=17, dynamo=False)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    g = torch.Generator().manual_seed(1)
    x = (torch.randn(3, 7, 24, generator=g), torch.randn(3, 14, 12, generator=g))
    got = sess.run(None, {n: t.numpy() for n, t in zip(spec.input_names, x)})
    with torch.no_grad():
        ref = spec.module(*x)
    assert got[0].shape == (3, 64, 22, 3, 3) and got[1].shape == (3, 64, 3)
    for a, b in zip(got, ref):
        np.testing.assert_allclose(a, b.numpy(), rtol=1e-3, atol=1e-5)


def test_tiny_training_runs_decrease_loss_and_load(tmp_path):
    rest = torch.tensor(SMPL_LIKE_REST_JOINTS)
    w64 = _windows(16, 64, seed=1)
    _, rec = train_hmvae(tmp_path, steps=20, seed=0, config=TINY, windows=w64, val_windows=w64[:4], rest=rest,
                         batch_size=4, lr=3e-3, log_every=5)
    first, last = rec["history"][0], rec["history"][-1]
    assert last["loss"] < first["loss"]
    assert rec["deep_only_steps"] == 4 and rec["final_val"] is not None
    assert (tmp_path / "hmvae.json").exists()
    w128 = _windows(8, 128, seed=2)
    _, trec = train_trajectory(tmp_path, steps=12, seed=0, config=TINY_TRAJ, windows=w128, rest=rest, batch_size=4,
                               lr=3e-3, log_every=4)
    assert trec["history"][-1]["loss"] < trec["history"][0]["loss"]
    prior = HMVAETrajectoryPrior(size="embedded", weights=str(tmp_path))
    assert prior.vae.config == TINY and prior.trajectory_model.config == TINY_TRAJ
    with pytest.raises(FileExistsError, match="--force"):
        HMVAEPrior.train_embedded(out_dir=tmp_path)


def test_missing_embedded_weights_error(tmp_path, monkeypatch):
    with pytest.raises(FileNotFoundError, match="nothing.pt: no such file; check the path given with --weights"):
        HMVAEPrior(size="embedded", weights=str(tmp_path / "nothing.pt"))  # a path the user gave: mistyped
    monkeypatch.setattr(HMVAEPrior, "default_weights", tmp_path / "hmvae.pt")
    with pytest.raises(FileNotFoundError, match="train hmvae"):  # the embedded weights missing: train them
        HMVAEPrior(size="embedded")
    with pytest.raises(ValueError, match="unknown size"):
        HMVAEPrior(size="huge")
