"""Slow: a two-node Ray cluster on this machine (loopback only), started the way a user starts one
(``ray start --head`` and ``ray start --address``), runs the smoke inbetween table for six
priors across both nodes; the stored metrics must be bit-identical to a serial local run.
Prints units per second of both runs (``python -m pytest -m slow tests/test_ray_cluster.py -s``).

Teardown stops only the Ray processes this test started: they are found by the unique temporary
folder given to ``ray start`` (never ``ray stop``, which would stop every Ray on the machine).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import pytest

from benchmark.run.backends import RayBackend
from benchmark.run.catalog import get_profile, load_table_spec
from benchmark.run import table_run

ROOT = Path(__file__).resolve().parents[1]
TABLE = "inbetween"
PRIORS = ["slerp", "no-prior", "vposer-slerp", "hmvae", "structured-latent", "motion-dvae"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ray_cli() -> str:
    exe = shutil.which("ray") or str(Path(os.sys.executable).with_name("ray"))
    if not Path(exe).exists():
        pytest.skip("the 'ray' command is not installed: pip install -e '.[ray]'")
    return exe


def _our_ray_processes(marker: str) -> list[int]:
    import psutil

    pids = []
    for proc in psutil.process_iter(["pid", "cmdline"]):
        try:
            if any(marker in part for part in proc.info["cmdline"] or []):
                pids.append(proc.info["pid"])
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return pids


@pytest.fixture
def two_node_cluster():
    pytest.importorskip("ray")
    exe = _ray_cli()
    temp_dir = tempfile.mkdtemp(prefix="rb16-")  # short: Ray's socket paths must stay under 108 bytes
    port = _free_port()
    # Ray >= 2.59 starts 'ray start' clusters with token authentication: every node and the driver
    # use the token file (~/.ray/auth_token, created by the first local start when missing)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "RAY_USAGE_STATS_ENABLED": "0",
           "RAY_AUTH_MODE": "token", "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tests")])}
    if not Path("~/.ray/auth_token").expanduser().exists():
        subprocess.run([exe, "get-auth-token", "--generate"], env=env, capture_output=True, timeout=60)
    common = ["--num-cpus", "1", "--node-ip-address", "127.0.0.1", "--temp-dir", temp_dir, "--disable-usage-stats"]
    try:
        subprocess.run([exe, "start", "--head", "--port", str(port), "--include-dashboard", "false", *common],
                       check=True, env=env, cwd=ROOT, capture_output=True, text=True, timeout=180)
        subprocess.run([exe, "start", "--address", f"127.0.0.1:{port}", *common],
                       check=True, env=env, cwd=ROOT, capture_output=True, text=True, timeout=180)
        yield f"127.0.0.1:{port}", env
    except subprocess.CalledProcessError as exc:
        pytest.fail(f"ray start failed: {exc.stderr or exc.stdout}")
    finally:
        for pid in _our_ray_processes(temp_dir):
            try:
                os.kill(pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        time.sleep(2)
        for pid in _our_ray_processes(temp_dir):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        shutil.rmtree(temp_dir, ignore_errors=True)


class RecordNode:
    """Wraps the table executor; each result names the Ray node that computed it."""

    def __init__(self, execute):
        self.execute = execute

    def unit_cost(self, unit):
        return self.execute.unit_cost(unit)

    def __call__(self, unit):
        import ray

        result = self.execute(unit)
        result["ray_node"] = ray.get_runtime_context().get_node_id()
        return result


def _run(spec, body, out, backend):
    t0 = time.perf_counter()
    result = table_run.run_table(spec, get_profile("smoke", table=TABLE), priors=PRIORS, body=body,
                                 device="cpu", seed=0, out_dir=out, backend=backend)
    assert not result["failures"], result["failures"]
    return time.perf_counter() - t0


def _numbers(out: Path) -> dict:
    return {p.stem: {k: json.loads(p.read_text())[k] for k in ("fingerprint", "na_reason", "per_sequence")}
            for p in sorted((out / "units").glob("*.json"))}


@pytest.mark.slow
def test_two_node_cluster_matches_local(two_node_cluster, tmp_path, anny_body):
    """The cluster run's driver is a separate process (as a user's would be: Ray reads its
    authentication settings when it is imported)."""
    address, env = two_node_cluster
    spec = load_table_spec(TABLE)
    local_s = _run(spec, anny_body, tmp_path / "local", "local")
    proc = subprocess.run([os.sys.executable, __file__, str(tmp_path / "cluster"), address], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stderr[-4000:]
    cluster_s = float(proc.stdout.strip().splitlines()[-1])
    local, cluster = _numbers(tmp_path / "local"), _numbers(tmp_path / "cluster")
    assert local and local == cluster  # bit-identical
    nodes = {json.loads(p.read_text())["ray_node"] for p in (tmp_path / "cluster" / "units").glob("*.json")}
    assert len(nodes) == 2, f"units ran on {len(nodes)} node(s), not both"
    n = len(local)
    print(f"\n{TABLE} smoke, {n} units: local serial {local_s:.1f} s ({n / local_s:.2f} units/s), "
          f"two-node Ray cluster (1 CPU per node; driver start, Ray connection and body load included) "
          f"{cluster_s:.1f} s ({n / cluster_s:.2f} units/s)")


def _cluster_driver(out: str, address: str) -> None:
    """Run the table on the cluster at ``address``, each unit recording its node; print the wall time."""
    import ray

    from benchmark.body import get_body

    t0 = time.perf_counter()
    ray.init(address=address)
    deadline = time.monotonic() + 60
    while sum(1 for n in ray.nodes() if n["Alive"]) < 2:
        assert time.monotonic() < deadline, f"the second node did not join: {ray.nodes()}"
        time.sleep(0.5)
    real = table_run.TableExecutor
    table_run.TableExecutor = lambda *a: RecordNode(real(*a))
    _run(load_table_spec(TABLE), get_body("anny"), Path(out), RayBackend(address=address))
    ray.shutdown()
    print(time.perf_counter() - t0)


if __name__ == "__main__":
    _cluster_driver(os.sys.argv[1], os.sys.argv[2])
