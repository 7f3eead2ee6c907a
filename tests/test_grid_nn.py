"""The compiled grid nearest-neighbour search (benchmark.metrics.grid_nn) against scipy's cKDTree."""

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

grid_nn = pytest.importorskip("benchmark.metrics.grid_nn")
if not grid_nn.HAVE_NUMBA:  # pragma: no cover - numba is a dependency
    pytest.skip("numba is not installed", allow_module_level=True)


def _check(points, lengths, queries, qlengths, out):
    """Every valid query's answer is at the KD-tree's nearest distance (the same double); padding -1."""
    for n in range(points.shape[0]):
        ref = points[n, : lengths[n]]
        q = queries[n, : qlengths[n]]
        _, idx = cKDTree(ref).query(q)
        got = out[n, : qlengths[n]]
        assert (got >= 0).all() and (got < lengths[n]).all()
        d_got = ((ref[got] - q) ** 2).sum(-1)
        d_ref = ((ref[idx] - q) ** 2).sum(-1)
        assert np.array_equal(d_got, d_ref)
        assert (out[n, qlengths[n]:] == -1).all()


def _cloud(rng, n_batch, m, kind, scale):
    x = rng.standard_normal((n_batch, m, 3)) * scale
    if kind == "flat":
        x[..., 1] = 0.0
    elif kind == "line":
        x[..., 1:] = 0.0
    elif kind == "same":
        x[:] = x[:, :1]
    elif kind == "shell":  # a body-sized surface, as a fit's points are
        x = x / np.linalg.norm(x, axis=-1, keepdims=True) * np.array([0.25, 0.85, 0.15]) * scale
    return x


@pytest.mark.parametrize("candidates", [False, True])
@pytest.mark.parametrize("kind", ["blob", "flat", "line", "same", "shell"])
def test_nearest_is_exact(candidates, kind):
    rng = np.random.default_rng(hash((candidates, kind)) % 2**32)
    for scale in (1e-3, 1.0, 30.0):
        m, mq = int(rng.integers(1, 700)), int(rng.integers(1, 900))
        points = _cloud(rng, 3, m, kind, scale)
        lengths = rng.integers(1, m + 1, size=3)
        grids = grid_nn.PointGrids(points, lengths, candidates=candidates)
        for spread in (0.3, 1.0, 4.0):  # queries on, around and far outside the points (the KD-tree fallback)
            queries = rng.standard_normal((3, mq, 3)) * scale * spread
            qlengths = rng.integers(0, mq + 1, size=3)
            _check(points, lengths, queries, qlengths, grids.nearest(queries, qlengths))


def test_candidate_cells_fill_as_queries_move():
    """A fixed set queried by moving points (a fit): cells are listed on first use, the pool grows,
    and every answer stays exact."""
    rng = np.random.default_rng(0)
    points = _cloud(rng, 2, 300, "shell", 1.0)
    lengths = np.array([300, 170])
    grids = grid_nn.PointGrids(points, lengths, candidates=True)
    queries = _cloud(rng, 2, 2000, "shell", 1.0)
    used = []
    for _ in range(6):
        queries = queries + 0.05 * rng.standard_normal(queries.shape)
        _check(points, lengths, queries, np.array([2000, 1500]), grids.nearest(queries, np.array([2000, 1500])))
        used.append(grids._used)
    assert used[0] > 0 and used[-1] > used[0] and grids._pool.shape[0] >= grids._used


def test_query_order_does_not_change_answers():
    rng = np.random.default_rng(1)
    points = _cloud(rng, 2, 500, "shell", 1.0)
    queries = _cloud(rng, 2, 800, "shell", 1.1)
    lengths, qlengths = np.array([500, 400]), np.array([800, 600])
    grids = grid_nn.PointGrids(points, lengths)
    order = np.stack([rng.permutation(800) for _ in range(2)])
    order[1, :600] = rng.permutation(600)
    assert np.array_equal(grids.nearest(queries, qlengths), grids.nearest(queries, qlengths, order))


