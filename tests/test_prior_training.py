"""The shared training helpers of the embedded priors (priors/training.py)."""

import json
import types

import pytest
import torch

from priors import training


def _motion(T: int, offset: float):
    return types.SimpleNamespace(name="m", poses=torch.full((T, 22, 3), offset))


def test_pose_frames_every_and_seeded_subset():
    motions = [_motion(10, 0.0), _motion(7, 1.0)]
    frames = training.pose_frames(motions, every=3)
    assert frames.shape == (4 + 3, 22, 3)
    assert torch.equal(frames[:4, 0, 0], torch.zeros(4)) and torch.equal(frames[4:, 0, 0], torch.ones(3))
    a = training.pose_frames(motions, every=1, max_frames=5, seed=1)
    b = training.pose_frames(motions, every=1, max_frames=5, seed=1)
    assert a.shape == (5, 22, 3) and torch.equal(a, b)
    with pytest.raises(ValueError, match=r"\(T, 22, 3\)"):
        training.pose_frames([types.SimpleNamespace(name="bad", poses=torch.zeros(3, 21, 3))])


def test_train_loop_fits_a_line_deterministically():
    x = torch.linspace(-1, 1, 64)[:, None]
    data = torch.cat([x, 3 * x - 0.5], dim=1)

    def loss_fn(model, batch):
        return {"loss": (model(batch[:, :1]) - batch[:, 1:]).square().mean()}

    def run():
        training.seed_everything(0)
        model = torch.nn.Linear(1, 1)
        res = training.train_loop(model, loss_fn, data, steps=300, batch_size=16, seed=0, lr=0.05, log_every=50, val_data=data)
        return model, res

    m1, r1 = run()
    m2, r2 = run()
    assert torch.equal(m1.weight, m2.weight) and r1.final_train == r2.final_train
    torch.testing.assert_close(m1.weight.detach(), torch.tensor([[3.0]]), atol=0.05, rtol=0)
    torch.testing.assert_close(m1.bias.detach(), torch.tensor([-0.5]), atol=0.05, rtol=0)
    assert r1.final_val["loss"] < 1e-3 and [h["step"] for h in r1.history] == [50, 100, 150, 200, 250, 300]


def test_outputs_are_written_and_readable(tmp_path):
    sd = {"w": torch.arange(3.0)}
    path = training.save_checkpoint(tmp_path / "sub" / "x.pt", sd, {"hidden": 4})
    ck = torch.load(path, weights_only=True)
    assert torch.equal(ck["state_dict"]["w"], sd["w"]) and ck["config"] == {"hidden": 4}
    rec = {"steps": 3, **training.environment_record()}
    training.write_record(tmp_path / "x.json", rec)
    back = json.loads((tmp_path / "x.json").read_text())
    assert back["steps"] == 3 and back["torch"] == torch.__version__
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sub", "x.json"]  # no temp files left


def test_fallback_skeleton_is_a_plausible_t_pose():
    j = torch.tensor(training.SMPL_LIKE_REST_JOINTS)
    assert j.shape == (22, 3) and torch.equal(j[0], torch.zeros(3))
    assert j[1, 0] > 0 > j[2, 0] and j[20, 0] > 0.5 > -0.5 > j[21, 0]  # left at +x, arms out
    assert j[15, 1] > j[12, 1] > j[9, 1] > 0 > j[4, 1] > j[7, 1]  # head up, feet down
