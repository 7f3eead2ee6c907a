"""What `python -m benchmark train` does with a diverged training, a damaged resume state and the
files a user already has in --out (priors/training.py, priors/training_state.py,
benchmark/commands/train.py)."""

from pathlib import Path

import pytest
import torch

from benchmark.cli import main
from priors import training, training_state


class _Sqrt(torch.nn.Module):
    """loss sqrt(|w|) at w = 0: a finite loss (0) whose gradient is NaN, so the update of the last
    step turns the weight to NaN without any loss ever being non-finite."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(1))


def _sqrt_loss(model, batch):
    return {"loss": model.w.abs().sqrt().sum() + 0 * batch.sum()}


def _line_loss(model, batch):
    return {"loss": (model(batch[:, :1]) - batch[:, 1:]).square().mean()}


def _line(steps=4, **session):
    data = torch.randn(16, 2)
    model = torch.nn.Linear(1, 1)
    if session:
        with training_state.training_session(**session):
            return model, training.train_loop(model, _line_loss, data, steps=steps, batch_size=4, seed=0, log_every=2)
    return model, training.train_loop(model, _line_loss, data, steps=steps, batch_size=4, seed=0, log_every=2)


def test_a_training_whose_last_update_gives_nan_weights_says_it_diverged(tmp_path):
    data = torch.zeros(8, 1)
    with pytest.raises(FloatingPointError, match="training diverged: w holds NaN or inf after step 1"):
        training.train_loop(_Sqrt(), _sqrt_loss, data, steps=1, batch_size=4, seed=0)
    # nor is a diverged model saved as a state to continue from
    with pytest.raises(FloatingPointError, match="training diverged"):
        with training_state.training_session(tmp_path, checkpoint_every=1):
            training.train_loop(_Sqrt(), _sqrt_loss, data, steps=3, batch_size=4, seed=0, log_every=1)
    assert not (tmp_path / "loop0.pt").exists()


def test_nan_weights_are_never_written(tmp_path):
    with pytest.raises(FloatingPointError, match=r"x\.pt: not written: b hold NaN or inf"):
        training.save_trained(tmp_path, "x.pt", {"a": torch.zeros(2), "b": torch.tensor([1.0, float("nan")])}, {}, {})
    with pytest.raises(FloatingPointError, match="hold NaN or inf"):  # float16 overflows to inf
        training.save_checkpoint(tmp_path / "y.pt", {"a": torch.tensor([1e6]).half()}, {})
    assert list(tmp_path.iterdir()) == []


def test_a_resume_state_without_the_optimiser_names_the_file_and_the_fix(tmp_path):
    _line(checkpoint_every=2, state_dir=tmp_path)
    state = torch.load(tmp_path / "loop0.pt", weights_only=True)
    del state["optimiser"]
    torch.save(state, tmp_path / "loop0.pt")
    with pytest.raises(ValueError, match=r"loop0.pt: incomplete training state \(no optimiser\); delete it"):
        _line(state_dir=tmp_path, resume=True)


def test_a_resume_state_of_another_network_or_with_nan_is_refused_in_one_line(tmp_path):
    _line(checkpoint_every=2, state_dir=tmp_path)
    good = torch.load(tmp_path / "loop0.pt", weights_only=True)
    torch.save({**good, "model": {"weight": torch.zeros(3, 3), "bias": torch.zeros(3)}}, tmp_path / "loop0.pt")
    with pytest.raises(ValueError, match="loop0.pt: the saved state does not fit this network") as err:
        _line(state_dir=tmp_path, resume=True)
    assert "\n" not in str(err.value)
    nan = {k: torch.full_like(v, float("nan")) for k, v in good["model"].items()}
    torch.save({**good, "model": nan}, tmp_path / "loop0.pt")
    with pytest.raises(ValueError, match="loop0.pt: the saved model holds NaN or inf"):
        _line(state_dir=tmp_path, resume=True)


def test_a_different_steps_resume_says_how_to_continue(tmp_path):
    _line(steps=4, checkpoint_every=2, state_dir=tmp_path)
    with pytest.raises(ValueError, match="continue it with --steps 4 --seed 0"):
        _line(steps=6, state_dir=tmp_path, resume=True)


def test_the_users_own_record_file_in_out_is_not_overwritten(tmp_path):
    """`train vposer-slerp --out DIR` where DIR holds the user's own vposer.json (not vposer.pt)."""
    from priors.hmvae.train import train_embedded as train_hmvae
    from priors.vposer.checkpoint import DEFAULT_WEIGHTS

    (tmp_path / "vposer.json").write_text('{"mine": 1}')
    with pytest.raises(FileExistsError, match=r"vposer.json exists .*pass --force"):
        training.embedded_out_dir(tmp_path, DEFAULT_WEIGHTS, overwrite=False)
    assert training.embedded_out_dir(tmp_path, DEFAULT_WEIGHTS, overwrite=True) == tmp_path
    (tmp_path / "hmvae_trajectory.json").write_text('{"mine": 2}')
    with pytest.raises(FileExistsError, match="hmvae_trajectory.json exists"):
        train_hmvae(tmp_path, steps=1, dataset=None)  # refused before any data is asked for
    assert (tmp_path / "vposer.json").read_text() == '{"mine": 1}'


def _state(folder: Path) -> Path:
    state = folder / ".train_state" / "vposer-slerp" / "loop0.pt"
    state.parent.mkdir(parents=True)
    state.write_bytes(b"hours of training")
    return state


