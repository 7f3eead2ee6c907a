"""The Ray backend (``run --backend ray``): every unit a Ray task, on one machine or a cluster; the
executor put once in the object store; the driver and every worker must run the same code
(:func:`code_fingerprint`). Ray is imported only when the backend runs."""

from __future__ import annotations

import hashlib
import logging
import re
import signal
import threading
import traceback
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Sequence

from benchmark.run.backends.common import (WorkerDied, execute_unit, longest_first, reply_to_outcome, set_threads,
                                           worker_where)
from benchmark.run.backends.local import default_jobs

log = logging.getLogger(__name__)


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
        set_threads(threads)
        if fingerprint is not None and code_fingerprint() != fingerprint:
            import benchmark

            raise RuntimeError(f"this Ray worker runs other benchmark code than the driver (code fingerprint "
                               f"{code_fingerprint()[:12]} here, {fingerprint[:12]} on the driver; package at "
                               f"{Path(benchmark.__file__).parent}): install the same commit of the project on "
                               f"every node (README, 'Scale out')")
    except Exception as exc:
        return ("init-error", f"{type(exc).__name__}: {exc}", worker_where())
    execute = _WORKER_EXECUTORS.get(token)
    if execute is None:
        try:
            import ray

            execute = ray.get(boxed_ref[0])
        except Exception:  # e.g. a module the executor needs is missing on this worker
            return ("init-error", traceback.format_exc(), worker_where())
        _WORKER_EXECUTORS.clear()  # keep only the current run's
        _WORKER_EXECUTORS[token] = execute
    return execute_unit(execute, unit)


@contextmanager
def _keep_sigterm_handler():
    """``ray.init`` replaces the driver's SIGTERM handler (with ``sys.exit``, and, in C, with a crash
    reporter that prints a stack and aborts the process 3 s later). Where the CLI's handler was in
    place (:func:`benchmark.core.interrupts.sigterm_raises`), it is put back afterwards (which removes
    Ray's C handler too), so that SIGTERM unwinds the run like Ctrl-C: the pending tasks are
    cancelled, the Ray runtime shut down (the ``finally`` of :meth:`RayBackend.__call__`), the
    ``--out`` lock released, exit 143."""
    from benchmark.core.interrupts import is_terminated_handler

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
                    result, error = reply_to_outcome(reply)
                    on_done(unit, result, error)
        finally:
            for r in pending:  # interrupted: do not leave the cluster busy with a run nobody collects
                try:
                    ray.cancel(r, force=True)
                except Exception:  # noqa: BLE001 - best effort while unwinding
                    pass
            if owned:
                ray.shutdown()
