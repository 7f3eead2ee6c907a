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


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: the machine's cores, at most MAX_WORKERS. The tests of one file run on one
    worker, one after the other (``--dist loadfile`` in pyproject.toml), so that a file's
    module-scoped fixture (a smoke table run, a trained model) is built once, and the committed
    quick tables of ``-m slow`` (one file, each table on every core) never run at once."""
    return max(1, min(MAX_WORKERS, os.cpu_count() or 1))


@pytest.fixture(scope="session")
def anny_body():
    """The embedded body, built once per test session."""
    from benchmark.body.anny_body import load_anny_body

    return load_anny_body("cpu")


@pytest.fixture
def brief_searches(monkeypatch):
    """The facing and limb start searches cut to a few steps per hypothesis, for the tests of what
    surrounds a search (its caches, its plumbing, a command's path), not of what it finds."""
    from benchmark.protocols import facing, start_search

    monkeypatch.setattr(start_search, "START_SEARCH_STEPS", (2, 3))
    monkeypatch.setattr(facing, "FACING_STEPS", (2, 3))


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
