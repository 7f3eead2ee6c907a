"""The local backend with worker processes (``run --jobs N``): one process per job, each with one
torch thread, the executor shipped once to each through a private temporary file; a dead worker
fails its unit and is replaced; Ctrl-C / SIGTERM stop them and remove the file."""

from __future__ import annotations

import logging
import os
import pickle
import re
import shutil
import signal
import socket
import sys
import tempfile
import time
import traceback
from collections import deque
from contextlib import contextmanager
from typing import Callable, Sequence

from benchmark.run.backends.common import (WorkerDied, affinity_key, dumps_executor, execute_unit, longest_first,
                                           pick_next, reply_to_outcome, set_threads, worker_where)

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# Worker processes on this machine (--jobs N)
# --------------------------------------------------------------------------------------------

def default_jobs(device: str = "cpu") -> int:
    """``--jobs`` default: the CPU cores this process may use; 1 on CUDA (one device)."""
    if str(device).startswith("cuda"):
        return 1
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _die_with_driver(driver_pid: int) -> None:
    """Linux: ask the kernel to send this worker SIGTERM when the driver process ends, however it
    ends (even SIGKILL), so that no worker outlives it; exit now if it has already gone."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM))  # 1: PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
    if os.getppid() != driver_pid:
        os._exit(0)


def _process_worker(conn, payload_path: str, threads: int, driver_pid: int | None = None) -> None:
    """Worker process main: load the executor once (from the file the driver wrote), say
    ``ready``, then run the units the driver sends one at a time until it sends ``None``.

    Signals: Ctrl-C reaches every process of the terminal's group; a worker ignores it (the driver
    stops the workers). The driver starts workers with SIGINT blocked, so that none can arrive
    before this point. SIGTERM has its default action (also under the ``fork`` start method, which
    would inherit the driver's handler): the driver's ``terminate()`` ends a worker at once,
    silently. On Linux the kernel sends that SIGTERM too when the driver exits in any way
    (:func:`_die_with_driver`); a driver that is gone otherwise (its end of the pipe closed) ends
    the worker quietly at its next message."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # discards a Ctrl-C pending since the start
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    if driver_pid is not None:
        _die_with_driver(driver_pid)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)
    try:
        try:
            set_threads(threads)
            with open(payload_path, "rb") as fh:
                execute = pickle.load(fh)  # the harness's own file, in a folder only this user can read
        except BaseException:
            conn.send(("init-error", traceback.format_exc(), worker_where()))
            return
        conn.send(("ready",))
        while True:
            try:
                unit = conn.recv()
            except (EOFError, OSError):
                return
            if unit is None:
                return
            reply = execute_unit(execute, unit)
            try:
                conn.send(reply)
            except (BrokenPipeError, ConnectionResetError):
                raise
            except Exception as exc:  # a result that cannot be pickled back
                conn.send(("error", type(exc).__name__, f"the unit's result could not be sent back: {exc}",
                           traceback.format_exc(), worker_where()))
    except (BrokenPipeError, ConnectionResetError, EOFError):
        return  # the driver has gone (stopped, interrupted): nobody to answer, nothing to report


EXECUTOR_FOLDER_PREFIX = "benchmark-executor-"


def _host_tag() -> str:
    return re.sub(r"[^A-Za-z0-9.-]+", "_", socket.gethostname())[:64] or "host"


def _executor_folder() -> str:
    """A new folder only this user can open (``mkdtemp``: mode 0700) for the executor's pickle,
    ``$TMPDIR/benchmark-executor-<host>-<pid>-<random>``. The name says which process owns it, so
    that folders left by a driver that was killed outright (SIGKILL, the out-of-memory killer:
    nothing of it runs to remove them) are removed here, by the next run on the same host."""
    _remove_stale_executor_folders()
    return tempfile.mkdtemp(prefix=f"{EXECUTOR_FOLDER_PREFIX}{_host_tag()}-{os.getpid()}-")


