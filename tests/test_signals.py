"""SIGTERM and SIGINT (Ctrl-C) to a ``run --jobs 2`` driver: it stops its worker processes (none
outlives it, none prints a traceback), removes the executor's temporary folder, releases the
``--out`` lock, keeps the finished units, exits 143 / 130 with one line, and a rerun resumes.

The end-to-end tests run the real CLI in a subprocess (its own session, so that a Ctrl-C can be
sent to the whole process group as a terminal does) on the tiny table1 of :mod:`tiny_run`, with
``TMPDIR`` pointed into the test's folder. The pieces (the handler, the backend's cleanup, Ray's
handler) are also checked in this process, in a second or two.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import pytest

from benchmark.run import runner
from benchmark.run.backends.local import EXECUTOR_FOLDER_PREFIX, ProcessBackend, _executor_folder, _host_tag
from benchmark.run.backends.ray_backend import _keep_sigterm_handler
from benchmark.core.interrupts import Terminated, add_stop_note, exit_code, sigterm_raises, stop_message
from fake_units import FakeExecutor, plan
from tiny_run import write_motion

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc, POSIX signals")

# ``python -m benchmark run table1`` shrunk by tiny_run (the catalog the CLI reads is patched in the
# driver; the workers get the executor, which carries the shrunk spec). Workers are started with
# ``spawn`` and import this file again as ``__mp_main__``: only the driver may run the CLI.
_DRIVER = textwrap.dedent("""
    import sys
    sys.path[:0] = [{root!r}, {tests!r}]

    if __name__ == "__main__":
        import signal

        # Ctrl-C as a process started from a terminal gets it: a test run started in the background
        # of a non-interactive shell (`.ci/run &`) hands SIGINT down ignored, and Python keeps that
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {{signal.SIGINT}})

        import pytest
        from tiny_run import tiny_table1
        from benchmark.cli import main

        tiny_table1(pytest.MonkeyPatch(), fps=(5, 10))
        sys.exit(main(["run", "table1", "--prior", "no-prior", "--prior", "vposer-slerp", "--data", sys.argv[1],
                       "--out", sys.argv[2], *sys.argv[3:]]))
""")
UNITS = 4  # 2 priors x 2 cells x 1 batch


# ------------------------------------------------------------------------------------------------
# helpers


def _stat(pid: int) -> list[str] | None:
    """Fields of /proc/PID/stat after the command name (state, ppid, pgrp, ...), None when gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text.rsplit(")", 1)[1].split()


def _live(pids) -> list[int]:
    """The pids still running (a zombie waiting for its new parent to reap it has ended)."""
    return [p for p in pids if (st := _stat(p)) is not None and st[0] not in ("Z", "X")]


def _group(pgid: int) -> list[int]:
    """Every running process of the process group ``pgid`` (the driver's session: it and whatever it started)."""
    pids = [int(d) for d in os.listdir("/proc") if d.isdigit()]
    return [p for p in _live(pids) if (st := _stat(p)) is not None and int(st[2]) == pgid]


def _workers(driver: int) -> list[int]:
    """The driver's unit workers (multiprocessing ``spawn`` children; not its resource tracker)."""
    found = []
    for d in os.listdir("/proc"):
        if d.isdigit() and (st := _stat(int(d))) is not None and int(st[1]) == driver:
            try:
                if b"spawn_main" in Path(f"/proc/{d}/cmdline").read_bytes():
                    found.append(int(d))
            except OSError:
                pass
    return _live(found)


def _wait(condition, timeout: float, what: str, proc: subprocess.Popen | None = None):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        if proc is not None and proc.poll() is not None:
            pytest.fail(f"the driver exited (code {proc.returncode}) before {what}")
        time.sleep(0.02)
    pytest.fail(f"timed out after {timeout} s waiting for {what}")


