"""Resume never mixes data: unit checksums, content hashes of the motion data and the weights in the
spec hash, the resume counts, the --out lock, file modes, and SIGKILL-then-rerun bit-identity."""

from __future__ import annotations

import json
import os
import signal
import socket
import stat
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmark.run import runner
from benchmark.core.outdir import OutDirError, OutDirLock, check_out_dir
from benchmark.core.json_io import atomic_write_json
from benchmark.data.unit_arrays import write_arrays
from benchmark.core.work_units import checksum_problem, plan_units, unit_checksum, unit_path
from fake_units import FakeExecutor, plan, profile, table_spec
from tiny_run import tiny_table1, write_motion

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------------------
# checksums


def test_stored_units_carry_their_checksum_and_an_edited_one_is_moved_aside(tmp_path, capsys):
    units = plan(priors=["p"])
    runner.run_units(units, FakeExecutor(), tmp_path, progress=False)
    path = unit_path(tmp_path, units[2].unit_id)
    record = json.loads(path.read_text())
    assert record["checksum"] == unit_checksum(record) and checksum_problem(record) is None
    original = path.read_text()
    record["per_sequence"][0]["sums"]["chamfer_m"] *= 2  # "its Chamfer sum doubled", by hand
    path.write_text(json.dumps(record, indent=1))
    capsys.readouterr()

    ex = FakeExecutor()
    report = runner.run_units(units, ex, tmp_path, progress=False)
    assert ex.calls == [units[2].unit_id] and len(report.reused) == len(units) - 1
    assert "checksum mismatch" in report.moved_why[units[2].unit_id]
    moved = tmp_path / "units" / "stale" / f"{units[2].unit_id}.{units[2].spec_hash[:8]}.json"
    assert json.loads(moved.read_text())["per_sequence"][0]["sums"]["chamfer_m"] == record["per_sequence"][0]["sums"]["chamfer_m"]
    assert path.read_text() == original  # recomputed: the same bytes as the first run
    line = capsys.readouterr().out
    assert f"{len(units) - 1} reused, 1 to compute, 1 stored file(s) moved aside to units/stale/ (1 checksum mismatch)" in line
    counts = report.resume_counts()
    assert counts["reused"] == len(units) - 1 and counts["recomputed"] == 1 and counts["moved_aside"] == 1
    assert counts["moved_aside_reasons"] == {"checksum mismatch": 1}


def test_a_unit_file_without_checksum_is_not_trusted(tmp_path):
    units = plan(priors=["p"])
    runner.run_units(units, FakeExecutor(), tmp_path, progress=False)
    path = unit_path(tmp_path, units[0].unit_id)
    record = json.loads(path.read_text())
    del record["checksum"]
    path.write_text(json.dumps(record))
    ex = FakeExecutor()
    report = runner.run_units(units, ex, tmp_path, progress=False, announce=False)
    assert ex.calls == [units[0].unit_id] and "no checksum" in report.moved_why[units[0].unit_id]


# ------------------------------------------------------------------------------------------------
# what enters the spec hash


def test_data_hashes_enter_the_spec_of_the_batches_that_read_them():
    seqs = ["s0", "s1", "s2"]
    hashes = {s: f"h{s}" for s in seqs}
    a = plan_units(table_spec(), profile(batch_sequences=2), ["p"], seqs, 0, "cpu", {"p": {}}, data_hashes=hashes)
    b = plan_units(table_spec(), profile(batch_sequences=2), ["p"], seqs, 0, "cpu", {"p": {}},
                   data_hashes=dict(hashes, s2="other"))
    assert a[0].spec["data"] == ["hs0", "hs1"] and a[1].spec["data"] == ["hs2"]
    changed = {x.unit_id for x, y in zip(a, b) if x.spec_hash != y.spec_hash}
    assert changed == {u.unit_id for u in a if "s2" in u.sequence_ids}  # only batch 1 of every cell
    with pytest.raises(ValueError, match="no content hash for sequence"):
        plan_units(table_spec(), profile(), ["p"], seqs, 0, "cpu", {"p": {}}, data_hashes={"s0": "x"})
    # without data hashes the recipe is unchanged (the spec has no "data" key)
    assert "data" not in plan(priors=["p"])[0].spec


