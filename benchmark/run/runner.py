"""Run work units: resume from stored results, execute the rest on a backend, store each result.

:func:`run_units` owns the results store (``<out_dir>/units/<unit_id>.json``, one atomic JSON
per unit) and the resume policy; a *backend* only executes units and hands each outcome back, so a
crash or a preempted node loses one unit, not the table.

Resume policies:

- ``"only-missing"`` (default): a unit whose file exists with the same spec hash, is a valid result
  and matches its own ``checksum`` (:func:`benchmark.core.work_units.unit_checksum`, written with it) is done
  and reused. A file with another spec hash (the rules, profile sizes, the prior's weights -- by
  content hash --, the sequences, the motion data they hold -- by content hash --, or the seed
  changed), an invalid one, or one whose contents no longer match its checksum (edited by hand,
  damaged) is moved aside to ``units/stale/<unit_id>.<old_hash[:8]>.json`` and the unit is rerun.
- ``"never"``: every unit is rerun; existing files are moved aside the same way first.

Under ``"only-missing"``, a stored unit made under a smaller step cap whose every fit converged before
it is carried over instead of rerun, where the table's protocol allows it (``carry``;
:mod:`benchmark.run.cap_carry`): the same computation under any larger cap.

Before any unit runs, :func:`run_units` prints one line saying how many units it reuses, computes
and moved aside (and why); the counts are in the :class:`RunReport` (the table run stores them in
its provenance).

Nothing is ever deleted: a stale name that is taken gets a ``.1``, ``.2``... suffix.

Backends: ``"local"`` runs the units one after another in this process; ``"ray"`` runs each unit
as a Ray task (:mod:`benchmark.run.backends`, which also has the multi-process local backend behind
``--jobs N``). A backend is a callable ``backend(units, execute, on_done)`` that calls
``on_done(unit, result, error)`` once per unit, in this process, as each unit finishes
(``result`` the executor's dict, or ``error`` the exception it raised); see :data:`BACKENDS`.
Results are stored and resumed the same way whatever the backend.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

from benchmark.run.backends import BACKENDS, Backend
from benchmark.run.cap_carry import carry_problem, carry_unit
from benchmark.data.unit_arrays import ARRAYS_KEY, arrays_path, write_arrays
from benchmark.core.json_io import atomic_write_json
from benchmark.core.outdir import check_units_folder
from benchmark.core.work_units import WorkUnit, checksum_problem, unit_path, validate_unit_result, with_checksum

__all__ = ["RESUME_POLICIES", "RunReport", "progress_enabled", "run_units"]

log = logging.getLogger(__name__)

RESUME_POLICIES = ("only-missing", "never")

Executor = Callable[[WorkUnit], dict]
OnDone = Callable[[WorkUnit, "dict | None", "BaseException | None"], None]


@dataclass
class RunReport:
    """What :func:`run_units` did.

    results: unit_id -> result dict, for every unit that is done (reused or run), in plan order.
    reused / ran: unit ids reused from disk / executed now (and stored).
    carried: unit ids made under a smaller step cap and carried over (:mod:`benchmark.run.cap_carry`;
        also in ``reused``).
    failed: unit_id -> "ExceptionType: message" for units that raised or returned an invalid
        result; nothing was stored for them.
    moved: paths of stale files moved aside under ``units/stale/``.
    """

    results: dict[str, dict] = field(default_factory=dict)
    reused: list[str] = field(default_factory=list)
    carried: list[str] = field(default_factory=list)
    restored: list[str] = field(default_factory=list)  # unit ids taken back from units/stale/ (also in reused)
    ran: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    errors: dict[str, BaseException] = field(default_factory=dict)  # unit_id -> the exception (its traceback)
    moved: list[Path] = field(default_factory=list)
    moved_why: dict[str, str] = field(default_factory=dict)
    wall_s: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.failed

    def __iter__(self):
        """Unpacks as ``results, failures = run_units(...)``: the done results (a list, plan
        order, ready for ``derive_table``) and the failures (unit_id -> message)."""
        return iter((list(self.results.values()), dict(self.failed)))

    def resume_counts(self) -> dict:
        """What happened to stored unit files: for the table's provenance."""
        reasons: dict[str, int] = {}
        for why in self.moved_why.values():
            key = why.split(" (", 1)[0]
            reasons[key] = reasons.get(key, 0) + 1
        return {"reused": len(self.reused), "carried": len(self.carried), "restored": len(self.restored), "recomputed": len(self.ran) + len(self.failed), "ran": len(self.ran),
                "failed": len(self.failed), "moved_aside": len(self.moved), "moved_aside_reasons": reasons}

    def summary(self) -> str:
        text = (f"{len(self.ran)} unit(s) run, {len(self.reused)} reused, {len(self.failed)} failed, "
                f"{len(self.moved)} stale file(s) moved aside, {self.wall_s:.1f} s")
        if self.failed:
            text += "\nfailed units:\n" + "\n".join(f"  {uid}: {msg}" for uid, msg in self.failed.items())
        return text