class Driver:
    """The tiny table1 run through the real CLI, in a subprocess of its own session."""

    def __init__(self, tmp_path: Path):
        self.tmp = tmp_path
        self.script = tmp_path / "driver.py"
        self.script.write_text(_DRIVER.format(root=str(ROOT), tests=str(ROOT / "tests")))
        self.data = tmp_path / "data"
        write_motion(self.data / "a.npz", seed=0, speed=1.0)
        self.out = tmp_path / "out"
        self.tmpdir = tmp_path / "tmp"  # the driver's TMPDIR: where its executor folder goes
        self.tmpdir.mkdir()
        self.env = dict(os.environ, OMP_NUM_THREADS="1", TMPDIR=str(self.tmpdir))
        self.proc: subprocess.Popen | None = None

    def command(self, *extra, out: Path | None = None) -> list[str]:
        return [sys.executable, str(self.script), str(self.data), str(out or self.out), *extra]

    def start(self, *extra) -> subprocess.Popen:
        self.stdout, self.stderr = self.tmp / "stdout.txt", self.tmp / "stderr.txt"
        with open(self.stdout, "wb") as out, open(self.stderr, "wb") as err:
            self.proc = subprocess.Popen(self.command(*extra), cwd=ROOT, env=self.env, stdout=out, stderr=err,
                                         start_new_session=True)
        return self.proc

    def units(self) -> list[Path]:
        return sorted((self.out / "units").glob("*.json"))

    def executor_folders(self) -> list[Path]:
        return sorted(self.tmpdir.glob(f"{EXECUTOR_FOLDER_PREFIX}*"))

    def kill_all(self) -> None:
        """Whatever the test's outcome: nothing of this run survives it."""
        if self.proc is None:
            return
        for pid in _group(self.proc.pid):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.proc.wait()


@pytest.fixture
def driver(tmp_path):
    d = Driver(tmp_path)
    yield d
    d.kill_all()


def _stop(d: Driver, sig: int, group: bool) -> tuple[int, float, str]:
    """Send ``sig`` to the driver (or to its whole process group, like a terminal's Ctrl-C); wait for
    it to exit. Returns (exit code, seconds it took, stderr)."""
    t0 = time.monotonic()
    if group:
        os.killpg(d.proc.pid, sig)
    else:
        d.proc.send_signal(sig)
    try:
        code = d.proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the driver did not exit within 30 s of signal {sig}")
    return code, time.monotonic() - t0, d.stderr.read_text()


def _assert_stopped_cleanly(d: Driver, workers: list[int], stderr: str) -> None:
    assert "Traceback" not in stderr and "BrokenPipeError" not in stderr, stderr
    # no worker (nor anything else the driver started) outlives it; reparented zombies count as ended
    _wait(lambda: not _live(workers) and not _group(d.proc.pid), 10, "the driver's processes to end")
    assert d.executor_folders() == []
    assert not (d.out / ".lock").exists()


# ------------------------------------------------------------------------------------------------
# end to end: the real CLI


