"""What the backends share: the order units are submitted in (longest first, cell affinity),
the errors that come back from workers, running one unit on a worker, the thread count, and
the serial backend (``--jobs 1``)."""

from __future__ import annotations

import os
import pickle
import socket
import traceback
from collections import deque
from typing import Sequence

from benchmark.core.work_units import estimate_cost
from benchmark.core.memory import release_free_memory


# --------------------------------------------------------------------------------------------
# Ordering
# --------------------------------------------------------------------------------------------

def longest_first(units: Sequence, execute=None) -> list:
    """``units`` sorted by decreasing cost (``execute.unit_cost(unit)`` when the executor has it,
    else :func:`benchmark.core.work_units.estimate_cost`); ties keep the plan order, so units of one cell stay together."""
    cost_of = getattr(execute, "unit_cost", None) or estimate_cost
    costs = [float(cost_of(u)) for u in units]
    order = sorted(range(len(units)), key=lambda i: (-costs[i], i))
    return [units[i] for i in order]


def affinity_key(unit) -> tuple:
    """What a worker process caches between units (:func:`~benchmark.protocols.start_search.prior_free_start`
    keeps the prior-free start per observation): units with the same key share the cache. The key is
    the unit's cell and sequences (every prior of a table cell sees the same observation)."""
    cell = getattr(unit, "cell", None) or {}
    return (tuple(sorted((str(k), repr(v)) for k, v in cell.items())), tuple(getattr(unit, "sequence_ids", ()) or ()))


def pick_next(queue: deque, mine: set, claimed: set):
    """Remove and return the unit a free worker runs next: the first queued unit of a cell that
    worker has run before (its caches are warm), else of a cell no worker has started, else the
    first queued unit. ``mine``: the worker's affinity keys; ``claimed``: every worker's. The queue
    stays longest-first within each choice, so a worker keeps to its cells and only takes another
    worker's cell when none of its own or unstarted ones are left (no idle worker at the end)."""
    first_free = None
    for i, unit in enumerate(queue):
        key = affinity_key(unit)
        if key in mine:
            break
        if first_free is None and key not in claimed:
            first_free = i
    else:
        i = first_free if first_free is not None else 0
    unit = queue[i]
    del queue[i]
    return unit


# --------------------------------------------------------------------------------------------
# Errors that come back from workers
# --------------------------------------------------------------------------------------------

class UnitError(RuntimeError):
    """A unit raised on a worker. ``str()`` names the original exception type, its message, the
    worker (host and process id) and the worker's traceback."""

    def __init__(self, type_name: str, message: str, remote_traceback: str, where: str):
        self.type_name = type_name
        self.message = message
        self.remote_traceback = remote_traceback
        self.where = where
        super().__init__(f"{type_name}: {message} (on worker {where})\n--- worker traceback ---\n"
                         f"{remote_traceback.rstrip()}")


class WorkerDied(RuntimeError):
    """The worker process running a unit died without an answer (killed for memory, or a crash in
    native code)."""


def worker_where() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def execute_unit(execute, unit) -> tuple:
    """Run one unit on a worker; exceptions become a picklable error reply (with the traceback)."""
    try:
        return ("ok", execute(unit))
    except Exception as exc:  # one failing unit must not take the worker (or the run) down
        return ("error", type(exc).__name__, str(exc), traceback.format_exc(), worker_where())
    finally:  # the unit's fit freed its arrays: hand the pages back before the next unit (benchmark.core.memory)
        release_free_memory()


def reply_to_outcome(reply) -> tuple[dict | None, BaseException | None]:
    if reply[0] == "ok":
        return reply[1], None
    _, type_name, message, tb, where = reply
    return None, UnitError(type_name, message, tb, where)


def dumps_executor(execute) -> bytes:
    try:
        return pickle.dumps(execute, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:
        raise ValueError(f"the unit executor ({type(execute).__qualname__}) cannot be pickled, so it cannot be shipped "
                         f"to worker processes: {type(exc).__name__}: {exc}. Run with --jobs 1 (in this process), or "
                         f"make it picklable (no lambdas, open files or locks; see "
                         f"benchmark.run.table_run.TableExecutor)") from exc


def set_threads(threads: int) -> None:
    import torch

    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)


def interrupt_behind(exc: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt (Ctrl-C, or SIGTERM's :class:`~benchmark.core.interrupts.Terminated`)
    that ``exc`` was raised from, if any: a signal handler's exception raised while numba's compiled
    code runs comes out as ``SystemError: CPUDispatcher(...) returned a result with an exception
    set``, its cause the interrupt, and must stop the run rather than fail one unit."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def serial_backend(units: Sequence, execute, on_done) -> None:
    """Run units in this process, one after another (``--jobs 1``), each with one torch thread as
    in a worker process, so that ``--jobs 1``, ``--jobs N`` and Ray store the same bits. The
    caller's thread count is restored afterwards."""
    import torch

    before = torch.get_num_threads()
    try:
        set_threads(1)
        for unit in units:
            try:
                result = execute(unit)
            except Exception as exc:  # one failing unit must not take the others down
                stop = interrupt_behind(exc)
                if stop is not None:  # Ctrl-C or SIGTERM inside compiled code: numba wraps it in a SystemError
                    raise stop from None
                on_done(unit, None, exc)
            else:
                on_done(unit, result, None)
    finally:
        set_threads(before)