def clock(seconds: float) -> str:
    """``1 h 02 min``, ``3 min 05 s`` or ``42 s``: a run's elapsed wall time as its lines print it."""
    s = int(round(seconds))
    if s >= 3600:
        return f"{s // 3600} h {s % 3600 // 60:02d} min"
    return f"{s // 60} min {s % 60:02d} s" if s >= 60 else f"{s} s"


def progress_enabled(progress: bool | None) -> bool:
    """Progress bars: ``None`` means on only when stdout is a terminal."""
    if progress is None:
        try:
            return sys.stdout.isatty()
        except (AttributeError, ValueError):
            return False
    return bool(progress)


def move_aside(path: Path, unit_id: str, old_hash: str | None, arrays: bool = True) -> Path:
    """Move a stored result out of the way into ``units/stale/`` without overwriting anything; with
    ``arrays``, its ``.npz`` (the fitted motions) goes with it, to the same name (``.npz``)."""
    stale = path.parent / "stale"
    stale.mkdir(parents=True, exist_ok=True)
    tag = old_hash[:8] if old_hash else "unreadable"
    target = stale / f"{unit_id}.{tag}.json"
    n = 0
    while target.exists():
        n += 1
        target = stale / f"{unit_id}.{tag}.{n}.json"
    os.replace(path, target)
    npz = path.with_suffix(".npz")
    if arrays and npz.exists():
        os.replace(npz, target.with_suffix(".npz"))
    return target


def _stale_names(path: Path) -> list[str]:
    try:
        return os.listdir(path.parent / "stale")
    except OSError:
        return []


SPEC_DIFFERS = "spec hash differs"
OTHER_DEVICE = "made on another device"


def _device_problem(stored, unit: WorkUnit) -> str | None:
    """Why a stored unit cannot stand in this run's table for its device: the device is not in the
    spec hash (a run on a CPU and one on a GPU plan the same units), but a fit on a GPU is not the
    CPU's to the bit, so a table made on one device reports no unit made on another (cpu vs cuda;
    cuda:0 vs cuda:1 is the same kind). None for an n/a unit (no fit) or a record without a device."""
    made = stored.get("device") if isinstance(stored, dict) else None
    if not isinstance(made, str) or made == "none" or stored.get("na_reason") is not None:
        return None
    if made.split(":", 1)[0] != str(unit.device).split(":", 1)[0]:
        return f"{OTHER_DEVICE} (made on {made}, this run is on {unit.device})"
    return None
MOVED = "moved"  # _carry's answer when it moved the stored file aside and then failed


def _read_stored(path: Path, unit: WorkUnit) -> tuple[dict | None, str | None, str | None, dict | None]:
    """(valid result or None, the stored spec hash or None, why it is not reusable, the stored
    record as read where it was readable)."""
    try:
        stored = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        return None, None, f"unreadable ({exc})", None
    old_hash = stored.get("spec_hash") if isinstance(stored, dict) else None
    if not isinstance(old_hash, str):
        old_hash = None
    if old_hash != unit.spec_hash:
        return None, old_hash, f"{SPEC_DIFFERS} (its inputs, rules, sizes, weights, seed or torch threads changed)", stored
    try:
        validate_unit_result(stored, unit, source=str(path))
    except ValueError as exc:
        return None, old_hash, f"invalid ({exc})", stored
    problem = checksum_problem(stored)
    if problem:
        return None, old_hash, f"checksum mismatch ({problem})", stored
    other = _device_problem(stored, unit)
    if other:
        return None, old_hash, other, stored
    return stored, old_hash, None, stored


def _restore(path: Path, unit: WorkUnit, report: "RunReport") -> dict | None:
    """The unit's own result, taken back from ``units/stale/`` where an earlier run moved it aside
    (a rerun under other settings into the folder, since stopped or finished): the file named for
    its unit id and spec hash that is valid for it, checksum and device included. The unit's file
    in its place, if any, must have been moved aside already. None when there is none."""
    stale = path.parent / "stale"
    stem = f"{unit.unit_id}.{unit.spec_hash[:8]}"
    try:
        names = sorted(n for n in os.listdir(stale) if n == f"{stem}.json" or
                       (n.startswith(f"{stem}.") and n.endswith(".json") and n[len(stem) + 1:-5].isdigit()))
    except OSError:
        return None
    for name in names:
        candidate = stale / name
        stored, _, why, _ = _read_stored(candidate, unit)
        if stored is None:
            continue
        os.replace(candidate, path)
        if candidate.with_suffix(".npz").exists():
            os.replace(candidate.with_suffix(".npz"), path.with_suffix(".npz"))
        report.restored.append(unit.unit_id)
        log.info("%s: its result under these settings was in %s (moved aside by a run under other settings); "
                 "taken back", unit.unit_id, candidate)
        return stored
    return None


