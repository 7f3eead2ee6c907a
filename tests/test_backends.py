"""Parallel backends: worker processes (``--jobs N``) and Ray (``--backend ray``).

Nothing but the backend may change a number: the real tables (a one-cell slice of the smoke
table1, and the smoke inbetween table for four priors) are run serially in this process and on
the parallel backends, and every stored metric sum and observation fingerprint must be
bit-identical. Also: failures on a worker come back with their traceback while the other units
finish, a dead worker fails only its unit, interrupted runs resume on the other backend, units go
longest-first, and the CLI flags.

One local Ray runtime (2 CPUs, no dashboard) serves the whole module and is shut down at its end.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch

from benchmark.run import runner
from benchmark.run.backends import BACKENDS, ProcessBackend, RayBackend, affinity_key, longest_first, make_backend, pick_next
from benchmark.run.catalog import get_profile, load_table_spec
from benchmark.run.table_run import run_table
from benchmark.core.work_units import estimate_cost
from fake_units import FakeExecutor, plan

ROOT = Path(__file__).resolve().parents[1]
TABLE1_GRID = {"points": [100], "fps": [5]}  # one of the CI cells of tests/test_table1_regression.py
TABLE1_PRIORS = ["no-prior", "vposer-slerp"]
INBETWEEN_PRIORS = ["slerp", "no-prior", "vposer-slerp", "hmvae"]
TIMING_KEYS = {"fit_s", "eval_s", "s_per_frame", "s_per_frame_std", "time_per_frame_s", "time_per_frame_s_std",
               "time_per_frame_s_ci95"}


# ------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------

def _spec(table: str) -> dict:
    spec = load_table_spec(table)
    if table != "table1":
        return spec
    # the backends, not the fit's rules: table1's version 1 start (no facing or limb search) keeps
    # these units short; every backend runs the same rules, so bit-identity is still the check
    return {**spec, "grid": TABLE1_GRID, "objective": {**spec["objective"], "facing": "heading8", "start_search": "none"}}


def _run(table, priors, body, out, backend="local", **options):
    """A smoke run of ``table``; in this process (no ``jobs``) with one torch thread, as every worker
    runs (a unit's thread count enters its spec: the serial run must make the same units)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        result = run_table(_spec(table), get_profile("smoke", table=table), priors=priors, body=body, device="cpu",
                           seed=0, out_dir=out, backend=backend, backend_options=options)
    finally:
        torch.set_num_threads(before)
    assert not result["failures"], result["failures"]
    return result["table"]


def _unit_numbers(out: Path) -> dict:
    """unit id -> everything in its stored result that is a number or an input, timings left out."""
    numbers = {}
    for path in sorted((out / "units").glob("*.json")):
        r = json.loads(path.read_text())
        numbers[path.stem] = {"fingerprint": r["fingerprint"], "na_reason": r["na_reason"], "spec_hash": r["spec_hash"],
                              "per_sequence": r["per_sequence"]}
    return numbers


def _table_numbers(table: dict) -> list:
    return [(row["prior"], [{k: v for k, v in cell.items() if k not in TIMING_KEYS} for cell in row["cells"]])
            for row in table["rows"]]


def _assert_identical(out_a: Path, table_a: dict, out_b: Path, table_b: dict) -> None:
    a, b = _unit_numbers(out_a), _unit_numbers(out_b)
    assert a and sorted(a) == sorted(b)
    for uid in a:
        assert a[uid] == b[uid], f"{uid}: the stored results differ between backends"  # exact float equality
    assert _table_numbers(table_a) == _table_numbers(table_b)


def _served(unit):
    return None


class Fake(FakeExecutor):
    """The runner tests' fake protocol, picklable (no lambda) so that it can go to workers."""

    def __init__(self, fail=()):
        super().__init__(fail=fail, na=_served)


class ExitingExecutor(Fake):
    """Kills its worker process (no exception, no answer) on the chosen units."""

    def __init__(self, die=()):
        super().__init__()
        self.die = set(die)

    def __call__(self, unit):
        if unit.unit_id in self.die:
            os._exit(3)
        return super().__call__(unit)


class UnloadableOnWorkers(Fake):
    """Cannot be unpickled anywhere (like an executor whose module a worker lacks)."""

    def __setstate__(self, state):
        raise ImportError("simulated: a module this executor needs is missing on the worker")


class InterruptAfter:
    """Wraps an executor; raises KeyboardInterrupt (Ctrl-C) instead of running the n-th unit."""

    def __init__(self, execute, n):
        self.execute, self.n, self.calls = execute, n, 0

    def __call__(self, unit):
        self.calls += 1
        if self.calls > self.n:
            raise KeyboardInterrupt
        return self.execute(unit)


