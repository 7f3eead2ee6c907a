"""A cell's part of the report (:mod:`benchmark.report.build`): per-sequence diagnostics from the
stored fitted motions (:mod:`benchmark.data.unit_arrays`), the animations to render and their
rendering, here or in worker processes."""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmark.report.run_folder import RunFolder

log = logging.getLogger(__name__)

ANIMATION_SIZE = (140, 190)  # pixels of each of the two views
BACKWARDS_FRACTION = 0.5  # a sequence is flagged backwards when its fit faces > 90° away on this share of frames


@dataclass
class SequenceDiag:
    """Diagnostics of one fitted sequence, computed from its stored arrays."""

    facing_err_mean: float  # degrees
    root_err_mean: float  # degrees
    backwards_fraction: float  # share of output frames facing > 90° away from the ground truth
    v2v_mm: float | None = None  # mean per-vertex distance to the ground-truth mesh (animated sequences only)

    @property
    def backwards(self) -> bool:
        return self.backwards_fraction > BACKWARDS_FRACTION


FITTED_MOTION_PROTOCOLS = ("completion", "sls")  # the protocols whose units store their fitted motions (.npz)


@dataclass
class CellReport:
    table: str
    prior: str
    cell: dict
    anchor: str
    units: list
    seq_rows: list = field(default_factory=list)
    diag: dict = field(default_factory=dict)  # sequence id -> SequenceDiag
    animations: list = field(default_factory=list)  # (sequence id, relative path)
    facing_curves: list = field(default_factory=list)  # (label, t, facing error)
    no_animation: str | None = None  # why there is none


def safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", str(text)).strip("-")


@dataclass
class AnimationJob:
    """One animation to render (picklable: it runs in a worker process when ``workers`` > 1)."""

    npz: str
    index: int
    out: str
    title: str
    body_spec: str
    size: tuple
    fps: float
    cell_report: object = field(default=None, repr=False)  # filled in this process only
    sequence_id: str = ""

    def payload(self) -> tuple:
        return (self.npz, self.index, self.out, self.title, self.body_spec, self.size, self.fps)


def diagnose(run, cr: CellReport, img_dir: Path, sequences: int, fmt: str, body_spec, animation_fps: float,
              jobs: list) -> None:
    """Per-sequence diagnostics of a cell from its stored root rotations; queue its animations."""
    from benchmark.report.animate import check_arrays, root_diagnostics
    from benchmark.data.unit_arrays import read_arrays

    if not cr.units:
        cr.no_animation = "no unit file for this cell under units/"
        return
    missing = [u["unit_id"] for u in cr.units if not run.npz_path(u).exists()]
    protocol = next((t.get("protocol") for t in run.tables if t.get("table") == cr.table), None)
    if len(missing) == len(cr.units) and protocol not in (None, *FITTED_MOTION_PROTOCOLS):
        cr.no_animation = (f"no animation: the {protocol} protocol stores no fitted motion (only the completion "
                           "protocols, table1 and sls, keep theirs)")
        return
    if len(missing) == len(cr.units):
        cr.no_animation = ("animation unavailable: this run stored no fitted motion for this cell (no "
                           f"units/{missing[0]}.npz; units run before the harness kept it, or a protocol that does not "
                           "store it). Rerun the table with --resume never into a new --out folder to get it.")
        return
    done = 0
    for u in cr.units:
        path = run.npz_path(u)
        if not path.exists():
            continue
        try:
            arrays = read_arrays(path)
        except (OSError, ValueError) as exc:
            cr.no_animation = f"{path.name}: unreadable ({exc})"
            continue
        why = check_arrays(arrays, u, path.name)
        if why:
            cr.no_animation = f"animation unavailable: {why}"
            continue
        for b in range(len(arrays["sequence_ids"])):
            root_err, facing_err = root_diagnostics(arrays, b)
            sid = str(arrays["sequence_ids"][b])
            cr.diag[sid] = SequenceDiag(facing_err_mean=float(facing_err.mean()), root_err_mean=float(root_err.mean()),
                                        backwards_fraction=float((facing_err > 90.0).mean()))
            if done < sequences:
                name = f"anim__{safe_name(u['unit_id'])}__{b}.{fmt}"
                cr.facing_curves.append((sid, arrays["t"][b].astype(np.float64), facing_err))
                cr.animations.append((sid, name))
                jobs.append(AnimationJob(str(path), b, str(img_dir / name), f"{cr.prior} {cell_text(cr.cell)}",
                                         body_spec or run_body(run, cr.table), ANIMATION_SIZE, animation_fps,
                                         cell_report=cr, sequence_id=sid))
                done += 1