def test_hints_do_not_change_answers():
    """Any hint (a point to start from: the right one, a random one, or none) gives the exact answer."""
    rng = np.random.default_rng(2)
    points = _cloud(rng, 2, 600, "shell", 1.0)
    lengths, qlengths = np.array([600, 350]), np.array([900, 700])
    queries = _cloud(rng, 2, 900, "shell", 1.0) * rng.choice([0.5, 1.0, 3.0], size=(2, 900, 1))
    grids = grid_nn.PointGrids(points, lengths)
    plain = grids.nearest(queries, qlengths)
    _check(points, lengths, queries, qlengths, plain)
    random_hints = np.stack([rng.integers(0, n, size=900) for n in lengths])
    random_hints[0, ::7] = -1
    assert np.array_equal(grids.nearest(queries, qlengths, hints=random_hints), plain)
    assert np.array_equal(grids.nearest(queries, qlengths, hints=plain), plain)
    with pytest.raises(ValueError, match="hints must be"):
        grids.nearest(queries, qlengths, hints=np.full((2, 900), 400))
    far = queries * 40.0  # far from every point: the hint's cube spans the whole grid
    far_plain = grids.nearest(far, qlengths)
    _check(points, lengths, far, qlengths, far_plain)
    assert np.array_equal(grids.nearest(far, qlengths, hints=random_hints), far_plain)


def test_errors():
    points = np.zeros((2, 5, 3))
    with pytest.raises(ValueError, match=r"\(N, M, 3\)"):
        grid_nn.PointGrids(points[0], np.array([5]))
    with pytest.raises(ValueError, match="every length"):
        grid_nn.PointGrids(points, np.array([0, 5]))
    grids = grid_nn.PointGrids(points, np.array([5, 5]))
    with pytest.raises(ValueError, match="queries must be"):
        grids.nearest(np.zeros((3, 4, 3)), np.array([4, 4, 4]))
    with pytest.raises(ValueError, match="query length"):
        grids.nearest(np.zeros((2, 4, 3)), np.array([5, 4]))
    with pytest.raises(ValueError, match="order must be"):
        grids.nearest(np.zeros((2, 4, 3)), np.array([4, 4]), order=np.full((2, 4), 4))


def test_static_chamfer_on_grids_equals_chamfer_loss_on_several_threads():
    """StaticChamfer splits the batch into one run of frames per thread: same value and gradient as
    the KD-tree reference, bit for bit, on one thread and on two."""
    from benchmark.metrics.chamfer import chamfer_loss
    from benchmark.metrics.static_chamfer import StaticChamfer, _chunks

    g = torch.Generator().manual_seed(0)
    b = torch.randn(5, 400, 3, generator=g) * torch.tensor([0.25, 0.85, 0.15])
    bl = torch.tensor([400, 300, 17, 1, 250])
    threads = torch.get_num_threads()
    try:
        for n_threads in (1, 2):
            torch.set_num_threads(n_threads)
            chunks = _chunks(5)  # contiguous runs covering the batch
            assert chunks[0].start == 0 and chunks[-1].stop == 5 and all(c.stop == d.start for c, d in zip(chunks, chunks[1:]))
            static = StaticChamfer(b, bl)
            assert static.grids
            a = torch.randn(5, 900, 3, generator=g) * 0.5
            for _ in range(3):
                a = a + 0.02 * torch.randn(a.shape, generator=g)
                x, y = a.clone().requires_grad_(True), a.clone().requires_grad_(True)
                got = static(x)
                ref = chamfer_loss(y, b, b_lengths=bl, backend="scipy")
                assert torch.equal(got, ref)
                got.sum().backward()
                ref.sum().backward()
                assert torch.equal(x.grad, y.grad)
    finally:
        torch.set_num_threads(threads)
