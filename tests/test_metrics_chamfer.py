"""Chamfer distance / loss: every backend against an independent brute-force reference."""

import math

import pytest
import torch

from benchmark.metrics import chamfer_distance, chamfer_loss, chamfer_perf, nearest_neighbors
from benchmark.metrics.chamfer import _tile_shape

BACKENDS = ("kdtree", "scipy", "tiled", "naive", "auto")


def reference_chamfer(a, b, a_lengths=None, b_lengths=None, squared=False):
    """Independent reference: per element, all pairwise differences, min, mean (autograd flows)."""
    out = []
    for n in range(a.shape[0]):
        x = a[n, : (a.shape[1] if a_lengths is None else int(a_lengths[n]))]
        y = b[n, : (b.shape[1] if b_lengths is None else int(b_lengths[n]))]
        sq = (x[:, None, :] - y[None, :, :]).square().sum(-1)
        d = sq if squared else sq.sqrt()
        out.append(0.5 * (d.min(dim=1).values.mean() + d.min(dim=0).values.mean()))
    return torch.stack(out)


def random_padded(seed, n=3, p=40, q=55, dtype=torch.float64, garbage=math.nan):
    """Random clouds with random valid lengths; the padding holds ``garbage``."""
    gen = torch.Generator().manual_seed(seed)
    a = torch.randn(n, p, 3, generator=gen, dtype=dtype)
    b = torch.randn(n, q, 3, generator=gen, dtype=dtype) * 0.7 + 0.2
    al = torch.randint(1, p + 1, (n,), generator=gen)
    bl = torch.randint(1, q + 1, (n,), generator=gen)
    al[0], bl[-1] = p, q  # one element without padding on each side
    for i in range(n):
        a[i, al[i]:] = garbage
        b[i, bl[i]:] = garbage
    return a, b, al, bl


# ----------------------------------------------------------------------------- values