def _carry(path: Path, unit: WorkUnit, raw: dict | None, old_hash: str | None, carry, out_dir,
           report: "RunReport") -> tuple[dict | None, str | None]:
    """The stored ``raw`` carried over to ``unit`` (moved aside, rewritten, stored), or None and why
    not (:mod:`benchmark.run.cap_carry`)."""
    if carry is None or not isinstance(raw, dict):
        return None, None
    problem = carry_problem(raw, unit, carry(unit)) or _device_problem(raw, unit)
    if problem is not None:
        return None, problem
    target = move_aside(path, unit.unit_id, old_hash, arrays=False)  # carry_unit copies the .npz there
    report.moved.append(target)
    try:
        record = carry_unit(raw, unit, out_dir, target)
        validate_unit_result(record, unit, source=str(path))
        atomic_write_json(path, record)
    except (ValueError, OSError) as exc:  # the original is safe in units/stale/: the unit is computed again
        npz, kept = path.with_suffix(".npz"), target.with_suffix(".npz")
        if npz.exists() and not kept.exists():
            try:
                os.replace(npz, kept)
            except OSError:
                pass
        report.moved_why[unit.unit_id] = f"spec hash differs; carrying it to the new cap failed ({exc})"
        log.warning("%s: carrying it to the new cap failed (%s); the original is in %s, rerunning", unit.unit_id, exc,
                    target)
        return None, MOVED
    report.moved_why[unit.unit_id] = "carried to a raised step cap"
    report.carried.append(unit.unit_id)
    log.info("%s: made under a cap of %s steps, every fit converged: carried to %s steps (the original in %s)",
             unit.unit_id, record["carried"]["from_steps"], record["carried"]["to_steps"], target)
    return record, None


