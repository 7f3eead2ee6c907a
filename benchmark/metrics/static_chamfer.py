"""The Chamfer loss against a fixed point set, called many times with a moving one (:class:`StaticChamfer`).

A fit's observed points never move: their search structures are built once and shared by every
step. Same values and gradients as :func:`benchmark.metrics.chamfer.chamfer_loss` (see its module
for the definition and the backends).

The nearest neighbours come from compiled uniform grids (:mod:`benchmark.metrics.grid_nn`, numba):
one grid per observed frame built here, one per mesh frame built at each call by a counting sort
(a fifth to an eighth of a KD-tree's build), every frame of the batch in one compiled call. Where
numba is missing, from KD-trees (pykdtree, else scipy). Both are exact: they return the same
nearest neighbours (up to points at exactly the same distance), so the same loss. Once the mesh
moves little from one call to the next, most answers come from neighbour lists kept across calls
(:mod:`benchmark.metrics.neighbour_lists`), exact too; the rest are searched.
"""

from __future__ import annotations

import numpy as np
import torch

from benchmark.metrics import grid_nn
from benchmark.metrics.chamfer import (
    DEFAULT_EPS,
    DEFAULT_MAX_TILE_ELEMENTS,
    REDUCTIONS,
    apply_reduction,
    build_tree,
    chamfer_loss,
    clean_padding,
    cpu_threads,
    directed_mean,
    map_elements,
    morton_order,
    nearest_indices,
    prefix_mask,
    pykdtree_class,
    query_tree,
    resolve_backend,
    validate_lengths,
    validate_points,
)


USE_NEIGHBOUR_LISTS = True  # answer from neighbour lists kept across calls (exact; False: search every call)


def _chunks(n_batch: int) -> list[slice]:
    """The batch split into one contiguous run of elements per thread (:func:`cpu_threads`)."""
    parts = max(1, min(cpu_threads(), n_batch))
    bounds = np.linspace(0, n_batch, parts + 1).round().astype(int)
    return [slice(int(lo), int(hi)) for lo, hi in zip(bounds[:-1], bounds[1:])]


