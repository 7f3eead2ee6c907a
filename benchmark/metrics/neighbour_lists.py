"""Exact nearest neighbours of a fit's Chamfer term, answered from neighbour lists kept across
steps (compiled, numba): the Verlet lists of molecular dynamics.

A fit asks the same two questions at every Adam step, for every observed frame: the nearest observed
point of each mesh vertex, and the nearest mesh vertex of each observed point. Between two steps the
vertices move a little, so the answers rarely change. A list keeps, for each query, its ``K``
nearest candidates at the moment the list was made, and ``r``, the distance from the query to its
(K + 1)-th nearest point then. Every point outside the list was at least ``r`` away; if the query
and the points have moved by at most ``delta`` since, it is still at least ``r - delta`` away. So
where the nearest candidate now lies closer than ``r - delta`` (less a rounding slack), it is the
nearest point of the whole set: the answer is exact, from ``K`` distances instead of a search.
Where it does not, the query is answered by a search, as without lists.

- :class:`MovingQueryLists`: the points are fixed (the observation), the queries move (the mesh
  vertices); ``delta`` is each query's own displacement since its list was made. Where a few of a
  frame's queries fail the test, they get new lists at once (a KD-tree on the fixed points, built
  once).
- :class:`FixedQueryLists`: the queries are fixed (the observed points), the points move (the mesh
  vertices); ``delta`` is the largest displacement of any vertex of the frame since its lists were
  made. The queries that fail are answered by the caller's search.

Early in a fit the mesh moves far at every step and lists would be remade at every call, which
costs more than searching. So each frame has a schedule (:class:`_Schedule`): a frame where more
than ``REBUILD_SHARE`` of the queries fail gets new lists if its last ones held for ``MIN_LIFE``
calls; if they died younger, the frame is searched by the caller for a wait that doubles with each
early death (from ``MIN_LIFE`` up to ``MAX_WAIT`` calls), then tried again.

Distances are the float64 ``dx*dx + dy*dy + dz*dz`` of :mod:`benchmark.metrics.grid_nn`; a candidate
replaces the best only when strictly closer, so the answers are those of the grid or a KD-tree up to
which of several points at exactly the same distance is returned (the same distance, the same
Chamfer value).
"""

from __future__ import annotations

import numpy as np

from benchmark.metrics.grid_nn import HAVE_NUMBA, numba

K = 6  # candidates per query (memory: 4 B each; the slack r - d grows with K)
SLACK = 1e-9  # metres: covers the rounding of the tree's distances and of the displacements
REBUILD_SHARE = 0.1  # a frame whose failing share exceeds this gets new lists ...
MIN_LIFE = 4  # ... if its last ones held for this many calls; else it is searched for a wait, doubled per early death ...
MAX_WAIT = 64  # ... up to this many calls (the first lists are made after 2 x MIN_LIFE calls: a fit's start searches jump)


def _njit(fn):
    return numba.njit(cache=True, nogil=True)(fn) if HAVE_NUMBA else fn


@_njit
def _answer(q, n, i, cand, pts, lim, out, fail, nf):
    """Query (n, i): its list's nearest candidate into ``out`` if closer than ``lim`` (the bound
    less the displacement and the slack), else (n, i) into ``fail[nf]``. Returns the new ``nf``."""
    qx, qy, qz = q[n, i, 0], q[n, i, 1], q[n, i, 2]
    best, bd = -1, np.inf
    for k in range(cand.shape[2]):
        c = cand[n, i, k]
        if c < 0:
            break
        ex, ey, ez = pts[n, c, 0] - qx, pts[n, c, 1] - qy, pts[n, c, 2] - qz
        d = ex * ex + ey * ey + ez * ez
        if d < bd:
            bd, best = d, c
    if best >= 0 and lim > 0.0 and bd < lim * lim:
        out[n, i] = best
        return nf
    fail[nf, 0], fail[nf, 1] = n, i
    return nf + 1


@_njit
def _check_fixed_points(q, ql, ref, cand, bound, pts, live, out, fail):
    """MovingQueryLists: answer each valid query from its list where the bound, less the query's
    own displacement since, holds; the others' (element, query) pairs go to ``fail``. Elements with
    ``live[n]`` False are skipped. Returns the count of failures."""
    nf = 0
    for n in range(q.shape[0]):
        if not live[n]:
            continue
        for i in range(ql[n]):
            dx, dy, dz = q[n, i, 0] - ref[n, i, 0], q[n, i, 1] - ref[n, i, 1], q[n, i, 2] - ref[n, i, 2]
            nf = _answer(q, n, i, cand, pts, bound[n, i] - np.sqrt(dx * dx + dy * dy + dz * dz) - SLACK, out, fail, nf)
    return nf