@pytest.mark.parametrize("backend", BACKENDS)
def test_matches_reference_with_padding(backend):
    a, b, al, bl = random_padded(0)
    got = chamfer_distance(a, b, al, bl, backend=backend)
    ref = reference_chamfer(a, b, al, bl)
    assert got.shape == (3,)
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)
    assert torch.isfinite(got).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_matches_reference_without_lengths(backend):
    gen = torch.Generator().manual_seed(1)
    a = torch.randn(2, 30, 3, generator=gen, dtype=torch.float64)
    b = torch.randn(2, 17, 3, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(chamfer_distance(a, b, backend=backend), reference_chamfer(a, b), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(chamfer_loss(a, b, squared=True, backend=backend),
                               reference_chamfer(a, b, squared=True), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_hand_computed(backend):
    # A = {(0,0,0), (2,0,0)}, B = {(0,1,0)}: A->B distances 1 and sqrt(5); B->A distance 1.
    a = torch.tensor([[[0.0, 0, 0], [2.0, 0, 0]]], dtype=torch.float64)
    b = torch.tensor([[[0.0, 1, 0]]], dtype=torch.float64)
    expected = 0.5 * ((1 + math.sqrt(5)) / 2 + 1)
    assert chamfer_distance(a, b, backend=backend).item() == pytest.approx(expected, abs=1e-15)
    # A = {origin}, B = {(3,4,0), (0,0,12)}: A->B 5; B->A mean(5, 12) = 8.5.
    a = torch.zeros(1, 1, 3, dtype=torch.float64)
    b = torch.tensor([[[3.0, 4, 0], [0, 0, 12]]], dtype=torch.float64)
    assert chamfer_distance(a, b, backend=backend).item() == pytest.approx(6.75, abs=1e-14)
    assert chamfer_loss(a, b, squared=True, backend=backend).item() == pytest.approx(0.5 * (25 + (25 + 144) / 2))
    # Symmetric in its arguments.
    assert chamfer_distance(b, a, backend=backend).item() == pytest.approx(6.75, abs=1e-14)


def test_identical_sets_are_zero_and_reductions():
    gen = torch.Generator().manual_seed(2)
    a = torch.randn(4, 20, 3, generator=gen, dtype=torch.float64)
    assert torch.equal(chamfer_distance(a, a.clone()), torch.zeros(4, dtype=torch.float64))
    b = a + 0.1 * torch.randn(4, 20, 3, generator=gen, dtype=torch.float64)
    per = chamfer_loss(a, b, reduction="none")
    assert chamfer_loss(a, b, reduction="mean").item() == pytest.approx(per.mean().item())
    assert chamfer_loss(a, b, reduction="sum").item() == pytest.approx(per.sum().item())


@pytest.mark.parametrize("max_tile_elements", [1, 7, 50, 600, 10**9])
def test_tiled_many_tiles(max_tile_elements):
    a, b, al, bl = random_padded(3, n=3, p=23, q=31)
    got = chamfer_distance(a, b, al, bl, backend="tiled", max_tile_elements=max_tile_elements)
    torch.testing.assert_close(got, reference_chamfer(a, b, al, bl), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("sizes", [(3, 23, 31, 1), (3, 23, 31, 7), (3, 23, 31, 50), (3, 23, 31, 600),
                                   (3, 23, 31, 10**6), (5, 1, 1, 3), (2, 10, 100, 2000)])
def test_tile_shape_is_bounded(sizes):
    n, p, q, limit = sizes
    tb, tp, tq = _tile_shape(n, p, q, limit)
    assert 1 <= tb <= n and 1 <= tp <= p and 1 <= tq <= q
    assert tb * tp * tq <= max(limit, 1)


def test_tiled_float32_far_from_origin():
    """float32 ranking with |r|^2 - 2 q.r stays accurate after centring, even 50 m from the origin."""
    a, b, al, bl = random_padded(4, garbage=0.0)
    ref = reference_chamfer(a, b, al, bl)
    shift = torch.tensor([50.0, -3.0, 20.0], dtype=torch.float64)
    got = chamfer_distance((a * 0.3 + shift).float(), (b * 0.3 + shift).float(), al, bl, backend="tiled")
    torch.testing.assert_close(got.double(), 0.3 * ref, rtol=0, atol=2e-5)


def test_backends_agree_on_float32_clouds():
    gen = torch.Generator().manual_seed(5)
    a = torch.rand(2, 300, 3, generator=gen)
    b = torch.rand(2, 250, 3, generator=gen)
    ref = reference_chamfer(a.double(), b.double()).float()
    for backend in ("kdtree", "tiled", "naive"):
        torch.testing.assert_close(chamfer_distance(a, b, backend=backend), ref, rtol=1e-5, atol=1e-6)


def test_nearest_neighbors_indices_and_padding():
    a, b, al, bl = random_padded(6)
    for backend in ("kdtree", "tiled", "naive"):
        dist, idx = nearest_neighbors(a, b, al, bl, backend=backend)
        for n in range(a.shape[0]):
            x, y = a[n, : al[n]], b[n, : bl[n]]
            d = (x[:, None] - y[None]).norm(dim=-1)
            assert torch.equal(idx[n, : al[n]], d.argmin(dim=1))  # random data: no ties
            torch.testing.assert_close(dist[n, : al[n]], d.min(dim=1).values, rtol=1e-12, atol=1e-12)
            assert (idx[n, al[n]:] == -1).all() and torch.isnan(dist[n, al[n]:]).all()


# ----------------------------------------------------------------------------- gradients


@pytest.mark.parametrize("backend", ("kdtree", "tiled", "naive"))
@pytest.mark.parametrize("squared", (False, True))
def test_gradcheck(backend, squared):
    gen = torch.Generator().manual_seed(7)
    a = torch.randn(2, 5, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    b = torch.randn(2, 4, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    al, bl = torch.tensor([5, 3]), torch.tensor([2, 4])
    assert torch.autograd.gradcheck(
        lambda x, y: chamfer_loss(x, y, al, bl, squared=squared, backend=backend), (a, b), eps=1e-6, atol=1e-7
    )


@pytest.mark.parametrize("backend", ("kdtree", "tiled", "naive"))
def test_gradients_match_autograd_through_reference(backend):
    a0, b0, al, bl = random_padded(8, garbage=0.0)
    a = a0.clone().requires_grad_(True)
    b = b0.clone().requires_grad_(True)
    chamfer_loss(a, b, al, bl, backend=backend, reduction="sum").backward()
    a_ref = a0.clone().requires_grad_(True)
    b_ref = b0.clone().requires_grad_(True)
    reference_chamfer(a_ref, b_ref, al, bl).sum().backward()
    torch.testing.assert_close(a.grad, a_ref.grad, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(b.grad, b_ref.grad, rtol=1e-10, atol=1e-12)
    for n in range(a.shape[0]):  # padding gets exactly zero gradient
        assert (a.grad[n, al[n]:] == 0).all() and (b.grad[n, bl[n]:] == 0).all()


def test_gradient_with_nan_padding_and_coincident_points():
    """NaN padding and zero distances (sqrt'(0)) must not produce NaN gradients."""
    a, b, al, bl = random_padded(9)  # NaN padding
    b[:, 0] = a[:, 0]  # coincident points: zero distance
    a.requires_grad_(True)
    chamfer_loss(a, b, al, bl).sum().backward()
    assert torch.isfinite(a.grad).all()
    x = torch.randn(1, 6, 3, dtype=torch.float64, requires_grad=True)
    chamfer_loss(x, x.detach().clone()).sum().backward()
    assert torch.equal(x.grad, torch.zeros_like(x))


def test_loss_value_is_the_metric():
    a, b, al, bl = random_padded(10)
    torch.testing.assert_close(chamfer_loss(a, b, al, bl, eps=0.0), chamfer_distance(a, b, al, bl))


# ----------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda a, b: chamfer_distance(a[0], b), r"`a` must have shape \(N, P, 3\)"),
        (lambda a, b: chamfer_distance(a, b[..., :2]), r"`b` must have shape \(N, P, 3\)"),
        (lambda a, b: chamfer_distance(a, b[:1]), "same batch size"),
        (lambda a, b: chamfer_distance(a, b.float()), "share device and dtype"),
        (lambda a, b: chamfer_distance(a.long(), b.long()), "floating-point"),
        (lambda a, b: chamfer_distance(a, b, torch.tensor([4, 2])), r"`a_lengths` must have shape \(N,\)"),
        (lambda a, b: chamfer_distance(a, b, torch.tensor([4, 0, 1])), r"`a_lengths` must lie in \[1, 4\]"),
        (lambda a, b: chamfer_distance(a, b, None, torch.tensor([1, 2, 6])), r"`b_lengths` must lie in \[1, 5\]"),
        (lambda a, b: chamfer_distance(a, b, torch.tensor([1.0, 2.0, 3.0])), "integer tensor"),
        (lambda a, b: chamfer_distance(a, b, backend="fast"), "`backend` must be one of"),
        (lambda a, b: chamfer_distance(a, b, backend="tiled", max_tile_elements=0), "max_tile_elements"),
        (lambda a, b: chamfer_loss(a, b, reduction="max"), "`reduction` must be one of"),
        (lambda a, b: chamfer_loss(a, b, eps=-1.0), "`eps` must be >= 0"),
        (lambda a, b: chamfer_distance(a[:, :0], b), "empty"),
        (lambda a, b: nearest_neighbors(a, b[0]), r"nearest_neighbors: `ref` must have shape"),
    ],
)
def test_errors(make, match):
    a = torch.zeros(3, 4, 3, dtype=torch.float64)
    b = torch.ones(3, 5, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=match):
        make(a, b)


def test_nan_in_valid_points_is_an_error():
    a, b, al, bl = random_padded(11)
    a[1, 0, 2] = math.nan
    with pytest.raises(ValueError, match="`a` holds NaN or inf at valid"):
        chamfer_distance(a, b, al, bl)


# ----------------------------------------------------------------------------- perf report


def test_perf_report_structure_and_agreement():
    """The perf report runs all three backends and checks they agree (timings are not asserted)."""
    report = chamfer_perf(frames=2, n_points=60, n_vertices=80, repeats=1)
    assert set(report["ms_per_frame"]) == {"kdtree", "tiled", "naive"}
    assert report["speedup_vs_naive"]["naive"] == 1.0
    assert report["loss_max_abs_diff_m"] < 1e-6
    assert report["frames_timed"] == {"kdtree": 2, "tiled": 1, "naive": 1}


# ----------------------------------------------------------------------------- fast exact paths


def test_pykdtree_backend_matches_scipy_reference_indices():
    """The default KD-tree backend (pykdtree) finds the same neighbours as the scipy reference."""
    pytest.importorskip("pykdtree")
    a, b, al, bl = random_padded(11, n=4, p=300, q=500, garbage=0.0)
    for q, r, ql, rl in ((a, b, al, bl), (b, a, bl, al)):
        d1, i1 = nearest_neighbors(q, r, ql, rl, backend="kdtree")
        d2, i2 = nearest_neighbors(q, r, ql, rl, backend="scipy")
        assert torch.equal(i1, i2)
        assert torch.equal(torch.nan_to_num(d1), torch.nan_to_num(d2))


@pytest.mark.parametrize("squared", [False, True])
@pytest.mark.parametrize("reduction", ["none", "sum"])
def test_static_chamfer_equals_chamfer_loss(squared, reduction):
    """StaticChamfer (trees of b built once) returns chamfer_loss's value and gradient, bit for bit,
    at every call while a moves, with padding (NaN in the padding never leaks)."""
    from benchmark.metrics.static_chamfer import StaticChamfer

    a, b, al, bl = random_padded(5, n=4, p=120, q=90, dtype=torch.float32)
    static = StaticChamfer(b, bl)
    gen = torch.Generator().manual_seed(0)
    for _ in range(3):
        a = torch.where(torch.isnan(a), a, a + 0.05 * torch.randn(a.shape, generator=gen))
        x, y = a.clone().requires_grad_(True), a.clone().requires_grad_(True)
        got = static(x, al, squared=squared, reduction=reduction)
        ref = chamfer_loss(y, b, al, bl, squared=squared, reduction=reduction, backend="scipy")
        assert torch.equal(got, ref)
        got.sum().backward()
        ref.sum().backward()
        assert torch.equal(x.grad, y.grad)
        assert torch.isfinite(x.grad).all()


def test_static_chamfer_errors():
    from benchmark.metrics.static_chamfer import StaticChamfer

    b = torch.randn(2, 10, 3)
    with pytest.raises(ValueError, match="shape"):
        StaticChamfer(b[0])
    static = StaticChamfer(b)
    with pytest.raises(ValueError, match="batch size"):
        static(torch.randn(3, 5, 3))
    with pytest.raises(ValueError, match="reduction"):
        static(torch.randn(2, 5, 3), reduction="max")


def test_pykdtree_results_do_not_depend_on_openmp_threads():
    """pykdtree's OpenMP thread count (OMP_NUM_THREADS, read at import) never changes a neighbour."""
    pytest.importorskip("pykdtree")
    import subprocess
    import sys

    code = ("import numpy as np\nfrom pykdtree.kdtree import KDTree\nrng = np.random.default_rng(0)\n"
            "p, q = rng.standard_normal((5000, 3)), rng.standard_normal((7000, 3))\n"
            "d, i = KDTree(p).query(q)\nprint(int(i.astype(np.int64).sum()), repr(float(d.sum())))\n")
    outs = set()
    for threads in ("1", "2"):
        env = {**__import__("os").environ, "OMP_NUM_THREADS": threads}
        outs.add(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout)
    assert len(outs) == 1


def test_static_chamfer_sampled_points_are_unbiased():
    """StaticChamfer(b_sample=m): the points -> mesh mean over m points drawn with replacement is an
    unbiased estimate of the exact loss and of its gradient (the completion fit's points_per_step)."""
    from benchmark.metrics.chamfer import chamfer_loss
    from benchmark.metrics.static_chamfer import StaticChamfer

    g = torch.Generator().manual_seed(0)
    a = torch.randn(3, 40, 3, generator=g, dtype=torch.float64).requires_grad_(True)
    b = torch.randn(3, 300, 3, generator=g, dtype=torch.float64)
    bl = torch.tensor([300, 120, 17])
    static = StaticChamfer(b, bl)
    exact = chamfer_loss(a, b, b_lengths=bl)
    (grad_exact,) = torch.autograd.grad(exact.sum(), a)
    sampler = torch.Generator().manual_seed(1)
    values, grads = [], []
    for _ in range(400):
        v = static(a, b_sample=30, generator=sampler)
        values.append(v.detach())
        grads.append(torch.autograd.grad(v.sum(), a)[0])
    mean_v, mean_g = torch.stack(values).mean(0), torch.stack(grads).mean(0)
    assert torch.allclose(mean_v, exact.detach(), rtol=0.02)
    assert (mean_g - grad_exact).norm() < 0.05 * grad_exact.norm()
    # a sample as large as the largest element is the exact loss
    assert torch.equal(static(a, b_sample=300).detach(), static(a).detach())
