"""The soft-min Chamfer of the start search (benchmark.metrics.soft_chamfer): within its bounds of
the Chamfer, tending to it, padding ignored, chunked alike, smooth where the Chamfer jumps."""

from __future__ import annotations

import math

import pytest
import torch

from benchmark.metrics import soft_chamfer
from benchmark.metrics.chamfer import chamfer_loss
from benchmark.metrics.soft_chamfer import SoftChamfer, reference_soft_chamfer


def _clouds(n=3, v=40, p=25, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, v, 3, generator=g, dtype=torch.float64), torch.randn(n, p, 3, generator=g, dtype=torch.float64)


def test_between_the_chamfer_less_its_bound_and_the_chamfer_and_tends_to_it():
    a, b = _clouds()
    exact = chamfer_loss(a, b, eps=0.0)
    lengths = torch.full((3,), b.shape[1])
    for tau in (0.3, 0.05, 0.01):
        soft = SoftChamfer(b, lengths, tau)(a)
        bound = 0.5 * tau * (math.log(b.shape[1]) + math.log(a.shape[1]))
        assert bool((soft <= exact + 1e-9).all()) and bool((soft >= exact - bound - 1e-9).all()), tau
    assert torch.allclose(SoftChamfer(b, lengths, 1e-4)(a), exact, atol=1e-3)


def test_padding_points_are_ignored_and_their_gradient_is_finite():
    a, b = _clouds()
    lengths = torch.tensor([25, 10, 1])
    padded = b.clone()
    padded[1, 10:] = 123.0  # whatever the padding holds
    padded[2, 1:] = float("nan")
    a = a.requires_grad_(True)
    got = SoftChamfer(torch.nan_to_num(padded, nan=0.0), lengths, 0.05)(a)
    for i, n in enumerate(lengths.tolist()):
        alone = SoftChamfer(b[i:i + 1, :n], torch.tensor([n]), 0.05)(a[i:i + 1])
        assert torch.allclose(got[i], alone[0]), i
    got.sum().backward()
    assert bool(torch.isfinite(a.grad).all())


def test_chunks_give_the_same_values(monkeypatch):
    a, b = _clouds(n=5)
    lengths = torch.full((5,), b.shape[1])
    whole = SoftChamfer(b, lengths, 0.05)(a)
    monkeypatch.setattr(soft_chamfer, "MAX_PAIR_ELEMENTS", a.shape[1] * b.shape[1] * 2)  # two elements per chunk
    assert torch.allclose(SoftChamfer(b, lengths, 0.05)(a), whole)


def test_smooth_where_the_chamfer_jumps():
    """One observed point midway between two vertices: the Chamfer's gradient flips as the point
    crosses the midpoint, the soft one's passes smoothly through 0."""
    verts = torch.tensor([[[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]], dtype=torch.float64)
    grads = {}
    for name, fn in (("hard", lambda x: chamfer_loss(verts, x, eps=0.0)),
                     ("soft", lambda x: SoftChamfer(x, torch.tensor([1]), 0.1)(verts))):
        out = []
        for dx in (-1e-6, 1e-6):
            x = torch.tensor([[[dx, 0.5, 0.0]]], dtype=torch.float64, requires_grad=True)
            fn(x).sum().backward()
            out.append(float(x.grad[0, 0, 0]))
        grads[name] = out
    assert grads["hard"][0] * grads["hard"][1] < 0 and abs(grads["hard"][0] - grads["hard"][1]) > 0.1
    assert abs(grads["soft"][0] - grads["soft"][1]) < 1e-4


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_same_values_and_gradients_as_autograd_through_the_pairs(dtype):
    """The one-function form against autograd through every pair (padding in two elements, an
    observed point on a vertex): values, the gradient to both point sets under unequal weights per
    element, and no gradient kept where none is wanted."""
    a, b = (x.to(dtype) + 3.0 for x in _clouds(n=4, v=30, p=20, seed=3))  # metres from the origin, as a walk's
    b[1, 0] = a[1, 5]  # a pair at distance 0
    lengths = torch.tensor([20, 7, 1, 20])
    weights = torch.tensor([1.0, -2.0, 0.5, 3.0], dtype=dtype)
    grads = []
    for fn in (lambda x, y: SoftChamfer(y, lengths, 0.05)(x), lambda x, y: reference_soft_chamfer(x, y, lengths, 0.05)):
        x, y = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
        value = fn(x, y)
        (value * weights).sum().backward()
        grads.append((value.detach(), x.grad, y.grad))
    value_tol = {"rtol": 0.0, "atol": 1e-7}  # the reference's sqrt(d^2 + 1e-12): 1e-6 m at the coincident pair
    tol = {"rtol": 1e-9, "atol": 1e-10} if dtype == torch.float64 else {"rtol": 1e-5, "atol": 1e-6}
    assert torch.allclose(grads[0][0], grads[1][0], **value_tol)
    for got, want in zip(grads[0][1:], grads[1][1:]):
        assert torch.allclose(got, want, **tol)
    assert float(grads[0][2][1, 7:].abs().max()) == 0.0  # padding: no gradient
    with torch.no_grad():
        assert torch.allclose(SoftChamfer(b, lengths, 0.05)(a), grads[1][0], **value_tol)


def test_bad_arguments_are_refused():
    a, b = _clouds()
    with pytest.raises(ValueError, match="temperature must be > 0"):
        SoftChamfer(b, torch.full((3,), 25), 0.0)
    with pytest.raises(ValueError, match="at least one valid point"):
        SoftChamfer(b, torch.tensor([25, 0, 3]), 0.1)
    with pytest.raises(ValueError, match=r"a must be \(3, V, 3\)"):
        SoftChamfer(b, torch.full((3,), 25), 0.1)(a[:2])


def test_perf_part_prints_both_forms_side_by_side(tmp_path):
    """``perf --only soft-chamfer``: both forms on the same points, their ratio and differences."""
    from benchmark.tools import perf

    report = perf.run_perf(out=tmp_path / "perf", parts=["soft-chamfer"])
    rows = report["soft_chamfer"]
    assert [(r["vertices"], r["points"]) for r in rows] == [(400, 100), (400, 256)]
    for r in rows:
        assert r["project_ms"] > 0 and r["reference_ms"] > 0 and r["ratio"] == r["project_ms"] / r["reference_ms"]
        assert r["max_value_diff_m"] < 1e-6 and r["max_grad_diff_rel"] < 1e-4
    assert "| 400 x 256 |" in (tmp_path / "perf" / "perf.md").read_text()
