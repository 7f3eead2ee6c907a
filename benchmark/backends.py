"""Execution backends that run work units in parallel: worker processes on this machine
(``run --jobs N``) and Ray (``run --backend ray``), on one machine or a cluster.

Both fit the runner's seam ``backend(units, execute, on_done)`` (:mod:`benchmark.runner`): the
driver (this process) keeps the results store, the resume rules, the progress bar and the table;
a backend only executes units elsewhere and hands each outcome back through ``on_done`` as it
arrives. So a parallel run writes the same unit files as a serial one, and a run interrupted on
one backend resumes on another.

Nothing but the backend may change a number, and it does not:

- the executor (:class:`benchmark.protocols.table_run.TableExecutor`: the built adapters with
  their weights, the body, the test motions) is pickled once on the driver and shipped once to
  each worker process (``--jobs``) or put once in Ray's object store (each Ray worker process
  fetches it once and keeps it), never per unit;
- every unit's randomness comes from its own seed, never from the order units run in, and each
  worker runs units with a fixed number of torch threads (one by default), so a unit's result is
  the same on any worker, in any order; the tests check bit-identity against the serial run.

Units are submitted longest-first (:func:`longest_first`), so the slowest units do not start last
and leave the other workers idle at the end. The local process backend keeps a worker on the cells
it has started (:func:`pick_next`): the prior-free start of a table1 cell is cached per worker
process, so two workers on one cell would each compute it.

A unit that raises on a worker comes back as a :class:`UnitError` carrying the worker's traceback;
the other units go on. A worker process that dies (out of memory, a crash in native code) fails
the unit it was running and is replaced. Ctrl-C or SIGTERM to the driver (:mod:`benchmark.interrupts`)
stops the workers, local or Ray, and leaves no temporary file behind.
"""

from __future__ import annotations

import hashlib
import logging
import os
import pickle
import re
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
import traceback
import uuid
from collections import deque
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Sequence

from benchmark.work_units import estimate_cost

log = logging.getLogger(__name__)

__all__ = ["ProcessBackend", "RayBackend", "UnitError", "WorkerDied", "code_fingerprint", "default_jobs",
           "longest_first", "make_backend", "serial_backend", "BACKENDS"]


# --------------------------------------------------------------------------------------------
# Ordering
# --------------------------------------------------------------------------------------------

def longest_first(units: Sequence, execute=None) -> list:
    """``units`` sorted by decreasing cost (``execute.unit_cost(unit)`` when the executor has it,
    else :func:`benchmark.work_units.estimate_cost`); ties keep the plan order, so units of one cell stay together."""
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


def _where() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _execute_unit(execute, unit) -> tuple:
    """Run one unit on a worker; exceptions become a picklable error reply (with the traceback)."""
    try:
        return ("ok", execute(unit))
    except Exception as exc:  # one failing unit must not take the worker (or the run) down
        return ("error", type(exc).__name__, str(exc), traceback.format_exc(), _where())


def _reply_to_outcome(reply) -> tuple[dict | None, BaseException | None]:
    if reply[0] == "ok":
        return reply[1], None
    _, type_name, message, tb, where = reply
    return None, UnitError(type_name, message, tb, where)


def _dumps_executor(execute) -> bytes:
    try:
        return pickle.dumps(execute, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:
        raise ValueError(f"the unit executor ({type(execute).__qualname__}) cannot be pickled, so it cannot be shipped "
                         f"to worker processes: {type(exc).__name__}: {exc}. Run with --jobs 1 (in this process), or "
                         f"make it picklable (no lambdas, open files or locks; see "
                         f"benchmark.protocols.table_run.TableExecutor)") from exc


def _set_threads(threads: int) -> None:
    import torch

    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)


def serial_backend(units: Sequence, execute, on_done) -> None:
    """Run units in this process, one after another (``--jobs 1``), each with one torch thread as
    in a worker process, so that ``--jobs 1``, ``--jobs N`` and Ray store the same bits. The
    caller's thread count is restored afterwards."""
    import torch

    before = torch.get_num_threads()
    try:
        _set_threads(1)
        for unit in units:
            try:
                result = execute(unit)
            except Exception as exc:  # one failing unit must not take the others down
                on_done(unit, None, exc)
            else:
                on_done(unit, result, None)
    finally:
        _set_threads(before)


