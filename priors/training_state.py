"""The resumable state of the embedded training loops (``python -m benchmark train NAME --resume``).

:class:`training_session` sets, for the :func:`priors.training.train_loop` calls of a ``with``
block, where each loop saves its state (``state_dir/loop<k>.pt``) and whether it continues from it.
:func:`load_state` reads and checks such a file: a state that is unreadable, incomplete, of another
run (steps, seed, data) or holding non-finite numbers is refused with the file and the fix.
:func:`check_finite` is the divergence check of the loop: it names the first non-finite parameter.
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

from benchmark.core.safe_loading import UnsafeFileError, torch_load_weights

# what a loop saves (priors.training.train_loop); a state without one of them cannot be continued
STATE_KEYS = ("steps", "seed", "samples", "step", "model", "optimiser", "schedule", "generator", "torch_rng", "perm",
              "pos", "history", "final_train", "wall_s")
RESUME_FIX = "delete it to train from the start, or rerun without --resume (with --force where the weights exist)"


@dataclass
class TrainingSession:
    """Where a training run keeps its resumable state, set for the runs of a ``with`` block
    (:func:`training_session`). Every :func:`priors.training.train_loop` call of the block is numbered
    in call order (a recipe that trains two networks makes two calls) and saves, every
    ``checkpoint_every`` steps, its model, optimiser, schedule, batching generator, position in the
    epoch, history and elapsed time to ``state_dir/loop<k>.pt`` (atomically; the folder is created
    at the first save). With ``resume``, a call whose state file exists continues from it, and a
    call that had finished is replayed from its final state without training; the result is the
    same as an uninterrupted run's (the batch order and every update are restored exactly).
    ``val_every``: also log the validation loss every that many steps (0: only at the end)."""

    state_dir: Path
    resume: bool = False
    checkpoint_every: int = 200
    val_every: int = 0
    calls: int = 0

    def state_path(self) -> Path:
        path = self.state_dir / f"loop{self.calls}.pt"
        self.calls += 1
        return path


_SESSION: TrainingSession | None = None


def current_session() -> TrainingSession | None:
    """The session of the enclosing ``with training_session(...)`` block, or None."""
    return _SESSION


class training_session:
    """``with training_session(state_dir, resume=...):`` makes every :func:`priors.training.train_loop`
    inside checkpoint into ``state_dir`` and, with ``resume``, continue from it (:class:`TrainingSession`)."""

    def __init__(self, state_dir: str | Path, resume: bool = False, checkpoint_every: int = 200, val_every: int = 0):
        self.session = TrainingSession(Path(state_dir), resume, checkpoint_every, val_every)

    def __enter__(self) -> TrainingSession:
        global _SESSION
        if _SESSION is not None:
            raise RuntimeError("training_session: sessions do not nest")
        _SESSION = self.session
        return self.session

    def __exit__(self, *exc) -> None:
        global _SESSION
        _SESSION = None


def saved_states(state_dir: str | Path) -> list[Path]:
    """The loop states (``loop<k>.pt``) in ``state_dir``, sorted; [] when there are none."""
    folder = Path(state_dir)
    return sorted(folder.glob("loop*.pt")) if folder.is_dir() else []


def check_finite(model: torch.nn.Module, step: int) -> None:
    """Raise FloatingPointError naming the first parameter or buffer of ``model`` holding NaN or inf
    (the training diverged at or before ``step``)."""
    for name, t in list(model.named_parameters()) + list(model.named_buffers()):
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise FloatingPointError(
                f"training diverged: {name} holds NaN or inf after step {step}; no weights were written. Train again "
                "with another --seed or fewer --steps (a resumable state saved before this step is kept)")


def atomic_write(path: Path, write: Callable[[str], None]) -> None:
    """Write ``path`` through ``write(tmp)`` on a temporary file beside it, then rename it into place
    (the folder is created; a failed write leaves no file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; shipped files are world-readable
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def save_state(path: Path, state: dict) -> None:
    """Save a loop's state (the keys of :data:`STATE_KEYS`, and a recipe's own) atomically."""
    atomic_write(path, lambda tmp: torch.save(state, tmp))


def load_state(path: Path, steps: int, seed: int, n: int) -> dict:
    """The saved state of a loop of ``steps`` steps, seeded with ``seed``, over ``n`` samples; a
    ValueError naming the file and the fix when it cannot be continued."""
    try:
        # plain tensors, numbers, lists and dicts (optimiser and schedule state dicts included):
        # weights_only=True reads all of it, and a file holding anything else is refused
        state = torch_load_weights(path, RESUME_FIX)
    except UnsafeFileError:
        raise
    except Exception as exc:
        raise ValueError(f"{path}: unreadable training state ({type(exc).__name__}: {exc}); {RESUME_FIX}") from None
    if not isinstance(state, dict):
        raise ValueError(f"{path}: not a training state (a {type(state).__name__}, expected a dict); {RESUME_FIX}")
    missing = [k for k in STATE_KEYS if k not in state]
    if missing:
        raise ValueError(f"{path}: incomplete training state (no {', '.join(missing)}); {RESUME_FIX}")
    mine = {"steps": steps, "seed": seed, "samples": n}
    theirs = {k: state.get(k) for k in mine}
    if theirs != mine:
        again = ""
        if theirs["samples"] == n:
            again = f"continue it with --steps {theirs['steps']} --seed {theirs['seed']}, or "
        raise ValueError(f"{path}: saved by a different training run ({theirs}, this run {mine}); {again}delete it or "
                         "rerun without --resume (with --force where the weights exist) to start over")
    if not (isinstance(state["step"], int) and 1 <= state["step"] <= steps):
        raise ValueError(f"{path}: step {state['step']!r} is not a step of this run (1 to {steps}); {RESUME_FIX}")
    bad = [k for k, v in state["model"].items() if torch.is_tensor(v) and v.is_floating_point()
           and not bool(torch.isfinite(v).all())] if isinstance(state["model"], dict) else []
    if bad or not math.isfinite(float(state["wall_s"])):
        raise ValueError(f"{path}: the saved model holds NaN or inf ({', '.join(bad[:3]) or 'wall_s'}); the training had "
                         f"diverged before it was saved: {RESUME_FIX}")
    return state


def restore(path: Path, state: dict, model: torch.nn.Module, opt, sched, gen: torch.Generator) -> None:
    """Load ``state`` (:func:`load_state`) into the model, optimiser, schedule and the random
    generators; a ValueError naming the file when it does not fit them (a state of another network)."""
    try:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimiser"])
        sched.load_state_dict(state["schedule"])
        gen.set_state(state["generator"])
        torch.set_rng_state(state["torch_rng"])
    except (RuntimeError, ValueError, KeyError, TypeError) as exc:
        first = str(exc).strip().splitlines()
        raise ValueError(f"{path}: the saved state does not fit this network ({type(exc).__name__}: "
                         f"{' '.join(line.strip() for line in first[:3])}); {RESUME_FIX}") from None


__all__ = ["TrainingSession", "atomic_write", "save_state", "training_session", "current_session", "saved_states", "check_finite", "load_state",
           "restore", "STATE_KEYS"]
