"""The shared training helpers of the embedded priors (priors/training.py)."""

import json
import types

import pytest
import torch

from benchmark.core.skeleton import SMPL_LIKE_REST_JOINTS
from priors import training, training_state


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
    j = torch.tensor(SMPL_LIKE_REST_JOINTS)
    assert j.shape == (22, 3) and torch.equal(j[0], torch.zeros(3))
    assert j[1, 0] > 0 > j[2, 0] and j[20, 0] > 0.5 > -0.5 > j[21, 0]  # left at +x, arms out
    assert j[15, 1] > j[12, 1] > j[9, 1] > 0 > j[4, 1] > j[7, 1]  # head up, feet down


class _Killed(Exception):
    """Stands for the process being killed mid-training."""


def test_train_loop_resumes_exactly_after_an_interruption(tmp_path):
    """``train NAME --resume``: a loop stopped after a checkpoint continues from it and ends with the
    same weights, losses and history as an uninterrupted run (dropout's RNG and the batch order
    included); its record keeps the validation curve and the wall time."""
    x = torch.linspace(-1, 1, 64)[:, None]
    data = torch.cat([x, 3 * x - 0.5], dim=1)

    def loss_fn(model, batch):
        return {"loss": (model(batch[:, :1]) - batch[:, 1:]).square().mean()}

    def make():
        training.seed_everything(0)
        return torch.nn.Sequential(torch.nn.Linear(1, 8), torch.nn.Dropout(0.2), torch.nn.Linear(8, 1))

    def run(state_dir, resume=False, stop_at=None):
        model = make()
        calls = []

        def loss(model, batch):
            calls.append(1) if model.training else None  # training steps only, not validation
            if stop_at is not None and len(calls) > stop_at:
                raise _Killed
            return loss_fn(model, batch)

        with training_state.training_session(state_dir, resume=resume, checkpoint_every=40, val_every=50):
            res = training.train_loop(model, loss, data, steps=150, batch_size=16, seed=0, lr=0.02, log_every=25,
                                      val_data=data)
        return model, res

    full_model, full = run(tmp_path / "a")
    with pytest.raises(_Killed):
        run(tmp_path / "b", stop_at=110)  # checkpoints at steps 50 and 100, killed during step 111
    state = torch.load(tmp_path / "b" / "loop0.pt", weights_only=True)  # what --resume reads: no other objects
    assert state["step"] == 100
    model, res = run(tmp_path / "b", resume=True)
    for p, q in zip(model.parameters(), full_model.parameters()):
        assert torch.equal(p, q)
    strip = lambda h: [{k: v for k, v in e.items() if k != "wall_s"} for e in h]  # noqa: E731
    assert strip(res.history) == strip(full.history) and res.final_val == full.final_val
    assert [h["step"] for h in res.history if "val_loss" in h] == [50, 100, 150]
    # a finished loop resumes to its end state without training again
    model2, res2 = run(tmp_path / "b", resume=True, stop_at=0)
    assert all(torch.equal(p, q) for p, q in zip(model2.parameters(), full_model.parameters()))
    # a state file from another run is refused with the file named
    torch.save({**state, "seed": 7}, tmp_path / "b" / "loop0.pt")
    with pytest.raises(ValueError, match="loop0.pt: saved by a different training run"):
        run(tmp_path / "b", resume=True)


def test_train_resume_without_a_state_names_the_folder(tmp_path):
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "benchmark", "train", "vposer-slerp", "--resume", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr
    assert "no training state in" in r.stderr and str(tmp_path / ".train_state" / "vposer-slerp") in r.stderr


def test_committed_weights_fit_the_budget():
    """Issue 13: the embedded weights and their records together stay within 60 MB (a new prior or a larger
    embedded size must make room: float16 storage where no metric moves by more than 0.1 mm)."""
    from pathlib import Path

    folder = Path(training.__file__).resolve().parent / "weights"
    files = [p for p in folder.iterdir() if p.is_file()]
    assert {p.suffix for p in files} <= {".pt", ".json"}
    total = sum(p.stat().st_size for p in files)
    assert total <= 60_000_000, f"{folder}: {total / 1e6:.2f} MB of weights and records, over the 60 MB budget"


class _Dataset:
    """Training data as the `train` command hands it to a recipe (priors.training, "data")."""

    def split(self, name):
        return [types.SimpleNamespace(name=f"{name}0", poses=torch.randn(40, 22, 3, generator=torch.Generator().manual_seed(0)) * 0.1)]

    def source(self, name):
        return f"test dataset {name!r}"


def test_a_recipe_trains_on_the_dataset_it_is_handed():
    """The priors never build their training data (docs/architecture.md, layers): a recipe reads the
    splits of the dataset its caller passes, records where they came from, and refuses to run
    without one."""
    from priors.vposer.train import train_vposer

    assert len(training.split_motions(_Dataset(), "train")) == 1
    with pytest.raises(ValueError, match="no training data for the 'train' split: pass dataset="):
        training.split_motions(None, "train")
    _, record = train_vposer(None, steps=2, dataset=_Dataset(), hidden=16, latent=4, log_every=1)
    assert record["data"]["train"]["source"] == "test dataset 'train'" and record["data"]["val"]["frames"] == 20
    with pytest.raises(ValueError, match="no training data"):
        train_vposer(None, steps=2, hidden=16, latent=4)


def test_the_synthetic_training_data_names_its_source_as_the_records_did():
    from benchmark.synthetic.train_data import SyntheticTrainingData

    assert SyntheticTrainingData().source("train") == "benchmark.synthetic.splits.build_split('train')"