def test_sigterm_stops_the_workers_cleans_up_and_the_rerun_resumes(driver):
    driver.start("--jobs", "2")
    workers = _wait(lambda: len(w := _workers(driver.proc.pid)) == 2 and w, 120, "two workers", driver.proc)
    assert len(driver.executor_folders()) == 1
    folder = driver.executor_folders()[0]
    assert folder.stat().st_mode & 0o777 == 0o700  # private to the user: the workers unpickle what is in it
    _wait(driver.units, 120, "the first unit file", driver.proc)

    code, took, stderr = _stop(driver, signal.SIGTERM, group=False)
    stored = driver.units()
    if code == 0 and len(stored) == UNITS:
        pytest.skip("the run finished before the signal arrived")
    assert code == 143 and took < 10, (code, took, stderr)
    assert stderr.strip().splitlines()[-1] == (f"terminated (SIGTERM): {len(stored)} of {UNITS} work unit(s) stored in "
                                               f"{driver.out / 'units'}; the same command resumes from them")
    assert 1 <= len(stored) < UNITS
    _assert_stopped_cleanly(driver, workers, stderr)
    assert not list((driver.out / "units").glob(".*.tmp"))  # no half-written unit file

    done = subprocess.run(driver.command("--jobs", "1", "--resume", "only-missing"), cwd=ROOT, env=driver.env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert f"{len(stored)} reused, {UNITS - len(stored)} to compute" in done.stdout
    table = json.loads((driver.out / "table1.json").read_text())
    assert table["provenance"]["resume"]["reused"] == len(stored)
    assert not (driver.out / ".lock").exists() and driver.executor_folders() == []


def test_ctrl_c_to_the_process_group_stops_every_process_quietly(driver):
    """A terminal's Ctrl-C reaches the driver and its workers at once: the workers ignore it, the
    driver stops them."""
    driver.start("--jobs", "2")
    workers = _wait(lambda: len(w := _workers(driver.proc.pid)) == 2 and w, 120, "two workers", driver.proc)
    code, took, stderr = _stop(driver, signal.SIGINT, group=True)
    assert code == 130 and took < 10, (code, took, stderr)
    assert stderr.strip().splitlines()[-1].startswith("interrupted: ")
    _assert_stopped_cleanly(driver, workers, stderr)


def _numbers(out: Path) -> tuple:
    """The table's cells without their measured seconds, and every unit's stored numbers."""
    table = json.loads((out / "table1.json").read_text())
    cells = [[{k: v for k, v in c.items() if k not in ("fit_s", "eval_s")} for c in r["cells"]] for r in table["rows"]]
    units = {}
    for path in sorted((out / "units").glob("*.json")):
        r = json.loads(path.read_text())
        units[path.stem] = (r["spec_hash"], r["fingerprint"], r["per_sequence"], r["na_reason"])
    return cells, units


@pytest.mark.slow
def test_sigterm_at_any_point_then_the_same_command_gives_the_same_table_bit_for_bit(driver, tmp_path):
    """SIGTERM while the workers load, and again after a unit is stored; the same command then
    finishes the run: every number equals an uninterrupted run's."""
    ref = tmp_path / "ref"
    subprocess.run(driver.command("--jobs", "1", out=ref), cwd=ROOT, env=driver.env, check=True, capture_output=True,
                   timeout=600)
    stored = []
    for moment in ("workers", "unit"):
        driver.start("--jobs", "2")
        workers = _wait(lambda: len(w := _workers(driver.proc.pid)) == 2 and w, 120, "two workers", driver.proc)
        if moment == "unit":
            _wait(lambda: len(driver.units()) > len(stored), 120, "a new unit file", driver.proc)
        stored = driver.units()
        code, _, stderr = _stop(driver, signal.SIGTERM, group=False)
        assert code == 143, stderr
        _assert_stopped_cleanly(driver, workers, stderr)
        stored = driver.units()
    assert 1 <= len(stored) < UNITS
    done = subprocess.run(driver.command("--jobs", "2"), cwd=ROOT, env=driver.env, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    assert _numbers(driver.out) == _numbers(ref)
    assert (driver.out / "table1.csv").read_bytes() == (ref / "table1.csv").read_bytes()


@pytest.mark.slow
def test_sigterm_on_ray_shuts_the_runtime_down_and_exits_143(driver):
    """ray.init replaces the SIGTERM handler (and adds a C one that aborts 3 s later): the run
    still unwinds, cancels its tasks and stops the Ray runtime it started."""
    pytest.importorskip("ray")
    short = Path(tempfile.mkdtemp(prefix="rs-", dir="/tmp"))  # Ray's socket paths must stay under 108 bytes
    try:
        driver.env.update(TMPDIR=str(short), RAY_USAGE_STATS_ENABLED="0")
        driver.start("--backend", "ray")
        _wait(driver.units, 300, "the first unit file", driver.proc)
        code, took, stderr = _stop(driver, signal.SIGTERM, group=False)
        assert code == 143 and took < 20, (code, took, stderr)
        assert "Traceback" not in stderr and "SIGTERM received" not in stderr, stderr
        assert stderr.strip().splitlines()[-1].startswith("terminated (SIGTERM): ")
        _wait(lambda: not _group(driver.proc.pid), 30, "the Ray processes to end")
        assert not (driver.out / ".lock").exists()
    finally:
        driver.kill_all()
        shutil.rmtree(short, ignore_errors=True)


# ------------------------------------------------------------------------------------------------
# the pieces, in this process


def _served(unit):
    return None


class Fake(FakeExecutor):
    """The runner tests' fake protocol, picklable (no lambda), for worker processes."""

    def __init__(self):
        super().__init__(na=_served)


class _Stop:
    """on_done that raises ``exc`` at the n-th finished unit (as the SIGTERM handler would)."""

    def __init__(self, n: int, exc: BaseException):
        self.n, self.exc, self.seen, self.folders = n, exc, [], []

    def __call__(self, unit, result, error):
        self.seen.append(unit.unit_id)
        def mode(path):
            return path.stat().st_mode & 0o777

        self.folders = [(f.name, mode(f), sorted((p.name, mode(p)) for p in f.iterdir()))
                        for f in Path(tempfile.gettempdir()).glob(f"{EXECUTOR_FOLDER_PREFIX}*")]
        if len(self.seen) == self.n:
            raise self.exc


@pytest.fixture
def private_tmp(tmp_path, monkeypatch):
    """tempfile.gettempdir() -> a folder of this test's own."""
    folder = tmp_path / "tmp"
    folder.mkdir()
    monkeypatch.setenv("TMPDIR", str(folder))
    monkeypatch.setattr(tempfile, "tempdir", None)  # read TMPDIR again
    yield folder
    tempfile.tempdir = None


@pytest.mark.parametrize("exc", [Terminated(), RuntimeError("simulated")], ids=lambda exc: type(exc).__name__)
def test_process_backend_stops_its_workers_and_removes_its_folder(private_tmp, exc):
    units = plan(priors=["p"])
    stop = _Stop(1, exc)
    with pytest.raises(type(exc)):
        ProcessBackend(2)(units, Fake(), stop)
    # while it ran: one folder only this user can open, holding the executor only this user can read
    assert [(mode, files) for _, mode, files in stop.folders] == [(0o700, [("executor.pkl", 0o600)])]
    assert list(private_tmp.iterdir()) == []  # and afterwards, nothing
    assert multiprocessing.active_children() == []  # every worker was stopped and reaped


def test_process_backend_removes_its_folder_after_a_full_run(private_tmp, tmp_path):
    report = runner.run_units(plan(priors=["p"]), Fake(), tmp_path / "out", backend=ProcessBackend(2), progress=False)
    assert report.ok and list(private_tmp.iterdir()) == []


def test_a_folder_left_by_a_killed_driver_is_removed_by_the_next_run(private_tmp):
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = private_tmp / f"{EXECUTOR_FOLDER_PREFIX}{_host_tag()}-{int(gone.stdout)}-k3x_9q1z"
    stale.mkdir()
    (stale / "executor.pkl").write_bytes(b"x" * 10)
    mine = Path(_executor_folder())  # this (live) process's: kept
    other = private_tmp / f"{EXECUTOR_FOLDER_PREFIX}other-host.example-{int(gone.stdout)}-abc"  # cannot be checked
    other.mkdir()
    assert mine.parent == private_tmp and mine.stat().st_mode & 0o777 == 0o700
    assert not stale.exists() and mine.exists() and other.exists()


def test_sigterm_raises_terminated_once_and_the_exit_codes():
    assert exit_code(KeyboardInterrupt()) == 130 and stop_message(KeyboardInterrupt()) == "interrupted"
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated) as caught:
        with sigterm_raises():
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(5)  # the handler raises before this ends
            finally:
                os.kill(os.getpid(), signal.SIGTERM)  # a second one while unwinding from the first: ignored
    assert signal.getsignal(signal.SIGTERM) is before  # the previous handler is back
    add_stop_note(caught.value, "3 of 4 stored")
    add_stop_note(caught.value, "not this one")
    assert exit_code(caught.value) == 143 and stop_message(caught.value) == "terminated (SIGTERM): 3 of 4 stored"


def test_run_units_says_what_is_stored_when_interrupted(tmp_path):
    class Interrupting(FakeExecutor):
        def __call__(self, unit):
            if len(self.calls) == 2:
                raise Terminated()
            return super().__call__(unit)

    units = plan()
    with pytest.raises(Terminated) as caught:
        runner.run_units(units, Interrupting(), tmp_path, progress=False)
    assert caught.value.stop_note == (f"2 of {len(units)} work unit(s) stored in {tmp_path / 'units'}; the same "
                                      "command resumes from them")
    assert len(list((tmp_path / "units").glob("*.json"))) == 2


def test_a_signal_between_a_units_file_and_its_bookkeeping_counts_the_file(tmp_path, monkeypatch):
    """The count in the stop line is what the rerun reuses: the files on disk, even when the signal
    lands right after a unit's file is written (seen on CI: the line said 0 while 1 file was there)."""
    written = []

    def write_then_stop(path, obj):
        runner_write(path, obj)
        written.append(path)
        if len(written) == 2:
            raise Terminated()

    runner_write = runner.atomic_write_json
    monkeypatch.setattr(runner, "atomic_write_json", write_then_stop)
    units = plan()
    with pytest.raises(Terminated) as caught:
        runner.run_units(units, FakeExecutor(), tmp_path, progress=False)
    assert caught.value.stop_note.startswith(f"2 of {len(units)} work unit(s) stored in ")
    assert len(list((tmp_path / "units").glob("*.json"))) == 2


def test_a_keyboard_interrupt_after_sigterm_is_still_sigterm():
    """Ray's ray.wait raises a new KeyboardInterrupt when a signal handler raised: still SIGTERM."""
    with pytest.raises(Terminated) as caught:
        with sigterm_raises():
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(5)
            except Terminated:
                interrupt = KeyboardInterrupt()
                add_stop_note(interrupt, "1 of 4 stored")
                raise interrupt from None
    assert exit_code(caught.value) == 143 and stop_message(caught.value) == "terminated (SIGTERM): 1 of 4 stored"
    with pytest.raises(KeyboardInterrupt) as caught:  # a Ctrl-C stays a Ctrl-C
        with sigterm_raises():
            raise KeyboardInterrupt
    assert exit_code(caught.value) == 130


def test_ray_init_does_not_keep_the_sigterm_handler_of_the_cli():
    """ray.init replaces the SIGTERM handler (sys.exit, and a C crash reporter that aborts): the
    CLI's is put back, so that SIGTERM on Ray unwinds like Ctrl-C as well."""
    with sigterm_raises():
        ours = signal.getsignal(signal.SIGTERM)
        with _keep_sigterm_handler():
            signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(signum))  # what ray.init does
        assert signal.getsignal(signal.SIGTERM) is ours
    with _keep_sigterm_handler():  # outside the CLI (a notebook): Ray's choice is left alone
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


