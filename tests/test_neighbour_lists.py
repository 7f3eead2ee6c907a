"""Neighbour lists kept across a fit's steps (benchmark/metrics/neighbour_lists.py) answer exactly
what a search answers: checked against a KD-tree over moves of every size, padded batches, elements
with fewer points than a list holds, and through StaticChamfer's value and gradient."""

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from benchmark.metrics import grid_nn
from benchmark.metrics import neighbour_lists as nl
from benchmark.metrics import static_chamfer as sc

pytestmark = pytest.mark.skipif(not grid_nn.HAVE_NUMBA, reason="the lists are compiled with numba")


def _nearest(points, n_points, queries):
    return cKDTree(points[:n_points]).query(queries)[1]


def _moves(rng, shape, steps):
    """A trajectory: large jumps at every step (the lists die young and are given up for a while),
    then small drifts with a jump now and then (they hold, and are remade after a jump)."""
    x = rng.normal(size=shape)
    for step in range(steps):
        x = x + rng.normal(size=shape) * (0.5 if step < 12 or step % 15 == 3 else 0.002)
        yield step, x


def test_moving_queries_against_fixed_points_are_exact():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(4, 400, 3))
    lengths = np.array([400, 399, 5, 1])  # 5 and 1 points: fewer than a list holds
    qlengths = np.array([250, 1, 250, 249])
    lists = nl.MovingQueryLists(points, lengths)
    searched = []
    for step, q in _moves(rng, (4, 250, 3), 60):
        out = np.full((4, 250), -1, dtype=np.int64)
        left = lists.nearest(q, qlengths, out)
        for n in left:  # the caller searches these elements
            out[n, : qlengths[n]] = _nearest(points[n], lengths[n], q[n, : qlengths[n]])
        searched.append(len(left))
        for n in range(4):
            assert (out[n, : qlengths[n]] == _nearest(points[n], lengths[n], q[n, : qlengths[n]])).all(), (step, n)
            assert (out[n, qlengths[n]:] == -1).all()
    assert searched[0] == 4  # the first lists are made after a few calls: searched until then
    assert searched[-1] == 0  # jumps: searched for a while; small drifts: from the lists


def test_fixed_queries_against_moving_points_are_exact():
    rng = np.random.default_rng(1)
    queries = rng.normal(size=(3, 500, 3))
    qlengths = np.array([500, 2, 480])
    plengths = np.array([300, 300, 7])
    lists = nl.FixedQueryLists(queries, qlengths)
    searched = []
    for step, p in _moves(rng, (3, 300, 3), 60):
        out = np.full((3, 500), -1, dtype=np.int64)
        left, whole = lists.nearest(p, plengths, out)
        for n, rows in left:
            assert (out[n, rows] == -1).all()
            out[n, rows] = _nearest(p[n], plengths[n], queries[n, rows])
        for n in whole:
            out[n, : qlengths[n]] = _nearest(p[n], plengths[n], queries[n, : qlengths[n]])
        searched.append(sum(r.shape[0] for _, r in left) + sum(int(qlengths[n]) for n in whole))
        for n in range(3):
            assert (out[n, : qlengths[n]] == _nearest(p[n], plengths[n], queries[n, : qlengths[n]])).all(), (step, n)
    assert searched[-1] < 0.1 * qlengths.sum() < max(searched)  # jumps: searched; small drifts: mostly from the lists


def test_new_point_counts_remake_the_lists():
    rng = np.random.default_rng(2)
    queries = rng.normal(size=(2, 100, 3))
    lists = nl.FixedQueryLists(queries, np.array([100, 100]))
    for m in (50, 40):
        for call in range(2 * nl.MIN_LIFE + 1):  # searched whole until the first lists are made
            p = rng.normal(size=(2, m, 3)) * 1e-3 + np.linspace(0, 1, m)[None, :, None]
            out = np.full((2, 100), -1, dtype=np.int64)
            left, whole = lists.nearest(p, np.array([m, m]), out)
            assert (whole == [0, 1]) == (call < 2 * nl.MIN_LIFE - 1)  # new points: no lists until then
            for n, rows in left:
                out[n, rows] = _nearest(p[n], m, queries[n, rows])
            for n in whole:
                out[n] = _nearest(p[n], m, queries[n])
            for n in range(2):
                assert (out[n] == _nearest(p[n], m, queries[n])).all()


def test_static_chamfer_gives_the_same_loss_and_gradient_with_and_without_lists(monkeypatch):
    g = torch.Generator().manual_seed(3)
    b = torch.randn(6, 3000, 3, generator=g)
    bl = torch.tensor([3000, 2999, 100, 7, 3000, 1])
    a0 = torch.randn(6, 800, 3, generator=g)
    al = torch.tensor([800, 799, 800, 800, 3, 800])
    results = {}
    for use in (False, True):
        monkeypatch.setattr(sc, "USE_NEIGHBOUR_LISTS", use)
        loss_fn, a, out = sc.StaticChamfer(b, bl), a0.clone(), []
        for step in range(12):
            a = a + (0.3 if step == 6 else 0.003) * torch.randn(a.shape, generator=torch.Generator().manual_seed(step))
            x = a.clone().requires_grad_(True)
            loss = loss_fn(x, al, reduction="sum")
            loss.backward()
            out.append((loss.detach(), x.grad))
        results[use] = out
    for (v0, g0), (v1, g1) in zip(results[False], results[True]):
        assert torch.equal(v0, v1) and torch.equal(g0, g1)


def test_perf_lists_part_is_wired_and_prints_both_forms(monkeypatch, tmp_path):
    """``perf --only lists`` runs benchmark.tools.perf_lists (a whole quick unit: minutes, so it is
    replaced here by its result's shape) and prints the grids' and the lists' seconds side by side."""
    from benchmark.tools import perf, perf_lists

    result = {"prior": "no-prior", "cell": "10000/5", "sequences": 8, "grids_s": 10.0, "lists_s": 4.0, "ratio": 0.4,
              "windows": [{"step": 50, "grids": 6.0, "lists": 3.0, "calls": 60},
                          {"step": None, "grids": 4.0, "lists": 1.0, "calls": 40}]}
    monkeypatch.setattr(perf_lists, "lists_compare", lambda: result)
    report = perf.run_perf(out=tmp_path / "perf", parts=["lists"])
    text = (tmp_path / "perf" / "perf.md").read_text()
    assert report["lists"] is result
    assert "| 50 | 60 | 6.00 | 3.00 | 0.50 |" in text and "| all | | 10.0 | 4.0 | 0.40 |" in text