def _ray_backend(units: Sequence, execute, on_done) -> None:
    """Each unit a Ray task, default options (:class:`RayBackend`; Ray is imported only when it
    runs, so that the harness does not need it installed)."""
    RayBackend()(units, execute, on_done)


Backend = Callable[[Sequence, Callable, Callable], None]

# name -> backend callable with default options (``backend(units, execute, on_done)``);
# :func:`make_backend` builds one with options (--jobs, --ray-address...), and
# ``benchmark.runner.run_units`` takes such a callable too. Add one with ``BACKENDS[name] = fn``.
BACKENDS: dict = {"local": serial_backend, "ray": _ray_backend}


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
            _set_threads(threads)
            with open(payload_path, "rb") as fh:
                execute = pickle.load(fh)  # the harness's own file, in a folder only this user can read
        except BaseException:
            conn.send(("init-error", traceback.format_exc(), _where()))
            return
        conn.send(("ready",))
        while True:
            try:
                unit = conn.recv()
            except (EOFError, OSError):
                return
            if unit is None:
                return
            reply = _execute_unit(execute, unit)
            try:
                conn.send(reply)
            except (BrokenPipeError, ConnectionResetError):
                raise
            except Exception as exc:  # a result that cannot be pickled back
                conn.send(("error", type(exc).__name__, f"the unit's result could not be sent back: {exc}",
                           traceback.format_exc(), _where()))
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
def _sigint_blocked():
    """SIGINT blocked in this thread while it starts a worker process: the worker inherits the
    blocked mask and unblocks SIGINT only once it ignores it (:func:`_process_worker`), so that a
    Ctrl-C at that moment cannot print a KeyboardInterrupt traceback from a half-started worker.
    The driver does not lose the Ctrl-C: another thread takes it, or it waits until the unblock."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
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
    :class:`benchmark.interrupts.Terminated`, an error) stops every worker before it propagates;
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
        payload = _dumps_executor(execute)
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
            with _sigint_blocked():
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
                        result, error = _reply_to_outcome(reply)
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


# --------------------------------------------------------------------------------------------
# Ray (--backend ray)
# --------------------------------------------------------------------------------------------

# Worker side: the executor of the current run, fetched from the object store once per process.
_WORKER_EXECUTORS: dict = {}
_FINGERPRINT: list = []


def code_fingerprint() -> str:
    """sha256 over the Python sources of the ``benchmark`` and ``priors`` packages (relative path
    and bytes of every ``.py`` file): the driver and every Ray worker must run the same code."""
    if _FINGERPRINT:
        return _FINGERPRINT[0]
    import importlib

    h = hashlib.sha256()
    for name in ("benchmark", "priors"):
        try:
            root = Path(importlib.import_module(name).__file__).parent
        except ImportError:
            h.update(f"{name}: missing\n".encode())
            continue
        for path in sorted(root.rglob("*.py")):
            if "__pycache__" in path.parts:
                continue
            h.update(f"{name}/{path.relative_to(root).as_posix()}\n".encode())
            h.update(path.read_bytes())
    _FINGERPRINT.append(h.hexdigest())
    return _FINGERPRINT[0]


def _ray_task(token: str, boxed_ref: list, unit, threads: int, fingerprint: str | None) -> tuple:
    """One unit on a Ray worker. ``boxed_ref`` holds the executor's object reference inside a list,
    so that Ray does not fetch it for every task; it is fetched on this worker's first unit."""
    try:
        _set_threads(threads)
        if fingerprint is not None and code_fingerprint() != fingerprint:
            import benchmark

            raise RuntimeError(f"this Ray worker runs other benchmark code than the driver (code fingerprint "
                               f"{code_fingerprint()[:12]} here, {fingerprint[:12]} on the driver; package at "
                               f"{Path(benchmark.__file__).parent}): install the same commit of the project on "
                               f"every node (README, 'Scale out')")
    except Exception as exc:
        return ("init-error", f"{type(exc).__name__}: {exc}", _where())
    execute = _WORKER_EXECUTORS.get(token)
    if execute is None:
        try:
            import ray

            execute = ray.get(boxed_ref[0])
        except Exception:  # e.g. a module the executor needs is missing on this worker
            return ("init-error", traceback.format_exc(), _where())
        _WORKER_EXECUTORS.clear()  # keep only the current run's
        _WORKER_EXECUTORS[token] = execute
    return _execute_unit(execute, unit)