_WORKER_CACHE: dict = {}  # per process: body models and skinned ground truths


def render_animation(npz: str, index: int, out: str, title: str, body_spec: str, size, fps: float) -> float:
    """Skin, render and write one animation; returns the sequence's mean V2V error (mm)."""
    from benchmark.report.animate import animate, sequence_motion
    from benchmark.data.unit_arrays import read_arrays

    body = _body(body_spec, _WORKER_CACHE.setdefault("bodies", {}))
    motion = sequence_motion(read_arrays(npz), index, body, _WORKER_CACHE.setdefault("gt", {}))
    animate(motion, body, out, title=title, size=tuple(size), fps=fps)
    return float(motion.v2v_mm.mean())


def _init_worker() -> None:
    """A worker ignores Ctrl-C (the driver stops the pool): it was started with SIGINT blocked
    (:func:`benchmark.run.backends.local.sigint_blocked`), so none arrived before this point."""
    import signal

    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # discards a Ctrl-C pending since the start
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    torch.set_num_threads(1)


def _outcome(call, *args) -> tuple:
    """``(call(*args), None)``, or ``(None, "Type: message")`` when it raises an Exception (one bad
    job must not take the report down)."""
    try:
        return call(*args), None
    except Exception as exc:
        return None, f"{type(exc).__name__}: {exc}"


def run_in_pool(fn, payloads: list, workers: int) -> list:
    """``fn(*payload)`` for every payload in up to ``workers`` spawned processes (one torch thread
    each); returns ``(result, None)`` or ``(None, "Type: message")`` per payload, in order.

    The workers start (at the submits) with SIGINT blocked and ignore it (:func:`_init_worker`): a
    Ctrl-C reaches only this process, which drops the payloads not started and lets the running
    ones end, instead of a traceback from every half-started worker."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from benchmark.run.backends.local import sigint_blocked

    with sigint_blocked():
        pool = ProcessPoolExecutor(max_workers=min(workers, len(payloads)), mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_init_worker)
        futures = [pool.submit(fn, *payload) for payload in payloads]
    try:
        results = [_outcome(fut.result) for fut in futures]
    except BaseException:  # Ctrl-C
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()
    return results


def run_animation_jobs(jobs: list, workers: int = 1) -> None:
    """Render ``jobs`` here (``workers`` <= 1) or in that many spawned processes; a job that fails
    leaves its cell without that animation and says why on the page."""
    if not jobs:
        return
    if workers <= 1 or len(jobs) == 1:
        results = [_outcome(render_animation, *job.payload()) for job in jobs]
    else:
        results = run_in_pool(render_animation, [job.payload() for job in jobs], workers)
    for job, (v2v, error) in zip(jobs, results):
        cr = job.cell_report
        if error is None:
            cr.diag[job.sequence_id].v2v_mm = v2v
            continue
        log.error("report: animation of %s (%s) failed: %s", job.sequence_id, Path(job.npz).name, error)
        cr.animations = [(sid, name) for sid, name in cr.animations if name != Path(job.out).name]
        cr.facing_curves = [c for c in cr.facing_curves if c[0] != job.sequence_id]
        cr.no_animation = f"animation of {job.sequence_id} failed: {error}"


def run_body(run: RunFolder, table_name: str) -> str:
    for t in run.tables:
        if t["table"] == table_name:
            return t.get("body") or "anny"
    return "anny"


def _body(spec: str, cache: dict):
    if spec not in cache:
        from benchmark.body import get_body

        try:
            cache[spec] = get_body(spec, device="cpu")
        except (FileNotFoundError, ValueError) as exc:
            raise FileNotFoundError(f"report: the run used body model {spec!r}, which cannot be loaded here ({exc}); "
                                    "pass --body with its files, or --sequences 0 for a report without animations") from exc
    return cache[spec]


def cell_text(cell: dict) -> str:
    from benchmark.run.writers import cell_label

    return cell_label(cell, list(cell))