def test_motion_hash_follows_content_not_name(tmp_path):
    from benchmark.core.motion import Motion
    from benchmark.run.table_run import motion_sha256

    a = Motion.load(write_motion(tmp_path / "a.npz", seed=0))
    again = Motion.load(write_motion(tmp_path / "copy" / "a.npz", seed=0))
    other = Motion.load(write_motion(tmp_path / "b.npz", seed=1))
    assert motion_sha256(a) == motion_sha256(again) != motion_sha256(other)
    nudged = Motion(poses=a.poses.clone(), trans=a.trans.clone(), timestamps=a.timestamps, source=a.source, meta=a.meta)
    nudged.trans[5, 0] += 1e-6
    assert motion_sha256(nudged) != motion_sha256(a)


def test_weights_content_hash_covers_embedded_and_given_files(tmp_path):
    import hashlib

    from benchmark.run.registry import make_adapter, weights_content_sha256

    src = ROOT / "priors" / "weights" / "vposer.pt"
    copy = tmp_path / "vposer.pt"
    copy.write_bytes(src.read_bytes())
    embedded = make_adapter("vposer-slerp")
    given = make_adapter("vposer-slerp", weights=str(copy))
    expect = hashlib.sha256(b"vposer.pt\0" + src.read_bytes()).hexdigest()
    assert weights_content_sha256(embedded) == weights_content_sha256(given) == expect
    assert weights_content_sha256(make_adapter("no-prior")) is None


# ------------------------------------------------------------------------------------------------
# end to end through the CLI: replaced data is recomputed, the counts are in the provenance


def test_replaced_motion_under_the_same_name_is_recomputed_not_mixed(tmp_path, monkeypatch, capsys):
    from benchmark.cli import main

    tiny_table1(monkeypatch)
    data, out = tmp_path / "data", tmp_path / "out"
    write_motion(data / "walk.npz", seed=0)
    argv = ["run", "table1", "--prior", "no-prior", "--data", str(data), "--out", str(out)]
    assert main(argv) == 0
    first = json.loads((out / "table1.json").read_text())
    assert first["provenance"]["resume"]["recomputed"] == 1 and first["provenance"]["resume"]["reused"] == 0
    capsys.readouterr()

    assert main(argv) == 0  # same inputs: reused
    again = json.loads((out / "table1.json").read_text())
    assert again["provenance"]["resume"] == dict(first["provenance"]["resume"], reused=1, recomputed=0, ran=0)
    assert again["rows"] == first["rows"]
    assert "1 reused, 0 to compute, 0 stored file(s) moved aside" in capsys.readouterr().out

    write_motion(data / "walk.npz", seed=7, scale=0.6, speed=2.0)  # another motion, same file name
    assert main(argv) == 0
    third = json.loads((out / "table1.json").read_text())
    assert third["provenance"]["resume"]["reused"] == 0 and third["provenance"]["resume"]["moved_aside"] == 1
    assert third["provenance"]["resume"]["moved_aside_reasons"] == {"spec hash differs": 1}
    assert "0 reused, 1 to compute, 1 stored file(s) moved aside" in capsys.readouterr().out
    assert third["rows"][0]["cells"][0]["mpjpe_mm"] != first["rows"][0]["cells"][0]["mpjpe_mm"]
    assert sorted(p.suffix for p in (out / "units" / "stale").iterdir()) == [".json", ".npz"]  # with its fitted motions
    assert not (out / ".lock").exists()  # released


# ------------------------------------------------------------------------------------------------
# --out: checks and the lock


def test_check_out_dir_creates_and_refuses(tmp_path):
    assert check_out_dir(tmp_path / "a" / "b").is_dir()
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutDirError, match="is a file"):
        check_out_dir(tmp_path / "f")
    with pytest.raises(OutDirError, match="only .* MiB free"):
        check_out_dir(tmp_path / "a", min_free_bytes=1 << 62)
    assert [p.name for p in (tmp_path / "a" / "b").iterdir()] == []  # the write probe is gone