def _no_training(monkeypatch):
    from priors.vposer import adapter

    def work(*a, **k):
        raise AssertionError("training started")

    monkeypatch.setattr(adapter.VPoserSlerp, "train_embedded", classmethod(work))


def test_a_run_without_resume_keeps_an_earlier_training_state(tmp_path, monkeypatch, capsys):
    state = _state(tmp_path)
    _no_training(monkeypatch)
    assert main(["train", "vposer-slerp", "--steps", "1", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "holds the state of an earlier training of vposer-slerp (loop0.pt): pass --resume" in err, err
    assert state.read_bytes() == b"hours of training"


def test_force_starts_over_without_the_earlier_state(tmp_path, monkeypatch):
    state = _state(tmp_path)
    seen = {}

    def train_embedded(cls, **kw):
        seen["states"] = list(state.parent.iterdir())
        return {}

    from priors.vposer import adapter

    monkeypatch.setattr(adapter.VPoserSlerp, "train_embedded", classmethod(train_embedded))
    assert main(["train", "vposer-slerp", "--steps", "1", "--force", "--out", str(tmp_path)]) == 0
    assert seen["states"] == []  # no loop of the new run can be replayed from the earlier one


def test_a_refused_train_leaves_no_state_folder(tmp_path, capsys):
    (tmp_path / "vposer.pt").write_bytes(b"the user's weights")
    assert main(["train", "vposer-slerp", "--steps", "1", "--out", str(tmp_path)]) == 2
    assert "vposer.pt exists" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["vposer.pt"]


def test_a_recipe_command_line_checks_its_out_before_training(tmp_path, monkeypatch, capsys):
    """`python -m priors.vposer.train --out FILE` trained first and died with a traceback at the
    write; `python -m priors.hmvae.train` over an existing record raised a FileExistsError traceback."""
    import priors.hmvae.train as hmvae_train
    import priors.vposer.train as vposer_train

    def work(*a, **k):
        raise AssertionError("training started before --out was checked")

    monkeypatch.setattr(vposer_train, "train_vposer", work)
    monkeypatch.setattr(hmvae_train, "train_embedded", work)
    (tmp_path / "afile").write_text("mine")
    (tmp_path / "hmvae.json").write_text("mine")
    for main_, argv, says in ((vposer_train.main, ["--out", str(tmp_path / "afile")], "is a file, not a folder"),
                              (hmvae_train.main, ["--out", str(tmp_path)], "hmvae.json exists")):
        with pytest.raises(SystemExit) as info:
            main_(argv + ["--steps", "1"])
        assert str(info.value.code).startswith("error: ") and says in str(info.value.code)
    assert (tmp_path / "afile").read_text() == "mine" and (tmp_path / "hmvae.json").read_text() == "mine"


def test_every_recipe_has_its_command_line(tmp_path, monkeypatch, capsys):
    """docs/priors.md: every recipe runs as `python -m priors.NAME.train`. The structured latent
    space's module had no `main`: the command did nothing and said nothing."""
    import importlib
    from pathlib import Path

    import priors

    names = sorted(p.parent.name for p in Path(priors.__file__).parent.glob("*/train.py"))
    assert "structured_latent" in names and len(names) >= 6
    for name in names:
        module = importlib.import_module(f"priors.{name}.train")
        assert callable(getattr(module, "main", None)), name
        assert 'if __name__ == "__main__":' in Path(module.__file__).read_text(), name
        with pytest.raises(SystemExit) as info:
            module.main(["--help"])
        assert info.value.code == 0 and "--out" in capsys.readouterr().out, name
    import priors.structured_latent.train as sl_train

    monkeypatch.setattr(sl_train, "train_structured_latent", lambda *a, **k: pytest.fail("trained before --out was checked"))
    (tmp_path / "afile").write_text("mine")
    with pytest.raises(SystemExit) as info:
        sl_train.main(["--out", str(tmp_path / "afile"), "--steps", "1"])
    assert "is a file, not a folder" in str(info.value.code) and (tmp_path / "afile").read_text() == "mine"


def test_an_interrupted_training_says_how_to_resume(tmp_path, monkeypatch, capsys):
    """Ctrl-C in a training printed only "interrupted"; it now names the kept state and the command."""
    from priors.vposer import adapter

    def train_embedded(cls, **kw):
        if kw.get("steps") == 2:  # a checkpoint was written, then Ctrl-C
            (tmp_path / ".train_state" / "vposer-slerp").mkdir(parents=True, exist_ok=True)
            (tmp_path / ".train_state" / "vposer-slerp" / "loop0.pt").write_bytes(b"state")
        raise KeyboardInterrupt

    monkeypatch.setattr(adapter.VPoserSlerp, "train_embedded", classmethod(train_embedded))
    assert main(["train", "vposer-slerp", "--steps", "1", "--out", str(tmp_path)]) == 130
    assert "stopped before its first checkpoint (every 200 steps); nothing to resume" in capsys.readouterr().err
    assert main(["train", "vposer-slerp", "--steps", "2", "--seed", "3", "--out", str(tmp_path)]) == 130
    err = capsys.readouterr().err
    assert "the training state is kept in" in err and "(loop0.pt)" in err
    assert f"`python -m benchmark train vposer-slerp --steps 2 --seed 3 --out {tmp_path} --resume` continues it" in err