# ------------------------------------------------------------------------------------------
# fixtures: one Ray runtime, the serial reference runs
# ------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def ray_runtime():
    ray = pytest.importorskip("ray", reason="the ray extra is not installed: pip install -e '.[ray]'")
    if ray.is_initialized():
        ray.shutdown()
    env = {v: "1" for v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
    # Ray workers import the project from the driver's folder, but not this tests/ folder (the fakes)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "tests")])
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, runtime_env={"env_vars": env})
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def table1_serial(tmp_path_factory, anny_body):
    out = tmp_path_factory.mktemp("table1_serial")
    return out, _run("table1", TABLE1_PRIORS, anny_body, out)


@pytest.fixture(scope="module")
def inbetween_serial(tmp_path_factory, anny_body):
    out = tmp_path_factory.mktemp("inbetween_serial")
    return out, _run("inbetween", INBETWEEN_PRIORS, anny_body, out)


# ------------------------------------------------------------------------------------------
# ordering and options (no workers)
# ------------------------------------------------------------------------------------------

def test_units_go_longest_first_and_ties_keep_the_plan_order():
    spec = load_table_spec("table1")
    units = plan(spec=spec, seqs=("s0", "s1", "s2"))  # batches of 2: s0,s1 and s2
    ordered = longest_first(units)
    costs = [estimate_cost(u) for u in ordered]
    assert costs == sorted(costs, reverse=True)
    assert ordered[0].cell == {"points": 10000, "fps": 10} and len(ordered[0].sequence_ids) == 2
    assert ordered[-1].cell == {"points": 100, "fps": 5} and len(ordered[-1].sequence_ids) == 1
    ties = [u.unit_id for u in ordered if estimate_cost(u) == costs[0]]
    assert ties == [u.unit_id for u in units if u.unit_id in ties]  # plan order among equals
    # numbers inside strings count (sls sweeps), and an executor's own estimate wins
    sls_units = plan(spec=load_table_spec("sls"), priors=["no-prior"], seqs=("s0",))
    assert longest_first(sls_units)[0].cell == {"sweep": "p10000"}

    class Reverse:
        def unit_cost(self, unit):
            return -estimate_cost(unit)

    assert longest_first(units, Reverse())[0].cell == {"points": 100, "fps": 5}


def test_a_worker_keeps_to_its_cells_and_takes_others_only_at_the_end():
    from collections import deque

    spec = load_table_spec("table1")
    units = longest_first(plan(spec=spec, priors=["no-prior", "hmvae", "vposer-slerp"], seqs=("s0",)))
    queue = deque(units)
    workers = [set(), set()]
    claimed: set = set()
    taken = [[], []]
    turn = 0
    while queue:
        u = pick_next(queue, workers[turn], claimed)
        workers[turn].add(affinity_key(u))
        claimed.add(affinity_key(u))
        taken[turn].append(u)
        turn = 1 - turn
    assert sorted(u.unit_id for t in taken for u in t) == sorted(u.unit_id for u in units)  # each unit once
    # the two workers start different cells, the longest two, and each opens a cell only when its own are done
    assert taken[0][0].cell == {"points": 10000, "fps": 10} and taken[1][0].cell == {"points": 10000, "fps": 5}
    for t in taken:
        keys = [affinity_key(u) for u in t]
        opened = [k for i, k in enumerate(keys) if k not in keys[:i]]
        for k in opened[:-1]:  # a cell is finished (by this worker) before the next is opened, but the last
            last = max(i for i, x in enumerate(keys) if x == k)
            assert all(x == k for x in keys[keys.index(k): last + 1])
    # 6 cells of 3 units on 2 workers: each cell is run by one worker
    assert not ({affinity_key(u) for u in taken[0]} & {affinity_key(u) for u in taken[1]})


def test_backend_options_are_checked():
    assert make_backend("local") is BACKENDS["local"]
    assert make_backend("local", jobs=1) is BACKENDS["local"]
    assert isinstance(make_backend("local", jobs=3), ProcessBackend)
    ray_backend = make_backend("ray", device="cuda")
    assert isinstance(ray_backend, RayBackend) and ray_backend.gpus_per_unit == 1 and ray_backend.cpus_per_unit == 1
    assert make_backend("ray", cpus_per_unit=2.5).threads == 2
    with pytest.raises(ValueError, match="--jobs must be a positive integer"):
        make_backend("local", jobs=0)
    with pytest.raises(ValueError, match="--ray-address applies to --backend ray"):
        make_backend("local", address="auto")
    with pytest.raises(ValueError, match="--jobs applies to --backend local"):
        make_backend("ray", jobs=2)
    with pytest.raises(ValueError, match="--ray-address must be 'auto' or HOST:PORT"):
        make_backend("ray", address="not an address")
    with pytest.raises(ValueError, match="--cpus-per-unit must be a positive number"):
        make_backend("ray", cpus_per_unit=0)
    with pytest.raises(ValueError, match="unknown backend 'dask'"):
        make_backend("dask")


