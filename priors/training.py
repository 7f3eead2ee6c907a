"""The shared training recipe of the embedded priors: data, skeleton, a seeded loop, outputs.

Every embedded checkpoint in ``priors/weights/`` is trained by the project on its own synthetic
training split (``benchmark.synthetic.splits.build_split("train")``), on a CPU, from a seed, and
ships with a JSON record beside it (data, sizes, steps, seed, wall time, losses, library versions,
date). A prior's own module owns its network and loss; this module owns what they share:

- :func:`split_motions` / :func:`pose_frames`: the motions of a split of the dataset the caller
  hands the recipe, and a seeded subsample of their frames as axis-angle poses (N, 22, 3).
- :func:`fixed_rest_skeleton`: the fixed rest skeleton (22, 3) used by forward-kinematics losses.
- :func:`seed_everything` and :func:`train_loop`: a seeded Adam loop over random mini-batches.
- :func:`save_checkpoint` / :func:`write_record`: atomic writes of the weights and the record.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import math
import platform
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import torch

from benchmark.core.skeleton import NUM_JOINTS, SMPL_LIKE_REST_JOINTS
from priors.training_state import (TrainingSession, atomic_write, check_finite, current_session, load_state, restore,
                                   save_state)

log = logging.getLogger(__name__)

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


# -- data ------------------------------------------------------------------------------------
# A recipe never builds its training data: the caller hands it a *dataset*, an object with
#   split(name) -> list of Motion   the motions of a split ("train", "val")
#   source(name) -> str             where that split comes from (the training record says it)
# and, for recipes that train on motion cycles, find_cycles(motion, **options) -> cycles. The
# `train` command and the recipes' command lines pass
# benchmark.synthetic.train_data.SyntheticTrainingData (the synthetic splits).
def split_motions(dataset, split: str) -> list:
    """The motions of ``split`` of ``dataset`` (above); a clear error when no dataset was given or the
    split is empty."""
    if dataset is None:
        raise ValueError(f"no training data for the {split!r} split: pass dataset= (what `python -m benchmark train` "
                         "passes: benchmark.synthetic.train_data.SyntheticTrainingData()) or explicit training data "
                         "(poses=, windows=, motions= of the prior's training function)")
    motions = dataset.split(split)
    if not motions:
        raise RuntimeError(f"{dataset.source(split)} returned no motions")
    return list(motions)


def pose_frames(motions: list, every: int = 1, max_frames: int | None = None, seed: int = 0) -> torch.Tensor:
    """(N, 22, 3) axis-angle poses (radians) of the frames of ``motions``.

    Takes every ``every``-th frame of each motion (``motion.poses`` (T, 22, 3)), concatenates them,
    and if more than ``max_frames`` remain keeps a random subset of that size (drawn with ``seed``,
    kept in the original order). Float32, CPU.
    """
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    chunks = []
    for i, m in enumerate(motions):
        poses = torch.as_tensor(m.poses, dtype=torch.float32)
        if poses.dim() != 3 or poses.shape[1:] != (NUM_JOINTS, 3):
            raise ValueError(f"motion {i} ({getattr(m, 'name', '?')}): poses must be (T, {NUM_JOINTS}, 3), got {tuple(poses.shape)}")
        chunks.append(poses[::every])
    if not chunks:
        raise ValueError("no motions given")
    frames = torch.cat(chunks)
    if max_frames is not None and frames.shape[0] > max_frames:
        g = torch.Generator().manual_seed(seed)
        keep = torch.randperm(frames.shape[0], generator=g)[:max_frames].sort().values
        frames = frames[keep]
    return frames


def motion_windows(motions: list, frames: int, stride: int, fps: float | None = 30.0,
                   max_windows: int | None = None, seed: int = 0) -> torch.Tensor:
    """(N, frames, 69) windows of ``motions``: per frame [axis-angle poses 22x3 (66), translation (3)].

    Each motion is resampled to ``fps`` (SLERP, exact rate; None keeps its frames), then cut into
    windows of ``frames`` consecutive frames every ``stride`` frames (windows never span two
    motions). Translation is absolute (world, y up); a prior normalises it as its paper does. If
    more than ``max_windows`` remain, a seeded random subset is kept. Split the result with
    :func:`unpack_windows`. Float32, CPU.
    """
    if frames < 1 or stride < 1:
        raise ValueError(f"frames and stride must be >= 1, got {frames}, {stride}")
    chunks = []
    for m in motions:
        if fps is not None and abs(m.fps - fps) > 1e-6:
            m = m.resample_fps(fps)
        x = torch.cat([torch.as_tensor(m.poses, dtype=torch.float32).reshape(-1, NUM_JOINTS * 3),
                       torch.as_tensor(m.trans, dtype=torch.float32)], dim=1)
        if x.shape[0] >= frames:
            chunks.append(x.unfold(0, frames, stride).permute(0, 2, 1))
    if not chunks:
        raise ValueError(f"no motion has {frames} frames at {fps} fps")
    out = torch.cat(chunks).contiguous()
    if max_windows is not None and out.shape[0] > max_windows:
        g = torch.Generator().manual_seed(seed)
        out = out[torch.randperm(out.shape[0], generator=g)[:max_windows].sort().values]
    return out


def unpack_windows(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, F, 69) windows -> poses (N, F, 22, 3) axis-angle, trans (N, F, 3)."""
    return x[..., : NUM_JOINTS * 3].unflatten(-1, (NUM_JOINTS, 3)), x[..., NUM_JOINTS * 3 :]