@_njit
def _check_fixed_queries(q, ql, cand, bound, pts, delta, live, out, fail):
    """FixedQueryLists: as :func:`_check_fixed_points` with one displacement ``delta[n]`` per
    element (its points' largest)."""
    nf = 0
    for n in range(q.shape[0]):
        if not live[n]:
            continue
        for i in range(ql[n]):
            nf = _answer(q, n, i, cand, pts, bound[n, i] - delta[n] - SLACK, out, fail, nf)
    return nf


@_njit
def _max_displacement(pts, ref, lengths, delta):
    for n in range(pts.shape[0]):
        m = 0.0
        for i in range(lengths[n]):
            dx, dy, dz = pts[n, i, 0] - ref[n, i, 0], pts[n, i, 1] - ref[n, i, 1], pts[n, i, 2] - ref[n, i, 2]
            d = dx * dx + dy * dy + dz * dz
            if d > m:
                m = d
        delta[n] = np.sqrt(m)


def _lists(tree, queries: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """(candidates (m, K) int32, -1 past the points; bound (m,)) of ``queries`` against ``tree``."""
    from benchmark.metrics.chamfer import query_tree

    k = min(K + 1, n_points)
    cand = np.full((queries.shape[0], K), -1, dtype=np.int32)
    if k == 1:
        _, idx = query_tree(tree, queries, k=1)
        cand[:, 0] = idx
        return cand, np.full(queries.shape[0], np.inf)
    dist, idx = query_tree(tree, queries, k=k)
    kc = min(K, k)
    cand[:, :kc] = idx[:, :kc]
    bound = dist[:, K] if k == K + 1 else np.full(queries.shape[0], np.inf)  # all points listed: no outsider
    return cand, np.ascontiguousarray(bound, dtype=np.float64)


def _failures(fail: np.ndarray, nf: int) -> list[tuple[int, np.ndarray]]:
    """The failed queries grouped by element: [(n, query indices)]."""
    if nf == 0:
        return []
    f = fail[:nf]
    cuts = np.flatnonzero(np.diff(f[:, 0])) + 1
    return [(int(g[0, 0]), g[:, 1].copy()) for g in np.split(f, cuts)]


class _Schedule:
    """When each element's lists are made, kept, or given up for a while (module docstring)."""

    def __init__(self, n: int):
        self.live = np.zeros(n, dtype=np.bool_)  # the element has lists
        self.age = np.zeros(n, dtype=np.int64)  # calls since its lists were made or given up
        self.wait = np.full(n, 2 * MIN_LIFE, dtype=np.int64)  # calls to search it while it has none

    def tick(self) -> None:
        self.age += 1

    def made(self, n: int) -> None:
        self.live[n], self.age[n] = True, 0

    def dormant(self) -> list[int]:
        """The elements without lists: each ``"remake"`` now if its wait is over (it is made live),
        else searched whole by the caller."""
        return [int(n) for n in np.flatnonzero(~self.live)]

    def decide(self, n: int, failed: int, total: int) -> str:
        """``"keep"`` (a few failed: the caller mends them), ``"remake"`` (the element's lists are
        made again now) or ``"search"`` (the caller searches the whole element)."""
        if failed <= REBUILD_SHARE * total and self.live[n]:
            return "keep"
        if self.live[n]:
            if self.age[n] >= MIN_LIFE:
                self.wait[n] = MIN_LIFE  # they held: next time, remake at once
                return "remake"
            self.live[n], self.age[n] = False, 0  # died young: search it for a while
            self.wait[n] = min(2 * self.wait[n], MAX_WAIT)
            return "search"
        return "remake" if self.age[n] >= self.wait[n] else "search"


class MovingQueryLists:
    """Nearest fixed point (``points`` (N, M, 3) float64, valid prefixes ``lengths``) of moving
    queries: :meth:`nearest` at every step, exact (module docstring)."""

    def __init__(self, points: np.ndarray, lengths: np.ndarray):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.lengths = np.ascontiguousarray(lengths, dtype=np.int64)
        self._trees: dict = {}
        self._shape = None

    def _tree(self, n: int):
        from benchmark.metrics.chamfer import build_tree

        if n not in self._trees:
            self._trees[n] = build_tree(np.ascontiguousarray(self.points[n, : self.lengths[n]]))
        return self._trees[n]

    def _make(self, n: int, rows: np.ndarray, q: np.ndarray, out: np.ndarray) -> None:
        cand, bound = _lists(self._tree(n), np.ascontiguousarray(q[n, rows]), int(self.lengths[n]))
        self.cand[n, rows], self.bound[n, rows], self.ref[n, rows] = cand, bound, q[n, rows]
        out[n, rows] = cand[:, 0]

    def nearest(self, queries: np.ndarray, qlengths: np.ndarray, out: np.ndarray) -> list[int]:
        """Fill ``out`` (N, Q) int64 with the nearest point's index of each valid query of
        ``queries`` (N, Q, 3) float64 (valid prefixes ``qlengths``) where the lists answer; returns
        the elements left to the caller's search (every valid query of each)."""
        q = np.ascontiguousarray(queries, dtype=np.float64)
        ql = np.ascontiguousarray(qlengths, dtype=np.int64)
        if self._shape != (q.shape, tuple(ql.tolist())):  # first call, or new queries: no lists yet
            self._shape = (q.shape, tuple(ql.tolist()))
            self.cand = np.full(q.shape[:2] + (K,), -1, dtype=np.int32)
            self.bound = np.zeros(q.shape[:2])
            self.ref = q.copy()
            self.schedule = _Schedule(q.shape[0])
        fail = np.empty((int(ql.sum()), 2), dtype=np.int64)
        dormant = self.schedule.dormant()
        nf = _check_fixed_points(q, ql, self.ref, self.cand, self.bound, self.points, self.schedule.live, out, fail)
        self.schedule.tick()
        left = []
        for n in dormant:
            if self.schedule.decide(n, int(ql[n]), int(ql[n])) == "remake":
                self.schedule.made(n)
                self._make(n, np.arange(ql[n]), q, out)
            else:
                left.append(n)
        for n, rows in _failures(fail, nf):
            action = self.schedule.decide(n, rows.shape[0], int(ql[n]))
            if action == "search":
                left.append(n)
                continue
            if action == "remake":
                rows = np.arange(ql[n])
                self.schedule.made(n)
            self._make(n, rows, q, out)
        return left


class FixedQueryLists:
    """Nearest moving point of fixed queries (``queries`` (N, Q, 3) float64, valid prefixes
    ``qlengths``): :meth:`nearest` at every step answers what its lists can, exactly, and returns
    the queries left to the caller's search (module docstring)."""

    def __init__(self, queries: np.ndarray, qlengths: np.ndarray):
        self.queries = np.ascontiguousarray(queries, dtype=np.float64)
        self.qlengths = np.ascontiguousarray(qlengths, dtype=np.int64)
        self.cand = np.full(self.queries.shape[:2] + (K,), -1, dtype=np.int32)
        self.bound = np.zeros(self.queries.shape[:2])
        self.schedule = _Schedule(self.queries.shape[0])
        self.ref = None  # (N, M, 3) the points when each element's lists were made
        self._plengths = None

    def _make(self, n: int, pts: np.ndarray, plengths: np.ndarray) -> None:
        from benchmark.metrics.chamfer import build_tree

        m = int(plengths[n])
        tree = build_tree(np.ascontiguousarray(pts[n, :m]))
        rows = int(self.qlengths[n])
        self.cand[n, :rows], self.bound[n, :rows] = _lists(tree, self.queries[n, :rows], m)
        self.ref[n] = pts[n]
        self.schedule.made(n)

    def nearest(self, points: np.ndarray, plengths: np.ndarray,
                out: np.ndarray) -> tuple[list[tuple[int, np.ndarray]], list[int]]:
        """Fill ``out`` (N, Q) int64 where the lists answer for the points (N, M, 3) float64 (valid
        prefixes ``plengths``); returns the rest for the caller's search: [(element, query
        indices)] of elements with lists, and the elements to search whole."""
        pts = np.ascontiguousarray(points, dtype=np.float64)
        pl = np.ascontiguousarray(plengths, dtype=np.int64)
        if self.ref is None or self.ref.shape != pts.shape or not np.array_equal(self._plengths, pl):
            self.ref, self._plengths = pts.copy(), pl.copy()
            self.schedule = _Schedule(pts.shape[0])  # new points: no lists yet
        delta = np.zeros(pts.shape[0])
        _max_displacement(pts, self.ref, pl, delta)
        fail = np.empty((int(self.qlengths.sum()), 2), dtype=np.int64)
        dormant = self.schedule.dormant()
        nf = _check_fixed_queries(self.queries, self.qlengths, self.cand, self.bound, pts, delta, self.schedule.live,
                                  out, fail)
        self.schedule.tick()
        left, whole = [], []
        for n in dormant:
            if self.schedule.decide(n, int(self.qlengths[n]), int(self.qlengths[n])) == "remake":
                self._make(n, pts, pl)
                out[n, : self.qlengths[n]] = self.cand[n, : self.qlengths[n], 0]
            else:
                whole.append(n)
        for n, rows in _failures(fail, nf):
            action = self.schedule.decide(n, rows.shape[0], int(self.qlengths[n]))
            if action == "remake":
                self._make(n, pts, pl)
                out[n, : self.qlengths[n]] = self.cand[n, : self.qlengths[n], 0]
            elif action == "search":
                whole.append(n)
            else:
                left.append((n, rows))
        return left, whole
