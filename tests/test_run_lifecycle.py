"""The life of a run folder when a user is interrupted or makes mistakes: stale locks whose pid was
reused, and the other cases of docs/running.md that earlier tests do not cover."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time

import pytest

from benchmark.core.outdir import OutDirError, OutDirLock


def _write_lock(folder, pid, started):
    (folder / ".lock").write_text(json.dumps({"pid": pid, "host": socket.gethostname(), "started": started,
                                              "command": "python -m benchmark run table1"}))


def test_a_lock_naming_this_process_pid_is_a_killed_run_before_a_restart(tmp_path, capsys):
    # a container restarted after its run was killed gives the new run the same pid: its lock was
    # refused as "this process already holds" it, for ever
    _write_lock(tmp_path, os.getpid(), time.time() - 3600)
    with OutDirLock(tmp_path) as lock:
        assert lock.took_over["pid"] == os.getpid()
        assert json.loads((tmp_path / ".lock").read_text())["started"] > time.time() - 60
    assert not (tmp_path / ".lock").exists()
    assert "its pid is now this process's" in capsys.readouterr().out


def test_the_same_process_taking_its_own_lock_twice_is_still_refused(tmp_path):
    with OutDirLock(tmp_path):
        with pytest.raises(OutDirError, match="this process already holds"):
            OutDirLock(tmp_path).acquire()
    with OutDirLock(tmp_path):  # released: free again
        pass


@pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="process start times come from /proc (Linux)")
def test_a_lock_whose_pid_now_belongs_to_a_later_process_is_taken_over(tmp_path, capsys):
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        _write_lock(tmp_path, other.pid, time.time() - 3600)  # written an hour before that process started
        with OutDirLock(tmp_path) as lock:
            assert lock.took_over["pid"] == other.pid
        assert "another process's, started later" in capsys.readouterr().out
        _write_lock(tmp_path, other.pid, time.time())  # written after it started: it may be its owner
        with pytest.raises(OutDirError, match="another run is writing there"):
            OutDirLock(tmp_path).acquire()
    finally:
        other.kill()
        other.wait()


@pytest.mark.parametrize("blocker", ["units", "units/stale"])
def test_a_units_folder_that_is_a_file_fails_before_any_unit_is_computed(tmp_path, blocker):
    # before: every unit was computed, then failed to be stored (FileExistsError), exit 1
    from benchmark.run import runner
    from fake_units import FakeExecutor, plan

    (tmp_path / "units").mkdir()
    (tmp_path / blocker).rmdir() if (tmp_path / blocker).is_dir() else None
    (tmp_path / blocker).write_text("my notes\n")
    ex = FakeExecutor()
    with pytest.raises(OutDirError, match=f"{tmp_path / blocker} is a file, not the folder .* move it away"):
        runner.run_units(plan(), ex, tmp_path, progress=False)
    assert ex.calls == [] and (tmp_path / blocker).read_text() == "my notes\n"


def test_the_run_command_checks_the_units_folder_before_loading_anything(tmp_path, monkeypatch, capsys):
    from benchmark.cli import main
    from benchmark.run import table_run

    monkeypatch.setattr(table_run, "run_table", lambda *a, **k: pytest.fail("run_table reached"))
    (tmp_path / "units").write_text("")
    assert main(["run", "table1", "--prior", "no-prior", "--profile", "smoke", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"error: --out {tmp_path}: {tmp_path / 'units'} is a file")
    assert not (tmp_path / ".lock").exists()


def test_half_written_files_of_a_killed_run_are_removed_by_the_next_run(tmp_path, monkeypatch, capsys):
    # a run killed during an atomic write (SIGKILL, OOM) left ".<file>.<random>.tmp" behind for ever
    import benchmark.body
    from benchmark.cli import main
    from benchmark.run import table_run

    seen = {}

    def fake_run_table(*args, out_dir, **kwargs):
        seen["left"] = sorted(p.name for p in out_dir.rglob("*") if p.is_file() and p.name != ".lock")
        return {"markdown": "", "files": {}, "failures": {}}

    monkeypatch.setattr(table_run, "run_table", fake_run_table)
    monkeypatch.setattr(benchmark.body, "get_body", lambda *a, **k: None)
    units = tmp_path / "units"
    units.mkdir()
    partial = [units / ".table1__no-prior__points=100_fps=5__b000.json.k2j4h5x_.tmp",
               units / ".table1__no-prior__points=100_fps=5__b000.npz.a1b2c3d4.tmp", tmp_path / ".table1.md.zz99yy88.tmp"]
    kept = [units / "notes.tmp", tmp_path / ".my.json.tmp", units / "table1__no-prior__points=100_fps=5__b000.json"]
    for p in partial + kept:
        p.write_text("{\"half")
    assert main(["run", "table1", "--prior", "no-prior", "--profile", "smoke", "--jobs", "1", "--out", str(tmp_path)]) == 0
    assert seen["left"] == sorted(p.name for p in kept)
    assert all(p.exists() for p in kept) and not any(p.exists() for p in partial)


def test_a_second_ctrl_c_while_the_first_unwinds_is_ignored():
    import signal

    from benchmark.core import interrupts

    before = signal.getsignal(signal.SIGINT)
    if before is not signal.default_int_handler:
        pytest.skip("SIGINT is not Python's default handler here")
    cleaned = []
    with pytest.raises(KeyboardInterrupt):
        with interrupts.sigint_once():
            try:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(1)
            finally:  # the cleanup of the first Ctrl-C: a second one must not cut it short
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.2)
                cleaned.append(True)
    assert cleaned == [True] and signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_ctrl_c_during_the_exit_after_the_stop_line_prints_no_traceback(tmp_path):
    # python -m benchmark stopped by Ctrl-C: a further Ctrl-C during the interpreter's exit (torch's
    # atexit hooks) printed "Exception ignored in atexit callback ... KeyboardInterrupt"
    code = ("import atexit, os, signal, time, runpy\n"
            "import benchmark.cli as cli\n"
            "def again():\n"
            "    os.kill(os.getpid(), signal.SIGINT); time.sleep(0.3); print('exit finished', flush=True)\n"
            "atexit.register(again)\n"
            "cli.main = lambda: 130\n"
            "runpy.run_module('benchmark', run_name='__main__')\n")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=60,
                          env={**os.environ, "PYTHONPATH": root})
    assert proc.returncode == 130, proc.stderr
    assert "exit finished" in proc.stdout and "Traceback" not in proc.stderr


def test_a_unit_made_on_another_device_is_not_reused(tmp_path, capsys):
    # the device is not in the spec hash: units fitted on a GPU were reused in a CPU run's table
    # (and the other way round), whose header says one device
    from benchmark.run import runner
    from fake_units import FakeExecutor, plan

    class OnGPU(FakeExecutor):
        def __call__(self, unit):
            return {**super().__call__(unit), "device": "cuda:0"}

    units = plan()
    assert runner.run_units(units, OnGPU(), tmp_path, progress=False).ok
    ex = FakeExecutor()  # the same units planned on a CPU
    report = runner.run_units(plan(), ex, tmp_path, progress=False)
    assert len(ex.calls) == len(units) and report.reused == [] and len(report.moved) == len(units)
    assert report.resume_counts()["moved_aside_reasons"] == {"made on another device": len(units)}
    assert "made on cuda:0, this run is on cpu" in next(iter(report.moved_why.values()))
    assert all(json.loads(p.read_text())["device"] == "cuda:0" for p in report.moved)  # kept, in units/stale/
    again = FakeExecutor()
    assert len(runner.run_units(plan(), again, tmp_path, progress=False).reused) == len(units) and again.calls == []


def test_a_full_disk_part_way_through_the_tables_leaves_the_earlier_set_whole(tmp_path, monkeypatch):
    # the four files were replaced one by one: ENOSPC (or Ctrl-C) on the Markdown left this run's
    # JSON beside the Markdown, CSV and LaTeX of an earlier run under other settings
    import errno

    from benchmark.run.table_derive import derive_table
    from benchmark.run.writers import FORMATS, write_table
    from fake_units import FakeExecutor, meta, plan, table_spec

    def table(seed):
        units = plan(seed=seed)
        return derive_table(table_spec(), [FakeExecutor()(u) for u in units], {**meta(units), "seed": seed})

    write_table(table(0), tmp_path)
    before = {f: (tmp_path / f"table1.{f}").read_bytes() for f in FORMATS}
    real_fsync = os.fsync

    def full(fd):
        if ".table1.md." in os.readlink(f"/proc/self/fd/{fd}"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_fsync(fd)

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError, match="table1.md"):
        write_table(table(1), tmp_path)
    assert {f: (tmp_path / f"table1.{f}").read_bytes() for f in FORMATS} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f"table1.{f}" for f in FORMATS)  # no temp file
    monkeypatch.setattr(os, "fsync", real_fsync)
    write_table(table(1), tmp_path)
    assert json.loads((tmp_path / "table1.json").read_text())["seed"] == 1


def test_units_made_with_other_torch_threads_are_another_computation():
    # Ray's --cpus-per-unit 2 fits each unit with 2 torch threads: table1 smoke, no-prior, 10000 pts /
    # 5 fps gave an MPJPE sum of 2.653 m against 2.935 m with 1 thread, and a resume across the two
    # mixed them in one table (the thread count was in no spec)
    from benchmark.run.backends import ProcessBackend, RayBackend, backend_threads, serial_backend
    from fake_units import plan, plan_units, profile, table_spec

    one = plan()
    assert "torch_threads" not in one[0].spec  # one thread: the spec and the stored hashes as before
    two = plan_units(table_spec(), profile(batch_sequences=2), [u.prior for u in one[:1]], ["s0", "s1", "s2"], 0, "cpu",
                     {one[0].prior: {}}, threads=2)
    same = [u for u in one if u.prior == one[0].prior]
    assert [u.unit_id for u in two] == [u.unit_id for u in same]
    assert all(a.spec_hash != b.spec_hash and b.spec["torch_threads"] == 2 for a, b in zip(same, two))
    assert backend_threads(ProcessBackend(2)) == 1
    import torch

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)  # the serial backend runs units in this process, with its threads
        assert backend_threads(serial_backend) == 1
        torch.set_num_threads(2)
        assert backend_threads(serial_backend) == 2
    finally:
        torch.set_num_threads(before)
    assert backend_threads(RayBackend(cpus_per_unit=2)) == 2 and backend_threads(RayBackend(cpus_per_unit=0.5)) == 1


def test_a_mistaken_rerun_stopped_at_once_does_not_cost_the_finished_units(tmp_path, capsys):
    # `run --seed 1` into a folder of seed-0 results, Ctrl-C at once: every seed-0 unit had gone to
    # units/stale/ and the right command (--seed 0) computed them all again
    from benchmark.run import runner
    from fake_units import FakeExecutor, plan

    class CtrlC(FakeExecutor):
        def __call__(self, unit):
            raise KeyboardInterrupt

    first = runner.run_units(plan(seed=0), FakeExecutor(), tmp_path, progress=False)
    with pytest.raises(KeyboardInterrupt):
        runner.run_units(plan(seed=1), CtrlC(), tmp_path, progress=False)
    assert not list((tmp_path / "units").glob("*.json"))  # all moved aside
    capsys.readouterr()
    ex = FakeExecutor()
    again = runner.run_units(plan(seed=0), ex, tmp_path, progress=False)
    assert ex.calls == [] and again.results == first.results and len(again.restored) == len(first.results)
    assert f"{len(first.results)} reused (of them {len(first.results)} taken back from units/stale/)" in capsys.readouterr().out
    seed0 = {u.spec_hash for u in plan(seed=0)}
    assert not [p for p in (tmp_path / "units" / "stale").glob("*.json") if json.loads(p.read_text())["spec_hash"] in seed0]


def test_alternating_settings_in_one_folder_swap_their_units_instead_of_recomputing(tmp_path):
    from benchmark.run import runner
    from fake_units import FakeExecutor, plan

    runner.run_units(plan(seed=0), FakeExecutor(), tmp_path, progress=False)
    runner.run_units(plan(seed=1), FakeExecutor(), tmp_path, progress=False)
    for seed in (0, 1, 0):
        ex = FakeExecutor()
        report = runner.run_units(plan(seed=seed), ex, tmp_path, progress=False)
        assert ex.calls == [] and len(report.restored) == len(report.results) == len(plan())
    edited = next((tmp_path / "units" / "stale").glob("*.json"))  # a stale copy edited by hand is not taken back
    record = json.loads(edited.read_text())
    record["per_sequence"][0]["frames"] += 1
    edited.write_text(json.dumps(record))
    ex = FakeExecutor()
    report = runner.run_units(plan(seed=1), ex, tmp_path, progress=False)
    assert len(ex.calls) == 1 and len(report.restored) == len(plan()) - 1