def fixed_rest_skeleton() -> tuple[torch.Tensor, str]:
    """(22, 3) rest joint positions (metres, pelvis at the origin) and where they come from.

    The default embedded Anny body's T-pose joints at its default shape when the body can be built,
    else :data:`benchmark.core.skeleton.SMPL_LIKE_REST_JOINTS`. The source string goes into the training record.
    """
    try:
        from benchmark.body.anny_body import load_anny_body

        body = load_anny_body("cpu")
        with torch.no_grad():
            joints = body.rest_joints(body.default_shape(1))[0].float()
        return (joints - joints[0]).cpu(), "anny default body rest_joints (default shape), pelvis-centred"
    except Exception as exc:  # the fallback is documented and recorded
        log.warning("embedded Anny body unavailable (%s: %s); using the SMPL-like fallback skeleton", type(exc).__name__, exc)
        return torch.tensor(SMPL_LIKE_REST_JOINTS, dtype=torch.float32), (
            f"SMPL-like fallback skeleton (benchmark/core/skeleton.py SMPL_LIKE_REST_JOINTS); Anny body unavailable: {type(exc).__name__}"
        )


# -- the loop --------------------------------------------------------------------------------
def seed_everything(seed: int) -> torch.Generator:
    """Seed torch's global RNG (initialisation, dropout) and return a CPU generator for batching."""
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)


@dataclass
class TrainResult:
    steps: int
    wall_s: float
    final_train: dict  # mean of each loss part over the last ``log_every`` steps
    final_val: dict | None
    history: list = field(default_factory=list)  # [{"step", parts...}] every log_every steps


def train_loop(
    model: torch.nn.Module,
    loss_fn: Callable[[torch.nn.Module, torch.Tensor], dict],
    data: torch.Tensor,
    *,
    steps: int,
    batch_size: int,
    seed: int,
    lr: float = 1e-3,
    weight_decay: float = 0.0,
    final_lr_ratio: float = 0.1,
    log_every: int = 100,
    val_data: torch.Tensor | None = None,
    val_batch: int = 4096,
    num_threads: int | None = 1,
) -> TrainResult:
    """Adam over shuffled mini-batches of ``data`` (first dim = samples), seeded.

    ``loss_fn(model, batch)`` returns a dict of scalar tensors with a ``"loss"`` entry to minimise
    (the other entries are logged). The learning rate follows a cosine from ``lr`` down to
    ``lr * final_lr_ratio``. Batches are epoch-wise permutations drawn from a generator seeded with
    ``seed``; ``torch.manual_seed(seed)`` is set too (call it before building the model for a
    reproducible initialisation). The validation loss (``loss_fn`` in eval mode, no gradient, mean
    over chunks of ``val_batch``) is computed once at the end.

    num_threads: torch intra-op threads during the loop (restored afterwards); None keeps the
    current setting. The default is 1: the embedded networks' matrices are small, and on a shared
    2-core machine two OpenMP threads were measured 40x slower than one (13 ms vs 540 ms per VPoser
    step; spin barriers under oversubscription), while on an idle machine two gain little.
    """
    old_threads = torch.get_num_threads()
    if num_threads is not None:
        torch.set_num_threads(num_threads)
    try:
        return _train_loop(model, loss_fn, data, steps, batch_size, seed, lr, weight_decay, final_lr_ratio, log_every,
                           val_data, val_batch, current_session())
    finally:
        torch.set_num_threads(old_threads)