def test_cli_rejects_flags_of_the_other_backend(capsys):
    from benchmark.cli import main

    assert main(["run", "inbetween", "--profile", "smoke", "--jobs", "2", "--backend", "ray"]) == 2
    assert "--jobs applies to --backend local" in capsys.readouterr().err
    assert main(["run", "inbetween", "--profile", "smoke", "--gpus-per-unit", "1"]) == 2
    assert "--gpus-per-unit applies to --backend ray" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------
# worker processes (--jobs)
# ------------------------------------------------------------------------------------------

def test_jobs_failure_comes_back_with_its_traceback_and_the_others_finish(tmp_path, caplog):
    units = plan()
    bad = units[1].unit_id
    serial = runner.run_units(units, FakeExecutor(), tmp_path / "serial", progress=False)
    report = runner.run_units(units, Fake(fail={bad}), tmp_path / "jobs", backend=ProcessBackend(2),
                              progress=False)
    assert list(report.failed) == [bad]
    assert "RuntimeError: simulated failure in" in report.failed[bad] and "worker traceback" in report.failed[bad]
    assert "fake_units.py" in report.failed[bad]  # the worker's own traceback, down to the raising line
    assert sorted(report.ran) == sorted(u.unit_id for u in units if u.unit_id != bad)
    assert {k: v for k, v in serial.results.items() if k != bad} == report.results  # bit-identical
    assert list(report.results) == [u.unit_id for u in units if u.unit_id != bad]  # plan order, whatever ran first


def test_jobs_a_dead_worker_fails_only_its_unit(tmp_path):
    units = plan()
    dead = units[0].unit_id
    report = runner.run_units(units, ExitingExecutor(die={dead}), tmp_path, backend=ProcessBackend(2), progress=False)
    assert list(report.failed) == [dead] and "WorkerDied" in report.failed[dead] and "exit code 3" in report.failed[dead]
    assert len(report.ran) == len(units) - 1


def test_jobs_an_unpicklable_executor_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="cannot be pickled.*--jobs 1"):
        runner.run_units(plan(), lambda unit: {}, tmp_path, backend=ProcessBackend(2), progress=False)


def test_jobs_a_worker_that_cannot_load_the_executor_stops_the_run(tmp_path):
    with pytest.raises(RuntimeError, match="could not load the unit executor(.|\n)*simulated: a module"):
        runner.run_units(plan(), UnloadableOnWorkers(), tmp_path, backend=ProcessBackend(2), progress=False)
    assert not list(tmp_path.glob("units/*.json"))


def test_jobs_2_is_bit_identical_to_jobs_1_on_table1(table1_serial, tmp_path, anny_body):
    serial_out, serial_table = table1_serial
    table = _run("table1", TABLE1_PRIORS, anny_body, tmp_path, jobs=2)
    _assert_identical(serial_out, serial_table, tmp_path, table)


# ------------------------------------------------------------------------------------------
# Ray
# ------------------------------------------------------------------------------------------

def test_ray_failure_comes_back_with_its_traceback_and_the_others_finish(ray_runtime, tmp_path):
    units = plan()
    bad = units[2].unit_id
    serial = runner.run_units(units, FakeExecutor(), tmp_path / "serial", progress=False)
    report = runner.run_units(units, Fake(fail={bad}), tmp_path / "ray", backend="ray", progress=False)
    assert list(report.failed) == [bad]
    assert "RuntimeError: simulated failure in" in report.failed[bad] and "fake_units.py" in report.failed[bad]
    assert {k: v for k, v in serial.results.items() if k != bad} == report.results
    assert ray_runtime.is_initialized()  # a runtime the backend did not start is left running


def test_ray_a_lost_worker_fails_only_its_unit(ray_runtime, tmp_path):
    units = plan()
    dead = units[0].unit_id
    backend = RayBackend(max_retries=0)
    report = runner.run_units(units, ExitingExecutor(die={dead}), tmp_path, backend=backend, progress=False)
    assert list(report.failed) == [dead] and "WorkerDied" in report.failed[dead]
    assert len(report.ran) == len(units) - 1