def _remove_stale_executor_folders() -> None:
    """Remove this user's executor folders whose driver (this host, that pid) no longer exists."""
    name = re.compile(re.escape(EXECUTOR_FOLDER_PREFIX + _host_tag()) + r"-(\d+)-[^-]+")
    try:
        entries = list(os.scandir(tempfile.gettempdir()))
    except OSError:
        return
    for entry in entries:
        match = name.fullmatch(entry.name)
        if not match or int(match.group(1)) == os.getpid():
            continue
        try:
            if not entry.is_dir(follow_symlinks=False) or entry.stat(follow_symlinks=False).st_uid != os.getuid():
                continue
            os.kill(int(match.group(1)), 0)
        except ProcessLookupError:  # its driver is gone
            shutil.rmtree(entry.path, ignore_errors=True)
            log.info("removed %s, left by a run killed before it could remove it", entry.path)
        except OSError:  # alive (perhaps another user's process), or unreadable: leave it
            continue


def _write_private(path: str, data: bytes) -> None:
    """Write ``data`` to a new file only this user can read (0600)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)


@contextmanager
def sigint_blocked():
    """SIGINT blocked in this thread while it starts a worker process: the worker inherits the
    blocked mask and unblocks SIGINT only once it ignores it (:func:`_process_worker`), so that a
    Ctrl-C at that moment cannot print a KeyboardInterrupt traceback from a half-started worker.
    The driver does not lose the Ctrl-C: another thread takes it, or it waits until the unblock.

    multiprocessing's resource tracker is started first: ``Process.start()`` starts it on first use,
    and its start *unblocks* SIGINT in this thread when done (``ResourceTracker.ensure_running``),
    which left the first worker unprotected (a Ctrl-C then killed it inside ``import site``, with a
    "Fatal Python error" traceback on the terminal)."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