def _train_loop(model, loss_fn, data, steps, batch_size, seed, lr, weight_decay, final_lr_ratio, log_every, val_data,
                val_batch, session: TrainingSession | None = None) -> TrainResult:
    if steps < 1 or batch_size < 1:
        raise ValueError(f"steps and batch_size must be >= 1, got {steps}, {batch_size}")
    n = data.shape[0]
    if n < 2:
        raise ValueError(f"need at least 2 training samples, got {n}")
    batch_size = min(batch_size, n)
    gen = seed_everything(seed)
    params = [p for p in model.parameters() if p.requires_grad]
    # fused Adam: one kernel for every tensor (measured 6x faster steps on the 7.6 M-parameter
    # embedded frequency-guided prior on one CPU core); the same update rule as the default.
    opt = torch.optim.Adam(params, lr=lr, weight_decay=weight_decay, fused=True)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: final_lr_ratio + (1 - final_lr_ratio) * 0.5 * (1 + math.cos(math.pi * min(s, steps) / steps))
    )
    model.train()
    perm, pos = torch.randperm(n, generator=gen), 0
    history, window = [], []
    final_train, start, before, saved = None, 1, 0.0, 0
    state_path = session.state_path() if session is not None else None
    if state_path is not None and session.resume and state_path.exists():
        state = load_state(state_path, steps, seed, n)
        restore(state_path, state, model, opt, sched, gen)
        perm, pos, history, final_train = state["perm"], state["pos"], state["history"], state["final_train"]
        start, before = state["step"] + 1, state["wall_s"]
        saved = state["step"]
        log.info("resumed %s at step %d of %d", state_path, state["step"], steps)

    def checkpoint(step: int, wall: float) -> None:
        save_state(state_path, {
            "steps": steps, "seed": seed, "samples": n, "step": step, "model": model.state_dict(),
            "optimiser": opt.state_dict(), "schedule": sched.state_dict(), "generator": gen.get_state(),
            "torch_rng": torch.get_rng_state(), "perm": perm, "pos": pos, "history": history,
            "final_train": final_train, "wall_s": wall})

    t0 = time.perf_counter() - before
    for step in range(start, steps + 1):
        if pos + batch_size > n:
            perm, pos = torch.randperm(n, generator=gen), 0
        batch = data[perm[pos : pos + batch_size]]
        pos += batch_size
        parts = loss_fn(model, batch)
        loss = parts["loss"]
        if not torch.isfinite(loss):
            raise FloatingPointError(f"training diverged: non-finite training loss at step {step} "
                                     f"({ {k: float(v) for k, v in parts.items()} }); no weights were written. Train again "
                                     "with another --seed or fewer --steps")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        window.append({k: float(v.detach()) for k, v in parts.items()})
        if step % log_every == 0 or step == steps:
            mean = {k: sum(w[k] for w in window) / len(window) for k in window[0]}
            entry = {"step": step, **mean}
            if session is not None and session.val_every and val_data is not None and (
                    step % session.val_every == 0 or step == steps):
                entry.update({f"val_{k}": v for k, v in evaluate(model, loss_fn, val_data, val_batch).items()})
            entry["wall_s"] = round(time.perf_counter() - t0, 2)
            history.append(entry)
            log.info("step %d/%d %s", step, steps, " ".join(f"{k}={v:.4g}" for k, v in entry.items() if k != "step"))
            final_train, window = mean, []
        # at a log step (no partial window to save), once per checkpoint_every steps, and at the end
        if state_path is not None and not window and (step // session.checkpoint_every > saved // session.checkpoint_every
                                                      or step == steps):
            check_finite(model, step)  # a diverged model is never saved as a state to continue from
            checkpoint(step, time.perf_counter() - t0)
            saved = step
    wall = time.perf_counter() - t0
    check_finite(model, steps)  # the last update can turn the weights to NaN after a finite loss
    final_val = evaluate(model, loss_fn, val_data, val_batch) if val_data is not None else None
    if final_val is not None and not all(math.isfinite(v) for v in final_val.values()):
        raise FloatingPointError(f"training diverged: the validation loss after step {steps} is not finite ({final_val}); "
                                 "no weights were written. Train again with another --seed or fewer --steps")
    return TrainResult(steps=steps, wall_s=wall, final_train=final_train, final_val=final_val, history=history)


