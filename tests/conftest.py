import os
import sys

import pytest
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

# Under pytest-xdist (the default: ``-n auto`` in pyproject.toml) each worker process runs on one
# torch thread, so that the workers share the cores instead of oversubscribing them; a run without
# workers (``-n 0``) uses up to two threads.
IN_WORKER = bool(os.environ.get("PYTEST_XDIST_WORKER"))
torch.set_num_threads(1 if IN_WORKER else max(1, min(2, torch.get_num_threads())))

MAX_WORKERS = 4  # each worker holds its own body model and data (about 1-2 GB): more cores than this gain little
# Test files that start Ray (a local runtime, or a two-node cluster with `ray start`) run on one
# worker, one after the other (``--dist loadgroup``), so that two Ray runtimes (and their signal
# tests) never start at once on one machine.
RAY_TEST_FILES = ("test_backends.py", "test_ray_cluster.py", "test_signals.py")
# The committed quick tables (``-m slow``) run one after the other too: each runs its units on every
# core (``--jobs`` = the cores), and an sls unit can hold several GB.
SERIAL_GROUPS = {**{f: "ray" for f in RAY_TEST_FILES}, "test_quick_tables.py": "quick-tables"}


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: the machine's cores, at most MAX_WORKERS."""
    return max(1, min(MAX_WORKERS, os.cpu_count() or 1))


def pytest_collection_modifyitems(config, items):
    for item in items:
        group = SERIAL_GROUPS.get(os.path.basename(str(item.fspath)))
        if group:
            item.add_marker(pytest.mark.xdist_group(name=group))


@pytest.fixture(scope="session")
def anny_body():
    """The embedded body, built once per test session."""
    from benchmark.body.anny_body import load_anny_body

    return load_anny_body("cpu")


def pytest_addoption(parser):
    parser.addoption(
        "--update-goldens", action="store_true", default=False,
        help="rewrite the committed reference tables under results/ (never in CI)",
    )


@pytest.fixture
def update_goldens(request):
    flag = request.config.getoption("--update-goldens")
    if flag and os.environ.get("CI"):
        raise RuntimeError("--update-goldens is refused under CI: goldens change only by an explicit local run")
    return flag