@contextmanager
def _keep_sigterm_handler():
    """``ray.init`` replaces the driver's SIGTERM handler (with ``sys.exit``, and, in C, with a crash
    reporter that prints a stack and aborts the process 3 s later). Where the CLI's handler was in
    place (:func:`benchmark.interrupts.sigterm_raises`), it is put back afterwards (which removes
    Ray's C handler too), so that SIGTERM unwinds the run like Ctrl-C: the pending tasks are
    cancelled, the Ray runtime shut down (the ``finally`` of :meth:`RayBackend.__call__`), the
    ``--out`` lock released, exit 143."""
    from benchmark.interrupts import is_terminated_handler

    previous = signal.getsignal(signal.SIGTERM)
    ours = threading.current_thread() is threading.main_thread() and is_terminated_handler(previous)
    try:
        yield
    finally:
        if ours:
            signal.signal(signal.SIGTERM, previous)


def _import_ray():
    try:
        import ray
    except ImportError as exc:
        raise ValueError("--backend ray needs Ray: pip install -e \".[ray]\" (or pip install \"ray>=2.9\")") from exc
    return ray


class RayBackend:
    """Each unit one Ray task asking for ``cpus_per_unit`` CPUs and ``gpus_per_unit`` GPUs.

    address: ``None`` starts a local Ray runtime with this machine's cores (``num_cpus`` to
        override) and stops it at the end; ``"auto"`` joins the cluster running on this machine
        (``ray start``); ``HOST:PORT`` joins that cluster's head. When Ray is already initialised
        in this process (a notebook, the tests) that runtime is used as it is and left running.
    cpus_per_unit: CPUs a unit reserves; it also sets the unit's torch threads (at least 1).
    gpus_per_unit: GPUs a unit reserves (a fraction shares a GPU between units).
    max_retries: Ray's retries of a unit whose worker or node was lost (not of a unit that raised).
    check_code: workers refuse to run when their ``benchmark``/``priors`` sources differ from the
        driver's (:func:`code_fingerprint`), since other code could change a number.
    """

    def __init__(self, address: str | None = None, cpus_per_unit: float = 1, gpus_per_unit: float = 0,
                 num_cpus: int | None = None, max_retries: int = 1, check_code: bool = True):
        if address is not None and not (address == "auto" or re.fullmatch(r"(ray://)?[^\s:]+:\d+", address)):
            raise ValueError(f"--ray-address must be 'auto' or HOST:PORT (the head node's GCS address, default port "
                             f"6379), got {address!r}")
        if not (isinstance(cpus_per_unit, (int, float)) and cpus_per_unit > 0):
            raise ValueError(f"--cpus-per-unit must be a positive number, got {cpus_per_unit!r}")
        if not (isinstance(gpus_per_unit, (int, float)) and gpus_per_unit >= 0):
            raise ValueError(f"--gpus-per-unit must be a number >= 0, got {gpus_per_unit!r}")
        self.address = address
        self.cpus_per_unit = cpus_per_unit
        self.gpus_per_unit = gpus_per_unit
        self.num_cpus = num_cpus
        self.max_retries = max_retries
        self.check_code = check_code

    def __repr__(self) -> str:
        return (f"RayBackend(address={self.address!r}, cpus_per_unit={self.cpus_per_unit}, "
                f"gpus_per_unit={self.gpus_per_unit})")

    @property
    def threads(self) -> int:
        return max(1, int(self.cpus_per_unit))

    def _connect(self, ray) -> bool:
        """Initialise Ray if needed; True when this backend owns the connection (and shuts it down)."""
        if ray.is_initialized():
            return False
        env = {var: str(self.threads) for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
        with _keep_sigterm_handler():
            if self.address is None:
                num_cpus = self.num_cpus or default_jobs("cpu")
                log.info("starting a local Ray runtime with %d CPUs", num_cpus)
                ray.init(num_cpus=num_cpus, include_dashboard=False, runtime_env={"env_vars": env})
            else:
                log.info("joining the Ray cluster at %s", self.address)
                try:
                    ray.init(address=self.address, runtime_env={"env_vars": env})
                except ConnectionError as exc:
                    raise ValueError(f"--ray-address {self.address}: no Ray cluster there ({exc}); start one with "
                                     f"'ray start --head' (README, 'Scale out')") from exc
        return True

    def _check_resources(self, ray) -> None:
        total = ray.cluster_resources()
        for what, need, flag in (("CPU", self.cpus_per_unit, "--cpus-per-unit"), ("GPU", self.gpus_per_unit, "--gpus-per-unit")):
            have = float(total.get(what, 0.0))
            if need and need > have:
                raise ValueError(f"{flag} {need:g}: the Ray cluster has {have:g} {what}(s) in all, so no unit could "
                                 f"ever be scheduled; lower {flag} or add nodes")

    def __call__(self, units: Sequence, execute: Callable, on_done: Callable) -> None:
        if not units:
            return
        ray = _import_ray()
        owned = self._connect(ray)
        pending: dict = {}
        try:
            self._check_resources(ray)
            ordered = longest_first(units, execute)
            try:
                ref = ray.put(execute)  # once: every worker fetches it from the object store
            except Exception as exc:
                raise ValueError(f"the unit executor ({type(execute).__qualname__}) cannot be serialised for Ray: "
                                 f"{type(exc).__name__}: {exc}") from exc
            token = uuid.uuid4().hex
            fingerprint = code_fingerprint() if self.check_code else None
            task = ray.remote(_ray_task).options(num_cpus=self.cpus_per_unit, num_gpus=self.gpus_per_unit,
                                                 max_retries=self.max_retries, name="benchmark-unit")
            for unit in ordered:
                pending[task.remote(token, [ref], unit, self.threads, fingerprint)] = unit
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
                for r in ready:
                    unit = pending.pop(r)
                    try:
                        reply = ray.get(r)
                    except Exception as exc:  # the worker or its node was lost (after retries), or cancelled
                        on_done(unit, None, WorkerDied(f"Ray could not run {unit.unit_id}: {type(exc).__name__}: {exc}"))
                        continue
                    if reply[0] == "init-error":
                        raise RuntimeError(f"a Ray worker ({reply[2]}) could not load the unit executor, so no unit "
                                           f"can run there; the run is stopped:\n{reply[1]}")
                    result, error = _reply_to_outcome(reply)
                    on_done(unit, result, error)
        finally:
            for r in pending:  # interrupted: do not leave the cluster busy with a run nobody collects
                try:
                    ray.cancel(r, force=True)
                except Exception:  # noqa: BLE001 - best effort while unwinding
                    pass
            if owned:
                ray.shutdown()


# --------------------------------------------------------------------------------------------
# Construction from the command line
# --------------------------------------------------------------------------------------------

def make_backend(name: str = "local", device: str = "cpu", jobs: int | None = None, address: str | None = None,
                 cpus_per_unit: float | None = None, gpus_per_unit: float | None = None):
    """The backend callable for ``run --backend NAME`` and its options.

    local: ``jobs`` worker processes with one torch thread each (``jobs`` None or 1: in this
        process, one unit after another, as before). ray: :class:`RayBackend` (``gpus_per_unit``
        defaults to 1 on a CUDA device, else 0; ``cpus_per_unit`` to 1).
    """
    if name == "local":
        given = [f for f, v in (("--ray-address", address), ("--cpus-per-unit", cpus_per_unit),
                                ("--gpus-per-unit", gpus_per_unit)) if v is not None]
        if given:
            raise ValueError(f"{', '.join(given)} appl{'ies' if len(given) == 1 else 'y'} to --backend ray; "
                             f"the local backend takes --jobs")
        if jobs is None or jobs == 1:
            return serial_backend
        return ProcessBackend(jobs)
    if name == "ray":
        if jobs is not None:
            raise ValueError("--jobs applies to --backend local; on Ray every unit is a task, sized by --cpus-per-unit "
                             "and --gpus-per-unit")
        if gpus_per_unit is None:
            gpus_per_unit = 1 if str(device).startswith("cuda") else 0
        return RayBackend(address=address, cpus_per_unit=1 if cpus_per_unit is None else cpus_per_unit,
                          gpus_per_unit=gpus_per_unit)
    if name in BACKENDS:
        return BACKENDS[name]
    raise ValueError(f"unknown backend {name!r}; available: {', '.join(sorted(BACKENDS))}")
