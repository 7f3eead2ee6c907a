"""The synthetic dataset splits and their on-disk cache.

Splits (see ``datasets/synthetic.md``):

- ``test``: mirrors the paper's table1 test set: 4 subjects (2 male, 2 female), 170 sequences of
  4.4 s at 50 fps: boxing, kicking, sidestepping, kinds of walking and running, one cartwheel.
- ``train``: 12 other subjects, 50 random multi-action sequences each (10-20 s, every action),
  30 fps, 2.5 hours; for training the embedded priors.
- ``val``: 2 other subjects, 12 sequences each (8-12 s), 30 fps.

``build_split(name)`` returns the split as a list of :class:`~benchmark.core.motion.Motion`, built on
the embedded Anny body by default (the generator stands each subject on its own mesh). Built
splits are cached under ``datasets/cache/<split>/`` (git-ignored): one ``.npz`` per sequence and
a ``manifest.json`` (split, seed, generator version, skeleton digest, per-file sha256). A cache
whose manifest does not match (another generator version, seed or body) or whose files fail
their hash is rebuilt; the build is deterministic, so the same seed gives the same arrays.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from benchmark.core.motion import Motion
from benchmark.synthetic.generator import GENERATOR_VERSION, SequencePlan, SyntheticSequence
from benchmark.synthetic.plans import plan_random_split, plan_test_split
from benchmark.synthetic.rest import skeleton_source
from benchmark.synthetic.subjects import TEST_SUBJECTS, Subject, sample_subjects

log = logging.getLogger(__name__)

CACHE_ENV = "MOTION_BENCHMARK_CACHE"  # overrides the cache root (default: <repo>/datasets/cache)
_REPO_CACHE = Path(__file__).resolve().parents[2] / "datasets" / "cache"


@dataclass(frozen=True)
class SplitSpec:
    """How a split is made: its subjects and plans from a seed, and its frame rate."""

    name: str
    seed: int
    fps: float
    subjects: Callable[[int], list[Subject]]
    plans: Callable[[list[Subject], int], list[SequencePlan]]
    description: str


SPLITS: dict[str, SplitSpec] = {
    "test": SplitSpec(
        "test", 1000, 50.0, lambda seed: list(TEST_SUBJECTS),
        lambda subjects, seed: plan_test_split(subjects, seed),
        "4 subjects (2 male, 2 female), 170 sequences of 4.4 s at 50 fps",
    ),
    "train": SplitSpec(
        "train", 2000, 30.0, lambda seed: sample_subjects(12, seed, "train"),
        lambda subjects, seed: plan_random_split(subjects, seed, per_subject=50, duration=(10.0, 20.0)),
        "12 subjects, 600 random multi-action sequences of 10-20 s at 30 fps",
    ),
    "val": SplitSpec(
        "val", 3000, 30.0, lambda seed: sample_subjects(2, seed, "val"),
        lambda subjects, seed: plan_random_split(subjects, seed, per_subject=12, duration=(8.0, 12.0)),
        "2 subjects, 24 random multi-action sequences of 8-12 s at 30 fps",
    ),
}


def get_spec(name: str) -> SplitSpec:
    if name not in SPLITS:
        raise KeyError(f"unknown synthetic split {name!r}; known: {', '.join(SPLITS)}")
    return SPLITS[name]


def split_plans(name: str, seed: int | None = None) -> list[SequencePlan]:
    """The plans of a split (cheap: no motion is generated). Plan i becomes motion i."""
    spec = get_spec(name)
    seed = spec.seed if seed is None else int(seed)
    return spec.plans(spec.subjects(seed), seed)


def cache_dir(name: str, seed: int | None = None, root: str | os.PathLike | None = None) -> Path:
    """``<root>/<split>/`` for the split's own seed, ``<root>/<split>-seed<N>/`` for another."""
    spec = get_spec(name)
    base = Path(root) if root is not None else Path(os.environ.get(CACHE_ENV, _REPO_CACHE))
    return base / (name if seed is None or int(seed) == spec.seed else f"{name}-seed{int(seed)}")