_STARTS_A_WORKER_BLOCKED = """
import multiprocessing as mp, signal, time
from benchmark.run.backends.local import sigint_blocked
ctx = mp.get_context("spawn")
with sigint_blocked():
    proc = ctx.Process(target=time.sleep, args=(0,))
    proc.start()  # the first start in this interpreter: it also starts multiprocessing's resource tracker
    print(signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, []))
proc.join()
print(signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, []))
"""


@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask"), reason="no signal masks on this platform")
def test_the_first_worker_starts_with_sigint_still_blocked():
    """The resource tracker's start unblocks SIGINT in the starting thread; the worker started right
    after it must still inherit the block (CI once saw a Ctrl-C kill a first worker in ``import site``)."""
    done = subprocess.run([sys.executable, "-c", _STARTS_A_WORKER_BLOCKED], cwd=ROOT, capture_output=True, text=True,
                          timeout=120, env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["True", "False"]  # blocked while starting; unblocked again afterwards


class _InterruptedInCompiledCode(FakeExecutor):
    """The third unit meets SIGTERM inside numba's compiled code: numba hands the handler's
    exception back wrapped in a SystemError (seen on a real sls run: the run went on to the next unit)."""

    def __init__(self, interrupt: KeyboardInterrupt):
        super().__init__()
        self.interrupt = interrupt

    def __call__(self, unit):
        if len(self.calls) == 2:
            self.calls.append(unit.unit_id)
            try:
                raise self.interrupt
            except KeyboardInterrupt as exc:
                raise SystemError("CPUDispatcher(<function _query_cached>) returned a result with an exception set") from exc
        return super().__call__(unit)


@pytest.mark.parametrize("interrupt", [Terminated(), KeyboardInterrupt()], ids=["SIGTERM", "Ctrl-C"])
def test_an_interrupt_inside_compiled_code_stops_the_serial_run(tmp_path, interrupt):
    units = plan()
    execute = _InterruptedInCompiledCode(interrupt)
    with pytest.raises(type(interrupt)) as caught:
        runner.run_units(units, execute, tmp_path, progress=False)
    assert len(execute.calls) == 3 and type(caught.value) is type(interrupt)  # stopped there, not failed and passed over
    assert len(list((tmp_path / "units").glob("*.json"))) == 2


_REPORT_POOL = """
import signal
from benchmark.report.cells import run_in_pool
out = run_in_pool(signal.getsignal, [(signal.SIGINT,)] * 2, workers=2)
print([r is signal.SIG_IGN for r, _ in out], [e for _, e in out])
print(signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, []))
print(run_in_pool(int, [("x",)] * 2, workers=2)[0][1])
"""


@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask"), reason="no signal masks on this platform")
def test_the_report_animation_workers_ignore_ctrl_c():
    """The report's animation pool: its workers ignore Ctrl-C (the driver stops the pool; before,
    a Ctrl-C printed a traceback from every worker), the driver's mask is put back, and a job's
    error comes back as its text."""
    done = subprocess.run([sys.executable, "-c", _REPORT_POOL], cwd=ROOT, capture_output=True, text=True,
                          timeout=120, env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[:2] == ["[True, True] [None, None]", "False"]
    assert lines[2].startswith("ValueError: invalid literal for int()")