def _holder(out: Path, seconds: float) -> subprocess.Popen:
    code = textwrap.dedent(f"""
        import sys, time
        from benchmark.core.outdir import OutDirLock
        with OutDirLock({str(out)!r}, command="holder"):
            print("locked", flush=True)
            time.sleep({seconds})
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_a_second_run_into_the_same_out_is_refused_naming_the_other(tmp_path, capsys):
    from benchmark.cli import main

    out = tmp_path / "out"
    out.mkdir()
    proc = _holder(out, 30)
    try:
        assert main(["run", "table1", "--prior", "no-prior", "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"error: --out {out}: another run is writing there (pid {proc.pid} on host ")
        assert "(holder)" in err and len(err.splitlines()) == 1
    finally:
        proc.kill()
        proc.wait()


def test_a_stale_lock_of_a_dead_process_is_taken_over(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    proc = _holder(out, 30)
    proc.send_signal(signal.SIGKILL)  # the lock stays behind, like a killed run's
    proc.wait()
    assert json.loads((out / ".lock").read_text())["pid"] == proc.pid
    with OutDirLock(out) as lock:
        assert lock.took_over["pid"] == proc.pid
        assert json.loads((out / ".lock").read_text())["pid"] == os.getpid()
    assert not (out / ".lock").exists()
    assert f"taking over a stale lock in {out} (pid {proc.pid}" in capsys.readouterr().out


def test_a_lock_from_another_host_is_refused(tmp_path):
    (tmp_path / ".lock").write_text(json.dumps({"pid": 1, "host": socket.gethostname() + "-elsewhere", "started": 0}))
    with pytest.raises(OutDirError, match="delete .*\\.lock"):
        OutDirLock(tmp_path).acquire()


# ------------------------------------------------------------------------------------------------
# file modes


@pytest.mark.parametrize("mask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_files_follow_the_umask(tmp_path, mask, mode):
    old = os.umask(mask)
    try:
        atomic_write_json(tmp_path / "t.json", {"a": 1})
        write_arrays(tmp_path / "t.npz", {"x": np.zeros(2)})  # a unit's fitted motions, as its JSON
        units = plan(priors=["p"])[:1]
        runner.run_units(units, FakeExecutor(), tmp_path / "run", progress=False, announce=False)
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "t.json").stat().st_mode) == mode
    assert stat.S_IMODE((tmp_path / "t.npz").stat().st_mode) == mode
    assert stat.S_IMODE(unit_path(tmp_path / "run", units[0].unit_id).stat().st_mode) == mode


# ------------------------------------------------------------------------------------------------
# SIGKILL at any point, then rerun: the same table, bit for bit

_KILL_SCRIPT = textwrap.dedent("""
    import json, sys, time
    sys.path[:0] = [{root!r}, {tests!r}]
    from benchmark.run import runner
    from benchmark.run.table_derive import derive_table
    from benchmark.run.writers import write_table
    from fake_units import FakeExecutor, meta, plan, table_spec

    out, delay = sys.argv[1], float(sys.argv[2])
    ex = FakeExecutor()

    def slow(unit):
        time.sleep(delay)
        return ex(unit)

    units = plan()
    report = runner.run_units(units, slow, out, progress=False, announce=False)
    table = derive_table(table_spec(), report.results.values(), meta(units))
    write_table(table, out)
    print(len(report.reused), len(report.ran), flush=True)
""")


def _comparable(out: Path) -> str:
    table = json.loads((out / "table1.json").read_text())
    table["provenance"].pop("timings", None)  # wall-clock facts of the run, not results
    return json.dumps(table, sort_keys=True)


def test_sigkill_at_any_point_then_rerun_gives_the_same_table(tmp_path):
    script = tmp_path / "run.py"
    script.write_text(_KILL_SCRIPT.format(root=str(ROOT), tests=str(ROOT / "tests")))
    cmd = [sys.executable, str(script)]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    ref = tmp_path / "ref"
    subprocess.run(cmd + [str(ref), "0"], cwd=ROOT, check=True, env=env, capture_output=True)
    for i, after in enumerate((1, 17, 35)):  # killed after that many unit files: early, mid-run, late
        out = tmp_path / f"killed{i}"
        proc = subprocess.Popen(cmd + [str(out), "0.03"], cwd=ROOT, env=env, stdout=subprocess.PIPE)
        deadline = time.monotonic() + 60
        while len(list((out / "units").glob("*.json"))) < after and time.monotonic() < deadline:
            time.sleep(0.002)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        stored = len(list((out / "units").glob("*.json")))
        assert after <= stored < 36 and not (out / "table1.json").exists()
        done = subprocess.run(cmd + [str(out), "0"], cwd=ROOT, check=True, env=env, capture_output=True, text=True)
        reused, ran = map(int, done.stdout.split())
        assert reused == stored and reused + ran == 36
        assert _comparable(out) == _comparable(ref)
        for f in (out / "units").glob("*.json"):  # every stored unit is byte-identical to the reference's
            assert f.read_bytes() == (ref / "units" / f.name).read_bytes()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/fd")
def test_a_full_disk_while_writing_names_the_file(tmp_path, monkeypatch, capsys):
    """ENOSPC in the middle of writing the tables: one line naming the file and the fix."""
    import errno

    from benchmark.cli import main

    tiny_table1(monkeypatch)
    write_motion(tmp_path / "data" / "a.npz")
    real_fsync = os.fsync

    def full(fd):
        if ".table1.md." in os.readlink(f"/proc/self/fd/{fd}"):  # the temp file of table1.md
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_fsync(fd)

    monkeypatch.setattr(os, "fsync", full)
    rc = main(["run", "table1", "--prior", "no-prior", "--data", str(tmp_path / "data"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err == (f"error: {tmp_path / 'o' / 'table1.md'}: No space left on device; free some space or "
                               "choose another folder")
    assert not list((tmp_path / "o").glob(".table1.md.*"))  # no temp file left behind


def test_onnx_is_a_normal_dependency():
    """export-onnx works after a plain ``pip install -e .``: onnx is in the project's dependencies,
    not only in an extra."""
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    names = {d.split(">")[0].split("=")[0].split("<")[0].strip() for d in project["dependencies"]}
    assert {"onnx", "onnxruntime"} <= names


_CLI_SCRIPT = textwrap.dedent("""
    import sys
    sys.path[:0] = [{root!r}, {tests!r}]
    import pytest
    from tiny_run import tiny_table1
    from benchmark.cli import main

    if __name__ == "__main__":  # worker processes (spawn) re-import this script
        mp = pytest.MonkeyPatch()
        tiny_table1(mp, fps=(5, 10))
        sys.exit(main(["run", "table1", "--prior", "no-prior", "--prior", "vposer-slerp", "--data", sys.argv[1],
                       "--out", sys.argv[2]]))
""")


@pytest.mark.slow
def test_sigkill_through_the_cli_then_rerun_gives_the_same_table(tmp_path):
    """The real protocol (shrunk): a run killed after its first unit file, rerun into the same --out
    (taking over the dead run's lock), gives the rows and CSV of an uninterrupted run, bit for bit."""
    script = tmp_path / "run.py"
    script.write_text(_CLI_SCRIPT.format(root=str(ROOT), tests=str(ROOT / "tests")))
    data = tmp_path / "data"
    write_motion(data / "a.npz", seed=0, speed=1.0)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    ref, out = tmp_path / "ref", tmp_path / "killed"
    subprocess.run([sys.executable, str(script), str(data), str(ref)], cwd=ROOT, env=env, check=True, capture_output=True)
    proc = subprocess.Popen([sys.executable, str(script), str(data), str(out)], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while not list((out / "units").glob("*.json")) and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert (out / ".lock").exists() and 1 <= len(list((out / "units").glob("*.json"))) < 4
    done = subprocess.run([sys.executable, str(script), str(data), str(out)], cwd=ROOT, env=env, check=True,
                          capture_output=True, text=True)
    assert "taking over a stale lock" in done.stdout
    a, b = (json.loads((d / "table1.json").read_text()) for d in (ref, out))

    def results(table):  # every cell without its measured seconds (wall-clock facts, not results)
        return [[{k: v for k, v in c.items() if k not in ("fit_s", "eval_s")} for c in r["cells"]] for r in table["rows"]]

    assert results(a) == results(b) and b["provenance"]["resume"]["reused"] >= 1
    assert (ref / "table1.csv").read_bytes() == (out / "table1.csv").read_bytes()