class ProcessBackend:
    """Run units in ``jobs`` worker processes on this machine, ``threads`` torch threads each.

    Workers are started with the ``spawn`` method (no fork of a process that holds torch thread
    pools); the executor is pickled once here, into a temporary folder only this user can read
    (``benchmark-executor-*`` under ``$TMPDIR``), which each worker loads once; the folder is removed
    when the call returns, however it returns. A worker runs one unit at a time, so a worker that
    dies fails exactly the unit it was running; it is replaced and the other units go on. A worker
    that cannot start (or cannot load the executor) stops the run with its error.

    Stopping: an exception in this process (Ctrl-C's KeyboardInterrupt, SIGTERM's
    :class:`benchmark.core.interrupts.Terminated`, an error) stops every worker before it propagates;
    the units already handed to ``on_done`` are stored, the ones running are lost. Workers ignore
    Ctrl-C, and on Linux they die with the driver even when it is killed outright.
    """

    def __init__(self, jobs: int, threads: int = 1, start_method: str = "spawn"):
        if not isinstance(jobs, int) or isinstance(jobs, bool) or jobs < 1:
            raise ValueError(f"--jobs must be a positive integer, got {jobs!r}")
        if not isinstance(threads, int) or threads < 1:
            raise ValueError(f"threads per job must be a positive integer, got {threads!r}")
        self.jobs = jobs
        self.threads = threads
        self.start_method = start_method

    def __repr__(self) -> str:
        return f"ProcessBackend(jobs={self.jobs}, threads={self.threads})"

    def __call__(self, units: Sequence, execute: Callable, on_done: Callable) -> None:
        if not units:
            return
        import multiprocessing as mp
        from multiprocessing.connection import wait

        queue = deque(longest_first(units, execute))
        payload = dumps_executor(execute)
        ctx = mp.get_context(self.start_method)
        # a private folder (mode 0700, mkdtemp's) for the pickle the workers load: removed in the
        # finally below, on success, on errors and on Ctrl-C / SIGTERM alike
        folder = _executor_folder()
        payload_path = os.path.join(folder, "executor.pkl")
        workers: list[dict] = []  # {"proc", "conn", "unit", "ready", "keys"}
        claimed: set = set()  # affinity keys of the units any worker has started

        def start() -> None:
            parent, child = ctx.Pipe(duplex=True)
            driver = os.getpid() if self.start_method in ("spawn", "fork") else None  # the worker's parent
            proc = ctx.Process(target=_process_worker, args=(child, payload_path, self.threads, driver),
                               name="benchmark-unit-worker", daemon=True)
            with sigint_blocked():
                proc.start()
            child.close()
            workers.append({"proc": proc, "conn": parent, "unit": None, "ready": False, "keys": set()})

        def retire(w: dict) -> None:
            workers.remove(w)
            try:
                w["conn"].close()
            except OSError:
                pass
            w["proc"].join(timeout=5)

        def feed(w: dict) -> None:
            """Give a ready worker the next unit, or let it go when there is none."""
            if not queue:
                try:
                    w["conn"].send(None)
                except OSError:
                    pass
                retire(w)
                return
            w["unit"] = pick_next(queue, w["keys"], claimed)
            key = affinity_key(w["unit"])
            w["keys"].add(key)
            claimed.add(key)
            try:
                w["conn"].send(w["unit"])
            except OSError:  # it is gone: the unit goes to a fresh worker
                queue.appendleft(w["unit"])
                w["unit"] = None
                retire(w)
                start()

        try:
            _write_private(payload_path, payload)
            del payload
            for _ in range(min(self.jobs, len(queue))):
                start()
            while workers:
                by_handle = {}
                for w in workers:
                    by_handle[w["conn"]] = w
                    by_handle[w["proc"].sentinel] = w
                for handle in wait(list(by_handle)):
                    w = by_handle[handle]
                    if w not in workers:
                        continue  # handled through its other handle
                    reply, eof = None, False
                    try:
                        if w["conn"].poll():
                            reply = w["conn"].recv()
                    except (EOFError, OSError):
                        eof = True
                    if reply is None:
                        if not eof and w["proc"].is_alive():
                            continue  # woken without a message: look again
                        w["proc"].join(timeout=5)
                        code = w["proc"].exitcode
                        unit = w["unit"]
                        retire(w)
                        if not w["ready"]:
                            raise RuntimeError(f"a worker process exited while starting (exit code {code}), before "
                                               f"it could run a unit; its error is above. Run with --jobs 1 to run "
                                               f"in this process")
                        if unit is not None:
                            signal_note = f", killed by signal {-code}" if isinstance(code, int) and code < 0 else ""
                            on_done(unit, None, WorkerDied(
                                f"the worker process running {unit.unit_id} died (exit code {code}{signal_note}) "
                                f"without a result: out of memory, or a crash in native code? Rerun to retry it"))
                        if queue:
                            start()
                        continue
                    if reply[0] == "init-error":
                        raise RuntimeError(f"a worker process could not load the unit executor (on {reply[2]}); "
                                           f"nothing was run there:\n{reply[1]}")
                    if reply[0] == "ready":
                        w["ready"] = True
                    else:
                        unit, w["unit"] = w["unit"], None
                        result, error = reply_to_outcome(reply)
                        on_done(unit, result, error)
                    feed(w)
        finally:
            # the loop ends with no worker left, unless it was cut short (an error, Ctrl-C, SIGTERM):
            # then the idle workers are let go, the busy or starting ones stopped now (SIGTERM; they
            # die silently), the executor's folder removed, and only then is any worker waited for
            for w in workers:
                try:
                    if w["unit"] is None and w["ready"]:
                        w["conn"].send(None)
                        continue
                except OSError:
                    pass
                w["proc"].terminate()
            shutil.rmtree(folder, ignore_errors=True)
            deadline = time.monotonic() + 2
            for w in workers:
                w["proc"].join(timeout=max(0.0, deadline - time.monotonic()))
                if w["proc"].is_alive():
                    w["proc"].terminate()
                    w["proc"].join(timeout=5)
                try:
                    w["conn"].close()
                except OSError:
                    pass
