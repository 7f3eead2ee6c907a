"""``python -m benchmark fit-check``: the completion fit of no-prior against its targets (issue 11).

The run itself is slow (4 quick sequences at 10,000 points / 10 fps, the table1 v2 schedule), so it
is behind the ``slow`` marker; the default suite checks the command's argument errors."""

import re
import subprocess
import sys

import pytest

from benchmark.tools.fit_check import TARGETS


def _cli(*args, timeout=3000):
    return subprocess.run([sys.executable, "-m", "benchmark", *args], capture_output=True, text=True, timeout=timeout)


def test_fit_check_refuses_a_cell_outside_the_grid(tmp_path):
    r = _cli("fit-check", "--points", "500", "--out", str(tmp_path / "fc"), timeout=300)
    assert r.returncode == 2
    assert "--points 500 / --fps 10 is not a table1 cell" in r.stderr


def test_fit_check_refuses_an_unknown_prior(tmp_path):
    r = _cli("fit-check", "--prior", "no-such-prior", "--out", str(tmp_path / "fc"), timeout=300)
    assert r.returncode == 2 and "no-such-prior" in r.stderr


@pytest.fixture(scope="module")
def fit_check_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("fit_check")
    r = _cli("fit-check", "--out", str(out))
    rows = dict(re.findall(r"^(\w+)\s+\S+\s+<= \S+\s+(ok|FAIL)$", r.stdout, flags=re.M))
    return r, rows


@pytest.mark.slow
def test_fit_check_faces_every_sequence_the_right_way_and_converges(fit_check_run):
    r, rows = fit_check_run
    assert r.returncode in (0, 1), r.stderr[-2000:]
    assert set(rows) == set(TARGETS), r.stdout[-3000:]
    for name in ("root_err_deg_max", "backwards", "not_converged"):
        assert rows[name] == "ok", r.stdout[-3000:]


@pytest.mark.slow
@pytest.mark.xfail(strict=False, reason="issue 11: no-prior at 10,000 pts / 10 fps reaches MPJPE ~45 mm and vertex "
                                        "Chamfer ~17.5 mm (targets 40 and 12): limb local minima of the per-frame fit")
def test_fit_check_meets_every_target(fit_check_run):
    r, rows = fit_check_run
    assert r.returncode == 0, r.stdout[-3000:]