@contextmanager
def _single_threaded():
    """Generation runs on many small tensors, where torch's intra-op threads bring nothing and,
    on a busy machine, cost a lot (measured 50x slower with 2 threads on 2 loaded cores); the
    previous thread count is restored on exit."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def generate_split(name: str, body=None, seed: int | None = None, limit: int | None = None) -> list[Motion]:
    """Generate a split's motions in memory (no cache). ``body``: see :func:`build_split`;
    ``limit``: only the first ``limit`` sequences (for quick looks and tests)."""
    spec = get_spec(name)
    seed = spec.seed if seed is None else int(seed)
    plans = split_plans(name, seed)
    if limit is not None:
        plans = plans[:limit]
    source = skeleton_source(body)
    out = []
    with _single_threaded():
        for i, plan in enumerate(plans):
            skeleton = source.rest_skeleton(plan.subject.phenotype)
            seq = SyntheticSequence(plan, skeleton)
            out.append(seq.to_motion(spec.fps, source=f"synthetic:{name}:{i:04d}",
                                     meta={"split": name, "index": i, "split_seed": seed,
                                           "subject_info": plan.subject.to_meta()}))
    return out


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _skeleton_digest(name: str, seed: int, source) -> str:
    h = hashlib.sha256()
    for subject in get_spec(name).subjects(seed):
        h.update(source.rest_skeleton(subject.phenotype).digest().encode())
    return h.hexdigest()


def _manifest_problem(folder: Path, expected: dict) -> str | None:
    """Why the cache in ``folder`` cannot be used (None if it can)."""
    path = folder / "manifest.json"
    if not path.is_file():
        return "no manifest"
    try:
        manifest = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        return f"unreadable manifest ({e})"
    for key, value in expected.items():
        if manifest.get(key) != value:
            return f"manifest {key!r} is {manifest.get(key)!r}, expected {value!r}"
    files = manifest.get("files", [])
    if len(files) != manifest.get("count"):
        return "manifest file list does not match its count"
    for entry in files:
        f = folder / entry["file"]
        if not f.is_file():
            return f"missing {f.name}"
        if _sha256(f) != entry["sha256"]:
            return f"{f.name} fails its sha256"
    return None


def _foreign_files(folder: Path, name: str) -> list[str]:
    """The ``.npz`` files in a split's cache folder that a build of split ``name`` did not write:
    neither listed in the folder's manifest nor named as the build names its files
    (``NAME_0000.npz``; an interrupted build leaves those without a manifest). A rebuild replaces
    only its own files, so it refuses a folder holding others."""
    if not folder.is_dir():
        return []
    listed: set[str] = set()
    try:
        listed = {str(e["file"]) for e in json.loads((folder / "manifest.json").read_text())["files"]}
    except (OSError, ValueError, KeyError, TypeError):
        pass
    own = re.compile(rf"{re.escape(name)}_\d{{4}}\.npz")
    return sorted(p.name for p in folder.glob("*.npz") if p.name not in listed and not own.fullmatch(p.name))


def build_split(
    name: str,
    body=None,
    seed: int | None = None,
    rebuild: bool = False,
    root: str | os.PathLike | None = None,
    cache: bool = True,
) -> list[Motion]:
    """The synthetic split ``name`` ("test", "train", "val") as a list of Motions.

    body: the body model whose rest skeleton the subjects stand on (each Motion's ``shape`` is
        the subject's phenotype for it); None for the embedded Anny body; or a skeleton source
        with ``rest_skeleton(phenotype)`` (e.g. ``CanonicalSkeletons()``, fast, for tests).
    seed: the split's seed (default: the split's own; another seed is cached beside it).
    rebuild: regenerate even if the cache is valid. root: the cache root (default
        ``$MOTION_BENCHMARK_CACHE`` or ``datasets/cache``). cache: False generates in memory only.
    """
    spec = get_spec(name)
    seed = spec.seed if seed is None else int(seed)
    source = skeleton_source(body)
    if not cache:
        return generate_split(name, source, seed)
    folder = cache_dir(name, seed, root)
    expected = {
        "split": name,
        "seed": seed,
        "generator_version": GENERATOR_VERSION,
        "fps": spec.fps,
        "skeleton_source": source.name,
        "skeleton_digest": _skeleton_digest(name, seed, source),
    }
    problem = "rebuild requested" if rebuild else _manifest_problem(folder, expected)
    if problem is None:
        return _load_cached(folder)
    with _build_lock(folder):  # one build at a time: another process asking for the split waits for it
        problem = "rebuild requested" if rebuild else _manifest_problem(folder, expected)
        if problem is None:  # built by the process we waited for
            return _load_cached(folder)
        return _build_into(folder, name, source, seed, spec, expected, problem)


def _load_cached(folder: Path) -> list[Motion]:
    manifest = json.loads((folder / "manifest.json").read_text())
    return [Motion.load(folder / e["file"]) for e in manifest["files"]]


@contextmanager
def _build_lock(folder: Path):
    """Held while a split is built into ``folder``: a second process (``run table1`` and ``run sls``
    started together on a fresh checkout) waits, then reads what the first built, instead of
    deleting and rewriting the files the first is writing. An advisory lock (``fcntl.flock``,
    released by the system if the holder dies) on ``.<split>.lock`` beside the folder; where the
    system has none (Windows), builds are not serialised."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    folder.parent.mkdir(parents=True, exist_ok=True)
    with open(folder.parent / f".{folder.name}.lock", "a+") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.info("synthetic split %s: another process is building it; waiting for it", folder.name)
            fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _build_into(folder: Path, name: str, source, seed: int, spec, expected: dict, problem: str) -> list[Motion]:
    foreign = _foreign_files(folder, name)
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
        raise FileExistsError(
            f"synthetic split {name!r}: its cache folder {folder} holds .npz files the split did not write "
            f"({shown}); building it there would replace them. Move them elsewhere, or point "
            "MOTION_BENCHMARK_CACHE at a folder of their own for the splits")
    log.info("building synthetic split %r in %s (%s)", name, folder, problem)
    t0 = time.perf_counter()
    motions = generate_split(name, source, seed)
    elapsed = time.perf_counter() - t0
    folder.mkdir(parents=True, exist_ok=True)
    keep = set(_foreign_files(folder, name))  # empty (checked above) unless a file appeared since
    (folder / "manifest.json").unlink(missing_ok=True)  # invalid until the new one is written
    for old in folder.glob("*.npz"):
        if old.name not in keep:
            old.unlink()
    entries = []
    for i, m in enumerate(motions):
        fname = f"{name}_{i:04d}.npz"
        m.save(folder / fname)
        entries.append({"file": fname, "sha256": _sha256(folder / fname), "source": m.source,
                        "subject": m.meta["subject"], "kind": m.meta["kind"], "frames": m.num_frames,
                        "duration": round(m.duration, 6)})
    manifest = {
        **expected,
        "description": spec.description,
        "count": len(entries),
        "total_seconds": round(sum(m.duration for m in motions), 3),
        "build_seconds": round(elapsed, 3),
        "files": entries,
    }
    fd, tmp = tempfile.mkstemp(dir=folder, prefix="manifest", suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        json.dump(manifest, f, indent=1)
    os.chmod(tmp, 0o644)
    os.replace(tmp, folder / "manifest.json")
    log.info("built %d sequences (%.1f min of motion) in %.1f s", len(motions), manifest["total_seconds"] / 60, elapsed)
    return motions


def content_digest(motion: Motion) -> str:
    """sha256 of a motion's arrays and metadata (independent of the .npz container's timestamps)."""
    h = hashlib.sha256()
    for a in (motion.poses, motion.trans, motion.timestamps):
        h.update(np.ascontiguousarray(a.numpy()).tobytes())
    if motion.shape is not None:
        h.update(np.ascontiguousarray(motion.shape.numpy()).tobytes())
    h.update(json.dumps(motion.meta, sort_keys=True, default=str).encode())
    h.update(f"{motion.body}|{motion.source}".encode())
    return h.hexdigest()
