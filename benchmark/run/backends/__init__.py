"""Execution backends that run work units in parallel: worker processes on this machine
(``run --jobs N``) and Ray (``run --backend ray``), on one machine or a cluster.

Both fit the runner's seam ``backend(units, execute, on_done)`` (:mod:`benchmark.run.runner`): the
driver (this process) keeps the results store, the resume rules, the progress bar and the table;
a backend only executes units elsewhere and hands each outcome back through ``on_done`` as it
arrives. So a parallel run writes the same unit files as a serial one, and a run interrupted on
one backend resumes on another.

Nothing but the backend may change a number, and it does not:

- the executor (:class:`benchmark.run.table_run.TableExecutor`: the built adapters with
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
the unit it was running and is replaced. Ctrl-C or SIGTERM to the driver (:mod:`benchmark.core.interrupts`)
stops the workers, local or Ray, and leaves no temporary file behind.

The modules: :mod:`.common` (the submission order, the errors, running one unit, the serial
backend), :mod:`.local` (worker processes), :mod:`.ray_backend` (Ray); this one names the
backends (:data:`BACKENDS`) and builds one from the command line's options (:func:`make_backend`).
"""

from __future__ import annotations

from typing import Callable, Sequence

from benchmark.run.backends.common import (UnitError, WorkerDied, affinity_key, longest_first, pick_next,
                                           serial_backend)
from benchmark.run.backends.local import ProcessBackend, default_jobs
from benchmark.run.backends.ray_backend import RayBackend, code_fingerprint

__all__ = ["ProcessBackend", "RayBackend", "UnitError", "WorkerDied", "affinity_key", "code_fingerprint", "default_jobs",
           "backend_threads", "longest_first", "make_backend", "pick_next", "serial_backend", "BACKENDS"]


def _ray_backend(units: Sequence, execute, on_done) -> None:
    """Each unit a Ray task, default options (:class:`RayBackend`; Ray is imported only when it
    runs, so that the harness does not need it installed)."""
    RayBackend()(units, execute, on_done)


Backend = Callable[[Sequence, Callable, Callable], None]

# name -> backend callable with default options (``backend(units, execute, on_done)``);
# :func:`make_backend` builds one with options (--jobs, --ray-address...), and
# ``benchmark.run.runner.run_units`` takes such a callable too. Add one with ``BACKENDS[name] = fn``.
BACKENDS: dict = {"local": serial_backend, "ray": _ray_backend}


def backend_threads(backend) -> int:
    """The torch threads a backend runs each unit with: its ``threads`` (worker processes: 1; Ray:
    ``--cpus-per-unit``); the serial backend runs units in this process, with its torch threads (all
    the cores unless OMP_NUM_THREADS or torch.set_num_threads says otherwise). The thread count
    changes a fit's numbers (the order of float reductions, which the optimisation amplifies), so it
    enters the units' spec (:func:`benchmark.core.work_units.plan_units`) when it is not 1."""
    if backend is serial_backend:
        import torch

        return max(1, torch.get_num_threads())
    threads = getattr(backend, "threads", 1)
    return threads if isinstance(threads, int) and not isinstance(threads, bool) and threads >= 1 else 1


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