def test_ray_a_worker_that_cannot_load_the_executor_stops_the_run(ray_runtime, tmp_path):
    with pytest.raises(RuntimeError, match="could not load the unit executor(.|\n)*simulated: a module"):
        runner.run_units(plan(), UnloadableOnWorkers(), tmp_path, backend="ray", progress=False)
    assert not list(tmp_path.glob("units/*.json"))


def test_ray_workers_refuse_other_code_than_the_drivers(ray_runtime, tmp_path, monkeypatch):
    from benchmark.run.backends import ray_backend as backends

    monkeypatch.setattr(backends, "code_fingerprint", lambda: "0" * 64)  # the driver now "runs" other code
    with pytest.raises(RuntimeError, match="runs other benchmark code than the driver"):
        runner.run_units(plan(), Fake(), tmp_path, backend="ray", progress=False)
    assert not list(tmp_path.glob("units/*.json"))


def test_ray_asks_for_resources_the_cluster_has(ray_runtime, tmp_path):
    with pytest.raises(ValueError, match="--gpus-per-unit 1: the Ray cluster has 0 GPU"):
        runner.run_units(plan(), Fake(), tmp_path, backend=RayBackend(gpus_per_unit=1), progress=False)
    assert not (tmp_path / "units").exists()


def test_ray_is_bit_identical_to_local_on_table1(ray_runtime, table1_serial, tmp_path, anny_body):
    serial_out, serial_table = table1_serial
    table = _run("table1", TABLE1_PRIORS, anny_body, tmp_path, backend="ray")
    _assert_identical(serial_out, serial_table, tmp_path, table)


def test_ray_is_bit_identical_to_local_on_inbetween(ray_runtime, inbetween_serial, tmp_path, anny_body):
    serial_out, serial_table = inbetween_serial
    table = _run("inbetween", INBETWEEN_PRIORS, anny_body, tmp_path, backend="ray")
    _assert_identical(serial_out, serial_table, tmp_path, table)


def test_start_local_interrupt_finish_on_ray(ray_runtime, inbetween_serial, tmp_path, anny_body, monkeypatch):
    """Resume across backends: Ctrl-C a local run after 5 units, finish it on Ray: same table, and
    the 5 stored units are reused, not rerun."""
    from benchmark.run import table_run

    serial_out, serial_table = inbetween_serial
    real = table_run.TableExecutor
    monkeypatch.setattr(table_run, "TableExecutor", lambda *a: InterruptAfter(real(*a), 5))
    with pytest.raises(KeyboardInterrupt):
        _run("inbetween", INBETWEEN_PRIORS, anny_body, tmp_path)
    monkeypatch.undo()
    stored = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "units").glob("*.json")}
    assert len(stored) == 5
    table = _run("inbetween", INBETWEEN_PRIORS, anny_body, tmp_path, backend="ray")
    assert {p: (tmp_path / "units" / p).stat().st_mtime_ns for p in stored} == stored  # reused, not rerun
    _assert_identical(serial_out, serial_table, tmp_path, table)


def test_interrupted_ray_run_resumes(ray_runtime, inbetween_serial, tmp_path, anny_body, monkeypatch):
    """Ctrl-C on the driver of a Ray run while it stores its 4th result: the 3 stored units stay,
    the rest is cancelled; a local rerun finishes the table, identical to the serial one."""
    serial_out, serial_table = inbetween_serial
    real_write, writes = runner.atomic_write_json, []

    def write_then_interrupt(path, obj):
        writes.append(path)
        if len(writes) == 4:
            raise KeyboardInterrupt
        return real_write(path, obj)

    monkeypatch.setattr(runner, "atomic_write_json", write_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        _run("inbetween", INBETWEEN_PRIORS, anny_body, tmp_path, backend="ray")
    monkeypatch.undo()
    assert len(list((tmp_path / "units").glob("*.json"))) == 3
    table = _run("inbetween", INBETWEEN_PRIORS, anny_body, tmp_path)
    _assert_identical(serial_out, serial_table, tmp_path, table)


def test_cli_runs_on_ray(ray_runtime, tmp_path, capsys):
    from benchmark.cli import main

    out = tmp_path / "cli"
    assert main(["run", "inbetween", "--profile", "smoke", "--prior", "slerp", "--backend", "ray",
                 "--cpus-per-unit", "1", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "backend ray" in text and "| slerp" in text
    assert len(list((out / "units").glob("*.json"))) == 4 and (out / "inbetween.json").exists()