@torch.no_grad()
def evaluate(model: torch.nn.Module, loss_fn: Callable, data: torch.Tensor, chunk: int = 4096) -> dict:
    """Sample-weighted mean of each ``loss_fn`` part over ``data``, model in eval mode (then restored)."""
    was_training = model.training
    model.eval()
    totals: dict[str, float] = {}
    for i in range(0, data.shape[0], chunk):
        batch = data[i : i + chunk]
        for k, v in loss_fn(model, batch).items():
            totals[k] = totals.get(k, 0.0) + float(v) * batch.shape[0]
    model.train(was_training)
    return {k: v / data.shape[0] for k, v in totals.items()}


# -- outputs ---------------------------------------------------------------------------------
def save_checkpoint(path: str | Path, state_dict: dict, config: dict) -> Path:
    """Write ``{"state_dict": ..., "config": ...}`` (CPU tensors, torch.save) atomically."""
    path = Path(path)
    payload = {"state_dict": {k: v.detach().cpu().clone() for k, v in state_dict.items()}, "config": dict(config)}
    bad = [k for k, v in payload["state_dict"].items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:  # a diverged training, or weights out of range of their stored type (float16)
        raise FloatingPointError(f"{path}: not written: {', '.join(bad[:3])}{' ...' if len(bad) > 3 else ''} hold NaN or "
                                 "inf (the training diverged); train again with another --seed or fewer --steps")
    atomic_write(path, lambda tmp: torch.save(payload, tmp))
    return path


def embedded_out_dir(out_dir: str | Path | None, default_weights: Path, overwrite: bool) -> Path:
    """The folder a prior's ``train_embedded`` writes to: ``out_dir``, or by default the folder of
    ``default_weights``; refuses (FileExistsError) when it already holds that checkpoint or its
    training record (:func:`refuse_overwrite`) and ``overwrite`` is false."""
    out = Path(out_dir) if out_dir is not None else default_weights.parent
    refuse_overwrite(out, [default_weights.name], overwrite)
    return out


def refuse_overwrite(out: Path, checkpoint_names: list[str], overwrite: bool) -> None:
    """FileExistsError unless ``overwrite``, when ``out`` holds one of the files a training writes:
    each checkpoint of ``checkpoint_names`` and its record (same stem, ``.json``: :func:`save_trained`)."""
    names = [f for n in checkpoint_names for f in (n, Path(n).with_suffix(".json").name)]
    existing = [str(Path(out) / n) for n in names if (Path(out) / n).exists()]
    if existing and not overwrite:
        them = "it" if len(existing) == 1 else "them"
        raise FileExistsError(f"{', '.join(existing)} exist{'s' if len(existing) == 1 else ''} (a training writes "
                              f"{', '.join(names)}): pass --force to overwrite {them}, or --out DIR to write elsewhere")


def recipe_parser(description: str, default_weights: Path, steps: int, min_steps: int = 1):
    """The command line every ``python -m priors.<name>.train`` shares: ``--out`` (default: the folder of
    ``default_weights``), ``--steps`` (at least ``min_steps``), ``--seed``, ``--force``; a recipe adds
    its own options to it (numbers range-checked with :mod:`benchmark.core.argtypes`)."""
    import argparse

    from benchmark.core import argtypes as at

    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--out", default=str(default_weights.parent), help="output folder (default: %(default)s)")
    ap.add_argument("--steps", type=at.Number(int, min_steps), default=steps, help="training steps (default: %(default)s)")
    ap.add_argument("--seed", type=at.seed, default=0)
    ap.add_argument("--force", action="store_true", help="overwrite existing weights")
    return ap


def parse_recipe_args(ap, default_weights: Path, argv: list[str] | None = None):
    """Parse a :func:`recipe_parser` command line, turn on INFO logging and refuse to overwrite
    existing weights without ``--force`` (exit with the reason)."""
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    check_recipe_out(args.out, [default_weights.name], args.force)
    return args


def check_recipe_out(out: str | Path, checkpoint_names: list[str], force: bool) -> None:
    """Before any data is built or step trained, for a recipe's command line: ``--out`` must be a
    folder that can be created and written, and (without ``force``) hold none of the files the
    training writes (:func:`refuse_overwrite`); else exit with the reason (exit code 1, no traceback)."""
    from benchmark.core.outdir import check_out_dir

    try:
        refuse_overwrite(check_out_dir(out, min_free_bytes=1 << 20), checkpoint_names, force)
    except (FileExistsError, ValueError) as exc:
        raise SystemExit(f"error: {exc}") from None


def save_trained(out_dir: str | Path, checkpoint_name: str, state_dict: dict, config: dict, record: dict) -> Path:
    """Write a trained model into ``out_dir``: the checkpoint (:func:`save_checkpoint`) and, beside it
    with the same stem and ``.json``, its training record (``record`` gains ``checkpoint_bytes``).
    Returns the checkpoint's path."""
    out = Path(out_dir)
    ckpt = save_checkpoint(out / checkpoint_name, state_dict, config)
    record["checkpoint_bytes"] = ckpt.stat().st_size
    rec_path = out / Path(checkpoint_name).with_suffix(".json").name
    write_record(rec_path, record)
    log.info("wrote %s (%d bytes) and %s", ckpt, record["checkpoint_bytes"], rec_path)
    return ckpt


def loop_record(result, *, steps: int, seed: int, lr: float, weight_decay: float, final_lr_ratio: float,
                batch_size: int) -> dict:
    """The training-record fields of one :func:`train_loop` run (optimiser, steps, timing, losses,
    history, environment)."""
    return {
        "optimiser": {"name": "Adam", "lr": lr, "weight_decay": weight_decay, "schedule": f"cosine to {final_lr_ratio}*lr",
                      "batch_size": batch_size},
        "steps": steps,
        "seed": seed,
        "torch_threads_training": 1,
        "train_wall_s": round(result.wall_s, 2),
        "seconds_per_step": round(result.wall_s / steps, 4),
        "final_train": result.final_train,
        "final_val": result.final_val,
        "history": result.history,
        **environment_record(),
    }


def environment_record() -> dict:
    """Library versions, host, date and git revision, for a training record."""
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent, capture_output=True, text=True, timeout=10
        ).stdout.strip() or None
    except Exception:
        rev = None
    return {
        "torch": torch.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "torch_threads": torch.get_num_threads(),
        "git_revision": rev,
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }


def write_record(path: str | Path, record: dict) -> Path:
    """Write a JSON training record atomically (sorted keys, indented)."""
    path = Path(path)
    text = json.dumps(record, indent=2, sort_keys=True) + "\n"

    def write(tmp: str) -> None:
        with open(tmp, "w") as f:
            f.write(text)

    atomic_write(path, write)
    return path


__all__ = [
    "WEIGHTS_DIR",
    "refuse_overwrite",
    "split_motions",
    "pose_frames",
    "fixed_rest_skeleton",
    "seed_everything",
    "TrainResult",
    "train_loop",
    "evaluate",
    "save_checkpoint",
    "environment_record",
    "write_record",
]