class StaticChamfer:
    """:func:`chamfer_loss` ``(a, b)`` for a fixed ``b``, called many times with a changing ``a``.

    An optimiser fits mesh vertices ``a`` to the same observed points ``b`` at every step: the
    search structure on ``b`` (a grid with candidate lists per element, or KD-trees without
    numba) is built once here and shared by every call, and the points of ``b`` are queried
    against ``a``'s grid (tree) in a cached Morton order (as are the rows of ``a``, in the order
    of the first call's positions). Every call returns exactly what
    ``chamfer_loss(a, b, a_lengths, b_lengths, squared=..., eps=..., reduction=...)`` returns with
    the KD-tree backend (same nearest neighbours, same value and gradient); on a non-CPU device,
    or where pykdtree is not installed, it simply calls :func:`chamfer_loss`.

    Args:
        b: (N, Q, 3) padded points, metres (no gradient flows to them).
        b_lengths: (N,) long valid-prefix lengths or None (all valid).
    """

    def __init__(self, b: torch.Tensor, b_lengths: torch.Tensor | None = None):
        caller = "StaticChamfer"
        validate_points(b, "b", caller)
        if b.shape[0] == 0:
            raise ValueError(f"{caller}: empty batch (N = 0).")
        self.bl = validate_lengths(b_lengths, "b_lengths", caller, b.shape[0], b.shape[1], b.device)
        self.b, self.bmask = clean_padding(b.detach(), self.bl, "b", caller)
        self.b_lengths = b_lengths
        on_cpu = self.b.device.type == "cpu"
        self.grids = on_cpu and grid_nn.HAVE_NUMBA
        self.cached = on_cpu and (self.grids or pykdtree_class() is not None)
        self._a_order = None
        self._hints = None
        self._lists = None  # neighbour lists (MovingQueryLists, FixedQueryLists), made on first need
        if not self.cached:
            return
        b_np = self.b.to(torch.float64).numpy()
        lengths = self.bl.tolist()
        if self.grids:
            self._b_np = np.ascontiguousarray(b_np)
            self._bl_np = self.bl.numpy().astype(np.int64)
            self._chunks = _chunks(b.shape[0])
            self._b_grids = map_elements(
                lambda c: grid_nn.PointGrids(self._b_np[self._chunks[c]], self._bl_np[self._chunks[c]],
                                             candidates=b.shape[1] <= grid_nn.CANDIDATE_MAX_POINTS), len(self._chunks))
            self._b_order_arr = np.zeros(self.b.shape[:2], dtype=np.int64)
            for n in range(b.shape[0]):
                self._b_order_arr[n, : lengths[n]] = morton_order(self._b_np[n, : lengths[n]])
            return
        self._b_pts = [np.ascontiguousarray(b_np[n, : lengths[n]]) for n in range(b.shape[0])]
        self._b_trees = map_elements(lambda n: build_tree(self._b_pts[n]), b.shape[0])
        self._b_order = [morton_order(pts) for pts in self._b_pts]
        self._b_sorted = [np.ascontiguousarray(pts[o]) for pts, o in zip(self._b_pts, self._b_order)]

    def select(self, elements: torch.Tensor) -> "StaticChamfer":
        """The StaticChamfer of the elements ``elements`` ((K,) long) of ``b`` only: what this one
        returns for them, element by element (each element's loss depends on its own points only).
        The new instance starts its searches from this one's last answers and query order for those
        elements, so a fit that drops finished sequences from its batch goes on as fast."""
        idx = elements.to(device=self.b.device, dtype=torch.long)
        out = StaticChamfer(self.b.index_select(0, idx),
                            None if self.b_lengths is None else self.b_lengths.index_select(0, idx))
        if not (out.cached and self.cached):
            return out
        rows = idx.cpu().numpy()
        if self._a_order is not None:
            out._a_order = [self._a_order[r] for r in rows]
            if self.grids:
                out._a_order_arr = np.ascontiguousarray(self._a_order_arr[rows])
        if self.grids and self._hints is not None:
            out._hints = tuple(np.ascontiguousarray(h[rows]) for h in self._hints)
        return out

    def indices(self, a: torch.Tensor, al: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """(idx a->b (N, P), idx b->a (N, Q)) long, -1 at padding, for clean (N, P, 3) ``a``."""
        a_np = a.detach().to(torch.float64).numpy()
        n_batch, p = a_np.shape[:2]
        self._order_a(a_np, al)
        if self.grids:
            return self._grid_indices(a_np, np.asarray(al, dtype=np.int64), self._b_np, self._bl_np, self._b_order_arr)
        idx_ab = np.full((n_batch, p), -1, dtype=np.int64)
        idx_ba = np.full((n_batch, self.b.shape[1]), -1, dtype=np.int64)

        def run(n: int) -> None:
            pa = a_np[n, : al[n]]
            oa, ob = self._a_order[n], self._b_order[n]
            idx_ab[n, oa] = query_tree(self._b_trees[n], np.ascontiguousarray(pa[oa]))[1]
            idx_ba[n, ob] = query_tree(build_tree(pa), self._b_sorted[n])[1]

        map_elements(run, n_batch)
        return torch.from_numpy(idx_ab), torch.from_numpy(idx_ba)

    def _order_a(self, a_np: np.ndarray, al: list[int]) -> None:
        """The Morton order of the first call's rows of ``a`` (kept while the lengths stay)."""
        n_batch, p = a_np.shape[:2]
        if self._a_order is None or len(self._a_order) != n_batch or any(
                o.shape[0] != al[n] for n, o in enumerate(self._a_order)):
            self._a_order = [morton_order(a_np[n, : al[n]]) for n in range(n_batch)]
            self._a_order_arr = np.zeros((n_batch, p), dtype=np.int64)
            for n in range(n_batch):
                self._a_order_arr[n, : al[n]] = self._a_order[n]

    def _grid_indices(self, a_np: np.ndarray, al: np.ndarray, b_np: np.ndarray, bl: np.ndarray,
                      b_order: np.ndarray | None) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`indices` on the grids, for the points ``b_np`` (the fixed ones, or a sample of
        them: ``b_order`` None, queried in their own order) against ``a``'s grid built here. For
        the fixed points, the previous call's answers (same shapes) start each search: exact
        whatever they are, fast while the mesh moves little."""
        idx_ab = np.full(a_np.shape[:2], -1, dtype=np.int64)
        idx_ba = np.full(b_np.shape[:2], -1, dtype=np.int64)
        hints = self._hints if b_order is not None else None
        if hints is not None and (hints[0].shape != idx_ab.shape or not np.array_equal(hints[2], al)):
            hints = None

        if b_order is not None and USE_NEIGHBOUR_LISTS and grid_nn.HAVE_NUMBA:
            self._listed_indices(a_np, al, idx_ab, idx_ba, hints)
        else:
            self._searched_indices(a_np, al, b_np, bl, b_order, hints, idx_ab, idx_ba)
        if b_order is not None:
            self._hints = (idx_ab.copy(), idx_ba.copy(), al.copy())
        return torch.from_numpy(idx_ab), torch.from_numpy(idx_ba)

    def _searched_indices(self, a_np, al, b_np, bl, b_order, hints, idx_ab, idx_ba) -> None:
        """Fill ``idx_ab`` and ``idx_ba`` by searching the grids (every element, on every thread)."""
        def run(c: int) -> None:
            sl = self._chunks[c]
            a_c = np.ascontiguousarray(a_np[sl])
            self._b_grids[c].nearest(a_c, al[sl], self._a_order_arr[sl], out=idx_ab[sl],
                                     hints=None if hints is None else hints[0][sl])
            grid_nn.PointGrids(a_c, al[sl]).nearest(
                np.ascontiguousarray(b_np[sl]), bl[sl], None if b_order is None else b_order[sl], out=idx_ba[sl],
                hints=None if hints is None else hints[1][sl])

        map_elements(run, len(self._chunks))

    def _listed_indices(self, a_np, al, idx_ab, idx_ba, hints) -> None:
        """:meth:`_grid_indices` for the fixed points, from neighbour lists kept across calls
        (:mod:`benchmark.metrics.neighbour_lists`): the same answers; a query its list cannot
        answer is searched on the grids as before."""
        from benchmark.metrics.neighbour_lists import FixedQueryLists, MovingQueryLists

        if self._lists is None:
            self._lists = (MovingQueryLists(self._b_np, self._bl_np), FixedQueryLists(self._b_np, self._bl_np))
        searched = self._lists[0].nearest(a_np, al, idx_ab)
        if searched:  # frames still moving fast: searched on the fixed points' grids, as without lists
            ql = np.zeros_like(al)
            ql[searched] = al[searched]

            def search(c: int) -> None:
                sl = self._chunks[c]
                self._b_grids[c].nearest(np.ascontiguousarray(a_np[sl]), ql[sl], self._a_order_arr[sl], out=idx_ab[sl],
                                         hints=None if hints is None else hints[0][sl])

            map_elements(search, len(self._chunks))
        left, whole = self._lists[1].nearest(a_np, al, idx_ba)
        if whole:  # frames still moving fast: searched whole, as without lists
            ns = np.array(sorted(whole), dtype=np.int64)
            found = np.full((ns.shape[0], self._b_np.shape[1]), -1, dtype=np.int64)
            grid_nn.PointGrids(np.ascontiguousarray(a_np[ns]), al[ns]).nearest(
                self._b_np[ns], self._bl_np[ns], self._b_order_arr[ns], out=found,
                hints=None if hints is None else np.ascontiguousarray(hints[1][ns]))
            idx_ba[ns] = found
        if not left:
            return
        ns = np.array([n for n, _ in left], dtype=np.int64)
        width = max(rows.shape[0] for _, rows in left)
        q = np.zeros((len(left), width, 3))
        ql = np.array([rows.shape[0] for _, rows in left], dtype=np.int64)
        h = np.full((len(left), width), -1, dtype=np.int64)
        for j, (n, rows) in enumerate(left):
            q[j, : rows.shape[0]] = self._b_np[n, rows]
            if hints is not None:
                h[j, : rows.shape[0]] = hints[1][n, rows]
        found = grid_nn.PointGrids(np.ascontiguousarray(a_np[ns]), al[ns]).nearest(q, ql, hints=h)
        for j, (n, rows) in enumerate(left):
            idx_ba[n, rows] = found[j, : rows.shape[0]]

    def sample_b(self, m: int, generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, min(m, Q), 3) points of ``b`` drawn uniformly with replacement from each element's valid
        prefix, and their (N,) lengths: an unbiased sample for the mean over ``b`` of any function."""
        m = min(int(m), self.b.shape[1])
        u = torch.rand(self.b.shape[0], m, generator=generator, dtype=torch.float64)
        bl = self.bl.cpu()  # the draws come from a CPU generator (the same samples on any device)
        idx = (u * bl.to(torch.float64)[:, None]).long().clamp_max(bl[:, None] - 1).to(self.b.device)
        return torch.gather(self.b, 1, idx[..., None].expand(-1, -1, 3)), torch.full_like(self.bl, m)

    def __call__(self, a: torch.Tensor, a_lengths: torch.Tensor | None = None, squared: bool = False,
                 reduction: str = "none", eps: float = DEFAULT_EPS, b_sample: int | None = None,
                 generator: torch.Generator | None = None) -> torch.Tensor:
        """The Chamfer loss of ``a`` (N, P, 3) against the fixed ``b``; see :func:`chamfer_loss`.

        ``b_sample``: where an element of ``b`` has more points than that, the ``b -> a`` mean is
        taken over ``b_sample`` of its points drawn uniformly with replacement (:meth:`sample_b`,
        ``generator``): an unbiased estimate of the exact mean, with an unbiased gradient. The
        ``a -> b`` direction stays exact (every point of ``b``).
        """
        if b_sample is not None and int(b_sample) < int(self.bl.max()):
            return self._sampled(a, a_lengths, squared, reduction, eps, int(b_sample), generator)
        if not self.cached:
            return chamfer_loss(a, self.b, a_lengths, self.b_lengths, squared=squared, reduction=reduction, eps=eps)
        caller = "StaticChamfer"
        if reduction not in REDUCTIONS:
            raise ValueError(f"{caller}: `reduction` must be one of {REDUCTIONS}; got {reduction!r}.")
        if not eps >= 0:
            raise ValueError(f"{caller}: `eps` must be >= 0; got {eps!r}.")
        validate_points(a, "a", caller)
        if a.shape[0] != self.b.shape[0] or a.device != self.b.device or a.dtype != self.b.dtype:
            raise ValueError(
                f"{caller}: `a` must have the batch size, device and dtype of the fixed points "
                f"({self.b.shape[0]}, {self.b.device}, {self.b.dtype}); got {a.shape[0]}, {a.device}, {a.dtype}."
            )
        al = validate_lengths(a_lengths, "a_lengths", caller, a.shape[0], a.shape[1], a.device)
        a, amask = clean_padding(a, al, "a", caller)
        idx_ab, idx_ba = self.indices(a, al.tolist())
        value = 0.5 * (directed_mean(a, self.b, idx_ab, amask, al, squared, eps)
                       + directed_mean(self.b, a, idx_ba, self.bmask, self.bl, squared, eps))
        return apply_reduction(value, reduction)


    def _sampled(self, a, a_lengths, squared, reduction, eps, m, generator):
        caller = "StaticChamfer"
        if reduction not in REDUCTIONS:
            raise ValueError(f"{caller}: `reduction` must be one of {REDUCTIONS}; got {reduction!r}.")
        validate_points(a, "a", caller)
        al = validate_lengths(a_lengths, "a_lengths", caller, a.shape[0], a.shape[1], a.device)
        a, amask = clean_padding(a, al, "a", caller)
        bs, bsl = self.sample_b(m, generator)
        bsmask = prefix_mask(bsl, bs.shape[1])
        if self.grids:
            a_np = a.detach().to(torch.float64).numpy()
            self._order_a(a_np, al.tolist())
            idx_ab, idx_ba = self._grid_indices(a_np, al.numpy().astype(np.int64), bs.to(torch.float64).numpy(),
                                                bsl.numpy().astype(np.int64), None)
        elif self.cached:
            a_np = a.detach().to(torch.float64).numpy()
            bs_np = bs.to(torch.float64).numpy()
            lens = al.tolist()
            idx_ab = np.full(a_np.shape[:2], -1, dtype=np.int64)
            idx_ba = np.empty(bs_np.shape[:2], dtype=np.int64)

            def run(n: int) -> None:
                pa = np.ascontiguousarray(a_np[n, : lens[n]])
                idx_ab[n, : lens[n]] = query_tree(self._b_trees[n], pa)[1]
                idx_ba[n] = query_tree(build_tree(pa), np.ascontiguousarray(bs_np[n]))[1]

            map_elements(run, a_np.shape[0])
            idx_ab, idx_ba = torch.from_numpy(idx_ab), torch.from_numpy(idx_ba)
        else:
            backend = resolve_backend("auto", a.device)
            idx_ab = nearest_indices(a.detach(), self.b, al, self.bl, backend, DEFAULT_MAX_TILE_ELEMENTS, both=False)[0]
            idx_ba = nearest_indices(bs, a.detach(), bsl, al, backend, DEFAULT_MAX_TILE_ELEMENTS, both=False)[0]
        value = 0.5 * (directed_mean(a, self.b, idx_ab, amask, al, squared, eps)
                       + directed_mean(bs, a, idx_ba, bsmask, bsl, squared, eps))
        return apply_reduction(value, reduction)
