import os
import sys

import pytest
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

torch.set_num_threads(max(1, min(2, torch.get_num_threads())))


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