def run_units(
    units: Sequence[WorkUnit],
    execute: Executor,
    out_dir: str | os.PathLike,
    resume: str = "only-missing",
    backend: str | Backend = "local",
    progress: bool | None = None,
    announce: bool = True,
    carry: Callable[[WorkUnit], "str | None"] | None = None,
) -> RunReport:
    """Run ``units`` with ``execute``, storing each result as ``<out_dir>/units/<unit_id>.json``.

    execute: ``execute(unit) -> unit-result dict`` (see :mod:`benchmark.core.work_units`); its result is
        validated against the unit (id, spec hash, sequences, finite sums) before it is stored.
    resume: ``"only-missing"`` or ``"never"`` (see the module docstring).
    backend: a name in :data:`BACKENDS`, or a backend callable (``benchmark.run.backends.make_backend``).
    progress: tqdm bar; ``None``: only when stdout is a terminal.
    announce: print the resume line (reused / to compute / moved aside) before running.
    carry: ``carry(unit)``: None where the unit's rules make a converged fit independent of the step
        cap, else why not (the table protocol's :meth:`~benchmark.protocols.base.Protocol.carry_problem`).
        Given, a stored unit that differs only by a smaller cap and whose every fit converged is
        carried over (:mod:`benchmark.run.cap_carry`) instead of rerun. None: never.

    A unit that raises is logged with its id and the traceback, nothing is stored for it, the
    others go on; the returned :class:`RunReport` lists it under ``failed`` (callers should exit
    non-zero when ``not report.ok``).
    """
    if resume not in RESUME_POLICIES:
        raise ValueError(f"unknown resume policy {resume!r}; choose one of {', '.join(RESUME_POLICIES)}")
    if not callable(backend) and backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; available: {', '.join(sorted(BACKENDS))}")
    run_backend = backend if callable(backend) else BACKENDS[backend]
    ids = [u.unit_id for u in units]
    if len(set(ids)) != len(ids):
        raise ValueError(f"run_units: unit ids repeat: {sorted({i for i in ids if ids.count(i) > 1})[:5]}")

    check_units_folder(out_dir)  # a units/ that is a file would fail every unit after computing it

    t0 = time.perf_counter()
    report = RunReport()
    done: dict[str, dict] = {}
    todo: list[WorkUnit] = []

    def restored(unit: WorkUnit, path: Path) -> bool:
        record = _restore(path, unit, report) if resume == "only-missing" else None
        if record is not None:
            done[unit.unit_id] = record
            report.reused.append(unit.unit_id)
        return record is not None

    for unit in units:
        path = unit_path(out_dir, unit.unit_id)
        if not path.exists():
            if not restored(unit, path):
                todo.append(unit)
            continue
        stored, old_hash, why, raw = _read_stored(path, unit)
        if resume == "only-missing" and stored is not None:
            done[unit.unit_id] = stored
            report.reused.append(unit.unit_id)
            continue
        not_carried = None
        # its own result in units/stale/ is taken back below, rather than another carried over
        own_in_stale = any(n.startswith(f"{unit.unit_id}.{unit.spec_hash[:8]}.") for n in _stale_names(path))
        if resume == "only-missing" and why is not None and why.startswith(SPEC_DIFFERS) and not own_in_stale:
            carried, not_carried = _carry(path, unit, raw, old_hash, carry, out_dir, report)
            if carried is not None:
                done[unit.unit_id] = carried
                report.reused.append(unit.unit_id)
                continue
            if not_carried == MOVED:
                if not restored(unit, path):
                    todo.append(unit)
                continue
        target = move_aside(path, unit.unit_id, old_hash)
        report.moved.append(target)
        reason = "resume policy 'never'" if why is None else why
        if not_carried:
            reason = f"{reason}; not carried to the new cap: {not_carried}"
        report.moved_why[unit.unit_id] = reason
        log.log(logging.WARNING if why and why.startswith(("checksum", "invalid", "unreadable", OTHER_DEVICE)) else logging.INFO,
                "%s: stored result not reused (%s); moved to %s", unit.unit_id, reason, target)
        if not restored(unit, path):
            todo.append(unit)
    if announce:
        counts = report.resume_counts()["moved_aside_reasons"]
        why = f" ({', '.join(f'{n} {k}' for k, n in counts.items())})" if counts else ""
        kinds = [f"{len(report.carried)} carried to a raised step cap"] if report.carried else []
        kinds += [f"{len(report.restored)} taken back from units/stale/"] if report.restored else []
        carried = f" (of them {', '.join(kinds)})" if kinds else ""
        print(f"work units in {Path(out_dir) / 'units'}: {len(report.reused)} reused{carried}, {len(todo)} to compute, "
              f"{len(report.moved)} stored file(s) moved aside to units/stale/{why}", flush=True)

    from tqdm import tqdm

    bar = tqdm(total=len(units), initial=len(report.reused), unit="unit", desc="work units",
               disable=not progress_enabled(progress), dynamic_ncols=True)
    lines = announce and bar.disable  # no bar (a log file, a batch job): one line per finished unit instead

    def on_done(unit: WorkUnit, result: dict | None, error: BaseException | None) -> None:
        try:
            if error is None:
                try:
                    record = dict(result) if isinstance(result, dict) else result
                    arrays = record.pop(ARRAYS_KEY, None) if isinstance(record, dict) else None
                    validate_unit_result(record, unit, source=f"executor result for {unit.unit_id}")
                    record["spec"] = unit.spec
                    record = with_checksum(record)
                    if arrays:  # the fitted motion, for the report: written before the JSON that marks the unit done
                        write_arrays(arrays_path(out_dir, unit.unit_id), arrays)
                    atomic_write_json(unit_path(out_dir, unit.unit_id), record)
                except (ValueError, TypeError, OSError) as exc:
                    error = exc
            if error is not None:
                report.failed[unit.unit_id] = f"{type(error).__name__}: {error}"
                report.errors[unit.unit_id] = error
                # one line; the traceback with --debug (or -v), which set this logger to DEBUG
                trace = log.isEnabledFor(logging.DEBUG)
                log.error("unit %s failed: %s: %s%s", unit.unit_id, type(error).__name__, error,
                          "" if trace else " (--debug shows its traceback)", exc_info=error if trace else None)
            else:
                done[unit.unit_id] = record
                report.ran.append(unit.unit_id)
                if lines:
                    print(f"unit {len(report.ran) + len(report.failed)} of {len(todo)} done: {unit.unit_id} stored "
                          f"({clock(time.perf_counter() - t0)} into the run)", flush=True)
        finally:
            bar.update(1)

    try:
        run_backend(todo, execute, on_done)
    except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: what finished is stored; say so, and how to go on
        from benchmark.core.interrupts import add_stop_note

        # counted on disk: the signal may land between a unit's file and its bookkeeping
        stored = sum(unit_path(out_dir, unit.unit_id).exists() for unit in units)
        add_stop_note(exc, f"{stored} of {len(units)} work unit(s) stored in "
                           f"{Path(out_dir) / 'units'}; the same command resumes from them")
        raise
    finally:
        bar.close()
    report.results = {uid: done[uid] for uid in ids if uid in done}
    report.wall_s = time.perf_counter() - t0
    if report.failed:
        log.error("%d of %d unit(s) failed: %s", len(report.failed), len(units), ", ".join(report.failed))
    return report
