"""Exact nearest neighbours on uniform grids, compiled (numba): the fit's Chamfer search.

A fit asks the same two questions at every Adam step, for every observed frame: the nearest
observed point of each mesh vertex, and the nearest mesh vertex of each observed point. The points
are a few hundred to ten thousand per frame, on one body's surface; a KD-tree answers each query
in 140-300 ns on this data, and rebuilding the vertices' tree at every step costs as much again.
A uniform grid over a frame's points, built by one counting sort (O(n)), answers a query near the
surface by scanning the few cells that meet a small cube about it, in compiled code, for a whole
batch of frames per call.

A point set that stays fixed while it is queried many times (a fit's observed points, up to
``CANDIDATE_MAX_POINTS`` per frame) can also carry a candidate grid (``candidates=True``): finer
cells, each listing, once it is first queried, every point that is the nearest of some position
in the cell (see :func:`_cell_candidates`). A query then reads one cell's list, 15-25 points on
body-like data, instead of searching: 2-3x faster once the cells it meets are filled.

Exactness: a query scans the cells that meet a cube about it (its half-side R starts from the
previous query's distance: queries come in a spatially coherent order), skipping a cell whose box
is farther than the best point found so far (less a rounding slack), and stops once that point
lies within R: every point outside the scanned cells lies outside the cube, farther than R. Else
R grows to the best distance (that cube holds the nearest point), or doubles while no point was
found; a query far from every point (its cube would span more than ``MAX_CELLS`` cells) is
answered by a KD-tree instead. So the answer is the nearest point of the whole set, whatever the
cell size; the cell size only sets the speed. Distances are the float64 ``dx*dx + dy*dy + dz*dz``
(the expression of scipy's and pykdtree's trees), and a point replaces the best one only when
strictly closer, so the only possible difference from a KD-tree is which of several points at
exactly the same distance is returned (the distance, and so the Chamfer value, is the same).

Without numba (``HAVE_NUMBA`` False) the callers keep their KD-tree path.
"""

from __future__ import annotations

import math

import numpy as np

try:  # numba is a dependency (pyproject); the KD-tree path remains for platforms without it
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None
    HAVE_NUMBA = False

POINTS_PER_CELL = 2.0  # mean points per cell of a grid's bounding box: sets the cell size (speed only)
MAX_CELLS_PER_POINT = 8  # the grid never has more cells than this many per point (plus 8)
CANDIDATE_CELLS_PER_POINT = 8  # a candidate grid never has more cells than this many per point (plus 64)
MAX_CELLS = 343  # a query whose search would span more cells than this with no point found goes to a KD-tree
UNRESOLVED = -2  # marks such a query between the compiled search and the KD-tree
CANDIDATE_MAX_POINTS = 2048  # fixed point sets up to this size per element get candidate grids (memory: 12 B a cell)


def _build(points, lengths, cells_per_point, points_per_cell):
    """Grids over each element's valid prefix of ``points`` (N, M, 3) float64.

    Returns ``geom`` (N, 7): origin xyz, cell size, cells per axis (as floats); ``cell_off`` (N + 1,)
    offsets of each element's cell-start table in ``starts``; ``starts`` (one entry per cell plus
    one per element): the first sorted position of each cell; ``index`` (sum of lengths,) the
    index within its element of the point at each sorted position (elements one after another);
    ``sorted_pts`` the points in that order (a cell's points are contiguous).
    """
    n_batch = points.shape[0]
    geom = np.empty((n_batch, 7))
    cell_off = np.zeros(n_batch + 1, dtype=np.int64)
    for n in range(n_batch):
        m = lengths[n]
        lo0 = lo1 = lo2 = math.inf
        hi0 = hi1 = hi2 = -math.inf
        for i in range(m):
            x, y, z = points[n, i, 0], points[n, i, 1], points[n, i, 2]
            lo0, lo1, lo2 = min(lo0, x), min(lo1, y), min(lo2, z)
            hi0, hi1, hi2 = max(hi0, x), max(hi1, y), max(hi2, z)
        e0, e1, e2 = hi0 - lo0, hi1 - lo1, hi2 - lo2
        emax = max(e0, e1, e2)
        if not emax > 0.0:
            emax = 1.0
        floor_ = emax * 1e-3  # a flat axis counts as a thousandth of the largest extent
        vol = max(e0, floor_) * max(e1, floor_) * max(e2, floor_)
        h = (vol * points_per_cell / max(m, 1)) ** (1.0 / 3.0)
        cap = cells_per_point * m + 8
        while True:
            d0 = int(e0 / h) + 1
            d1 = int(e1 / h) + 1
            d2 = int(e2 / h) + 1
            if d0 * d1 * d2 <= cap:
                break
            h *= 1.25
        geom[n, 0], geom[n, 1], geom[n, 2], geom[n, 3] = lo0, lo1, lo2, h
        geom[n, 4], geom[n, 5], geom[n, 6] = d0, d1, d2
        cell_off[n + 1] = cell_off[n] + d0 * d1 * d2 + 1
    total = 0
    for n in range(n_batch):
        total += lengths[n]
    starts = np.zeros(cell_off[n_batch], dtype=np.int64)
    index = np.empty(total, dtype=np.int64)
    sorted_pts = np.empty((total, 3))
    cell_of = np.empty(points.shape[1], dtype=np.int64)
    base = 0
    for n in range(n_batch):
        m = lengths[n]
        ox, oy, oz, h = geom[n, 0], geom[n, 1], geom[n, 2], geom[n, 3]
        d0, d1, d2 = int(geom[n, 4]), int(geom[n, 5]), int(geom[n, 6])
        c0 = cell_off[n]
        for i in range(m):
            i0 = min(max(int((points[n, i, 0] - ox) / h), 0), d0 - 1)
            i1 = min(max(int((points[n, i, 1] - oy) / h), 0), d1 - 1)
            i2 = min(max(int((points[n, i, 2] - oz) / h), 0), d2 - 1)
            c = (i0 * d1 + i1) * d2 + i2
            cell_of[i] = c
            starts[c0 + c + 1] += 1
        ncell = d0 * d1 * d2
        for c in range(ncell):
            starts[c0 + c + 1] += starts[c0 + c]
        for c in range(ncell + 1):
            starts[c0 + c] += base
        fill = starts[c0: c0 + ncell].copy()
        for i in range(m):
            c = cell_of[i]
            s = fill[c]
            fill[c] = s + 1
            index[s] = i
            sorted_pts[s, 0], sorted_pts[s, 1], sorted_pts[s, 2] = points[n, i, 0], points[n, i, 1], points[n, i, 2]
        base += m
    return geom, cell_off, starts, index, sorted_pts


def _build_candidates(geom, lengths, cells_per_point):
    """Empty candidate grids, one per element: each over its grid's box grown by one grid cell on
    every side, cells half a grid cell wide (wider where that would pass ``cells_per_point`` cells
    per point, plus 64). Returns ``cgeom`` (N, 7) as ``geom``, ``ccell_off`` (N + 1,), ``cstart``
    (-1: not filled yet) and ``ccount``."""
    n_batch = geom.shape[0]
    cgeom = np.empty((n_batch, 7))
    ccell_off = np.zeros(n_batch + 1, dtype=np.int64)
    for n in range(n_batch):
        h = geom[n, 3]
        e0, e1, e2 = geom[n, 4] * h + 2 * h, geom[n, 5] * h + 2 * h, geom[n, 6] * h + 2 * h
        hc = 0.5 * h
        cap = cells_per_point * lengths[n] + 64
        while True:
            k0, k1, k2 = int(e0 / hc) + 1, int(e1 / hc) + 1, int(e2 / hc) + 1
            if k0 * k1 * k2 <= cap:
                break
            hc *= 1.25
        cgeom[n, 0], cgeom[n, 1], cgeom[n, 2], cgeom[n, 3] = geom[n, 0] - h, geom[n, 1] - h, geom[n, 2] - h, hc
        cgeom[n, 4], cgeom[n, 5], cgeom[n, 6] = k0, k1, k2
        ccell_off[n + 1] = ccell_off[n] + k0 * k1 * k2
    cstart = np.full(ccell_off[n_batch], -1, dtype=np.int64)
    ccount = np.zeros(ccell_off[n_batch], dtype=np.int32)
    return cgeom, ccell_off, cstart, ccount


def _sqdist(pts, s, qx, qy, qz):
    """Squared distance from point ``s`` of ``pts`` to (qx, qy, qz), as the KD-trees compute it."""
    dx = pts[s, 0] - qx
    dy = pts[s, 1] - qy
    dz = pts[s, 2] - qz
    return dx * dx + dy * dy + dz * dz


def _cell_range(lo, hi, o, h, d):
    """Indices of the cells (of ``d`` along an axis from origin ``o``, width ``h``) that meet [lo, hi]."""
    a = min(max(int(math.floor((lo - o) / h)), 0), d - 1)
    b = min(max(int(math.floor((hi - o) / h)), 0), d - 1)
    return a, b


def _nearest(qx, qy, qz, ox, oy, oz, h, d0, d1, d2, starts, c0, pts, r0, max_cells, best0, bi0):
    """(sorted position, squared distance) of the nearest grid point to (qx, qy, qz).

    Scans the cells that meet the cube of half-side R about the query (R = ``r0`` first), skipping
    cells already scanned and cells farther than the best point so far; done once the best point
    is within R (every point outside the scanned cells lies outside the cube, farther than R).
    Otherwise R becomes the best distance (that cube holds the nearest point) or doubles while no
    point was found. ``bi0`` >= 0: a point known to lie within ``r0`` (a hint: its sorted position,
    ``best0`` its squared distance), so the first cube is the last, and the search starts from it
    as its best point, skipping the cells farther than it from the first (else -1 and inf).
    Returns (-1, inf) instead when the cube would span more than ``max_cells`` cells with no point
    found yet (the query is far from every point: the caller asks a KD-tree).
    """
    slack = 1e-9 * h + 1e-12
    best = best0
    bi = bi0
    r = r0
    conclusive = bi0 >= 0
    p0, q0, p1, q1, p2, q2 = 1, 0, 1, 0, 1, 0  # the block scanned so far (empty)
    while True:
        rr = r + slack
        a0, b0 = _cell_range(qx - rr, qx + rr, ox, h, d0)
        a1, b1 = _cell_range(qy - rr, qy + rr, oy, h, d1)
        a2, b2 = _cell_range(qz - rr, qz + rr, oz, h, d2)
        if bi < 0 and (b0 - a0 + 1) * (b1 - a1 + 1) * (b2 - a2 + 1) > max_cells:
            return -1, math.inf
        for j0 in range(a0, b0 + 1):
            g0 = max(max(ox + j0 * h - qx, qx - (ox + (j0 + 1) * h)) - slack, 0.0)
            g0 = g0 * g0
            if g0 >= best:  # no point of this slab of cells can be closer than the best so far
                continue
            in0 = p0 <= j0 <= q0
            for j1 in range(a1, b1 + 1):
                g1 = max(max(oy + j1 * h - qy, qy - (oy + (j1 + 1) * h)) - slack, 0.0)
                g1 = g0 + g1 * g1
                if g1 >= best:
                    continue
                in1 = in0 and p1 <= j1 <= q1
                for j2 in range(a2, b2 + 1):
                    if in1 and p2 <= j2 <= q2:  # scanned in an earlier pass
                        continue
                    g2 = max(max(oz + j2 * h - qz, qz - (oz + (j2 + 1) * h)) - slack, 0.0)
                    if g1 + g2 * g2 >= best:
                        continue
                    c = c0 + (j0 * d1 + j1) * d2 + j2
                    for s in range(starts[c], starts[c + 1]):
                        d = _sqdist(pts, s, qx, qy, qz)
                        if d < best:
                            best = d
                            bi = s
        if best <= r * r or conclusive:
            break
        if a0 == 0 and a1 == 0 and a2 == 0 and b0 == d0 - 1 and b1 == d1 - 1 and b2 == d2 - 1:
            break  # every cell scanned
        p0, q0, p1, q1, p2, q2 = a0, b0, a1, b1, a2, b2
        if bi >= 0:  # the cube of half-side the best distance (plus the slack) holds the nearest point
            r = math.sqrt(best)
            conclusive = True
        else:
            r = 2.0 * r
    return bi, best


def _positions(index, lengths):
    """The inverse of ``index``: per element (one after another), the sorted position of each of
    its points."""
    where = np.empty(index.shape[0], dtype=np.int64)
    base = 0
    for n in range(lengths.shape[0]):
        for s in range(base, base + lengths[n]):
            where[base + index[s]] = s
        base += lengths[n]
    return where


def _query(queries, qlengths, order, max_cells, hints, where, lengths, geom, cell_off, starts, index, sorted_pts, out):
    """``out[n, i]``: the index (in element n's valid prefix) of the nearest grid point of each valid
    ``queries[n, i]``, taken in the order ``order[n, :qlengths[n]]`` (a permutation of the valid
    positions: queries near each other one after another touch the same cells); padded positions
    are left as they are. ``hints[n, i]`` >= 0: a point of the element (an index into
    ``points[n]``) near the query, e.g. its answer at the previous optimiser step: its distance
    bounds the search. A query :func:`_nearest` leaves (far from every point) gets
    ``UNRESOLVED``; returns how many did."""
    far = 0
    base = 0
    for n in range(queries.shape[0]):
        ox, oy, oz, h = geom[n, 0], geom[n, 1], geom[n, 2], geom[n, 3]
        d0, d1, d2 = int(geom[n, 4]), int(geom[n, 5]), int(geom[n, 6])
        c0 = cell_off[n]
        r = 0.5 * h
        for k in range(qlengths[n]):
            i = order[n, k]
            qx, qy, qz = queries[n, i, 0], queries[n, i, 1], queries[n, i, 2]
            j = hints[n, i]
            if j >= 0:
                s0 = where[base + j]  # the previous answer: its distance bounds the search, and it is the best so far
                d = _sqdist(sorted_pts, s0, qx, qy, qz)
                s, d = _nearest(qx, qy, qz, ox, oy, oz, h, d0, d1, d2, starts, c0, sorted_pts, math.sqrt(d), max_cells,
                                d, s0)
            else:
                s, d = _nearest(qx, qy, qz, ox, oy, oz, h, d0, d1, d2, starts, c0, sorted_pts, r, max_cells,
                                math.inf, -1)
            if s < 0:
                out[n, i] = UNRESOLVED
                far += 1
            else:
                out[n, i] = index[s]
                r = max(1.25 * math.sqrt(d), 1e-3 * h)  # the next query (in spatial order) starts from this one's distance
        base += lengths[n]
    return far


def _cell_candidates(n, c, j0, j1, j2, cgeom, geom, cell_off, starts, sorted_pts, cstart, ccount, pool, used):
    """Fill candidate cell ``c`` (index (j0, j1, j2) of element n's candidate grid): every point
    that is the nearest of some position in the cell's box. With p the nearest point of the box's
    centre and U the distance from p to the box's farthest corner, every position in the box has a
    point within U, so its nearest point lies within U of the box: the candidates are the points
    whose distance to the box is at most U (plus a rounding slack). Returns (pool, used)."""
    hc = cgeom[n, 3]
    lx, ly, lz = cgeom[n, 0] + j0 * hc, cgeom[n, 1] + j1 * hc, cgeom[n, 2] + j2 * hc
    ux, uy, uz = lx + hc, ly + hc, lz + hc
    ox, oy, oz, h = geom[n, 0], geom[n, 1], geom[n, 2], geom[n, 3]
    d0, d1, d2 = int(geom[n, 4]), int(geom[n, 5]), int(geom[n, 6])
    c0 = cell_off[n]
    cx, cy, cz = lx + 0.5 * hc, ly + 0.5 * hc, lz + 0.5 * hc
    s_best, _ = _nearest(cx, cy, cz, ox, oy, oz, h, d0, d1, d2, starts, c0, sorted_pts, 0.5 * h, 1 << 62,
                         math.inf, -1)
    px, py, pz = sorted_pts[s_best, 0], sorted_pts[s_best, 1], sorted_pts[s_best, 2]
    fx = max(abs(px - lx), abs(px - ux))
    fy = max(abs(py - ly), abs(py - uy))
    fz = max(abs(pz - lz), abs(pz - uz))
    u = math.sqrt(fx * fx + fy * fy + fz * fz) * (1.0 + 1e-9) + 1e-12
    u2 = u * u
    a0, b0 = _cell_range(lx - u, ux + u, ox, h, d0)
    a1, b1 = _cell_range(ly - u, uy + u, oy, h, d1)
    a2, b2 = _cell_range(lz - u, uz + u, oz, h, d2)
    start = used
    for k0 in range(a0, b0 + 1):
        for k1 in range(a1, b1 + 1):
            for k2 in range(a2, b2 + 1):
                g = c0 + (k0 * d1 + k1) * d2 + k2
                for s in range(starts[g], starts[g + 1]):
                    x, y, z = sorted_pts[s, 0], sorted_pts[s, 1], sorted_pts[s, 2]
                    ex = max(lx - x, 0.0, x - ux)
                    ey = max(ly - y, 0.0, y - uy)
                    ez = max(lz - z, 0.0, z - uz)
                    if ex * ex + ey * ey + ez * ez <= u2:
                        if used == pool.shape[0]:
                            grown = np.empty(2 * pool.shape[0] + 1024, dtype=np.int64)
                            grown[:used] = pool[:used]
                            pool = grown
                        pool[used] = s
                        used += 1
    cstart[c] = start
    ccount[c] = used - start
    return pool, used


def _query_cached(queries, qlengths, order, max_cells, geom, cell_off, starts, index, sorted_pts,
                  cgeom, ccell_off, cstart, ccount, pool, used, out):
    """:func:`_query` through the candidate grids (cells filled on first use); a query outside its
    element's candidate grid takes the cube search. Returns (pool, used, number unresolved)."""
    far = 0
    for n in range(queries.shape[0]):
        ox, oy, oz, h = geom[n, 0], geom[n, 1], geom[n, 2], geom[n, 3]
        d0, d1, d2 = int(geom[n, 4]), int(geom[n, 5]), int(geom[n, 6])
        c0 = cell_off[n]
        gx, gy, gz, hc = cgeom[n, 0], cgeom[n, 1], cgeom[n, 2], cgeom[n, 3]
        e0, e1, e2 = int(cgeom[n, 4]), int(cgeom[n, 5]), int(cgeom[n, 6])
        k0 = ccell_off[n]
        for k in range(qlengths[n]):
            i = order[n, k]
            qx, qy, qz = queries[n, i, 0], queries[n, i, 1], queries[n, i, 2]
            j0 = int(math.floor((qx - gx) / hc))
            j1 = int(math.floor((qy - gy) / hc))
            j2 = int(math.floor((qz - gz) / hc))
            if j0 < 0 or j0 >= e0 or j1 < 0 or j1 >= e1 or j2 < 0 or j2 >= e2:
                s, _ = _nearest(qx, qy, qz, ox, oy, oz, h, d0, d1, d2, starts, c0, sorted_pts, 0.5 * h, max_cells,
                                math.inf, -1)
                if s < 0:
                    out[n, i] = UNRESOLVED
                    far += 1
                else:
                    out[n, i] = index[s]
                continue
            c = k0 + (j0 * e1 + j1) * e2 + j2
            if cstart[c] < 0:
                pool, used = _cell_candidates(n, c, j0, j1, j2, cgeom, geom, cell_off, starts, sorted_pts,
                                              cstart, ccount, pool, used)
            best = math.inf
            bs = -1
            for t in range(cstart[c], cstart[c] + ccount[c]):
                s = pool[t]
                d = _sqdist(sorted_pts, s, qx, qy, qz)
                if d < best:
                    best = d
                    bs = s
            out[n, i] = index[bs]
    return pool, used, far


if HAVE_NUMBA:
    _jit = numba.njit(cache=True, nogil=True, error_model="numpy")  # no fastmath: the same doubles as the trees
    _inline = numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
    _build = _jit(_build)
    _sqdist = _inline(_sqdist)
    _cell_range = _inline(_cell_range)
    _nearest = _inline(_nearest)
    _positions = _jit(_positions)
    _query = _jit(_query)
    _build_candidates = _jit(_build_candidates)
    _cell_candidates = _jit(_cell_candidates)
    _query_cached = _jit(_query_cached)


class PointGrids:
    """Uniform grids over a batch of point sets (N, M, 3) with valid-prefix ``lengths`` (N,):
    :meth:`nearest` answers exact nearest-neighbour queries (see the module docstring)."""

    def __init__(self, points: np.ndarray, lengths: np.ndarray, candidates: bool = False):
        if not HAVE_NUMBA:
            raise RuntimeError("PointGrids needs numba (pip install numba); the callers fall back to KD-trees without it.")
        points = np.ascontiguousarray(points, dtype=np.float64)
        lengths = np.ascontiguousarray(lengths, dtype=np.int64)
        if points.ndim != 3 or points.shape[2] != 3 or lengths.shape != (points.shape[0],):
            raise ValueError(f"PointGrids: points must be (N, M, 3) and lengths (N,); got {points.shape} and {lengths.shape}.")
        if (lengths < 1).any() or (lengths > points.shape[1]).any():
            raise ValueError(f"PointGrids: every length must be in [1, {points.shape[1]}]; got {lengths.tolist()}.")
        self.lengths = lengths
        self.points = points
        self._trees = {}
        self._grids = _build(points, lengths, MAX_CELLS_PER_POINT, POINTS_PER_CELL)
        self._where = None  # each point's sorted position (for hints), made on first need
        self._cand = None
        if candidates:
            self._cand = _build_candidates(self._grids[0], lengths, CANDIDATE_CELLS_PER_POINT)
            self._pool = np.empty(4096, dtype=np.int64)
            self._used = 0

    def nearest(self, queries: np.ndarray, qlengths: np.ndarray, order: np.ndarray | None = None,
                out: np.ndarray | None = None, hints: np.ndarray | None = None) -> np.ndarray:
        """(N, Mq) int64: the index (within its element's valid prefix) of the nearest point of
        each valid query of ``queries`` (N, Mq, 3) float64; -1 at padded positions (or ``out``'s
        values there). ``order`` (N, Mq) int64: per element, the valid positions in the order to
        query them (any order gives the same answers; a spatially coherent one is faster).
        ``hints`` (N, Mq) int64: per query, a point index to start from (-1: none), e.g. the
        previous step's answers; any hints give the same answers (faster when they are near). A
        grid with candidate lists needs none and ignores them."""
        queries = np.ascontiguousarray(queries, dtype=np.float64)
        qlengths = np.ascontiguousarray(qlengths, dtype=np.int64)
        if queries.ndim != 3 or queries.shape[0] != self.lengths.shape[0] or queries.shape[2] != 3:
            raise ValueError(f"PointGrids.nearest: queries must be ({self.lengths.shape[0]}, M, 3); got {queries.shape}.")
        if (qlengths < 0).any() or (qlengths > queries.shape[1]).any():
            raise ValueError(f"PointGrids.nearest: every query length must be in [0, {queries.shape[1]}]; got {qlengths.tolist()}.")
        if order is None:
            order = np.broadcast_to(np.arange(queries.shape[1], dtype=np.int64), queries.shape[:2])
        order = np.ascontiguousarray(order, dtype=np.int64)
        if order.shape != queries.shape[:2] or (order.size and (order.min() < 0 or order.max() >= queries.shape[1])):
            raise ValueError(f"PointGrids.nearest: order must be ({queries.shape[0]}, {queries.shape[1]}) positions in "
                             f"[0, {queries.shape[1]}); got shape {order.shape}.")
        if out is None:
            out = np.full(queries.shape[:2], -1, dtype=np.int64)
        if self._cand is None:
            if hints is None:
                hints = np.full(queries.shape[:2], -1, dtype=np.int64)
            hints = np.ascontiguousarray(hints, dtype=np.int64)
            if hints.shape != queries.shape[:2] or bool((hints >= self.lengths[:, None]).any()):
                raise ValueError(f"PointGrids.nearest: hints must be ({queries.shape[0]}, {queries.shape[1]}) indices "
                                 f"below each element's length (or -1); got shape {hints.shape}.")
            if self._where is None:
                self._where = _positions(self._grids[3], self.lengths)
            far = _query(queries, qlengths, order, MAX_CELLS, hints, self._where, self.lengths, *self._grids, out)
        else:
            self._pool, self._used, far = _query_cached(queries, qlengths, order, MAX_CELLS, *self._grids, *self._cand,
                                                        self._pool, self._used, out)
        if far:
            self._resolve_far(queries, out)
        return out

    def _resolve_far(self, queries: np.ndarray, out: np.ndarray) -> None:
        """Answer the queries the grid left (far from every point) with a KD-tree on the element's
        points (built on first need, kept for the grid's life)."""
        from benchmark.metrics.chamfer import build_tree, query_tree

        for n in np.flatnonzero((out == UNRESOLVED).any(axis=1)).tolist():
            rows = np.flatnonzero(out[n] == UNRESOLVED)
            tree = self._trees.get(n)
            if tree is None:
                tree = self._trees[n] = build_tree(np.ascontiguousarray(self.points[n, : self.lengths[n]]))
            out[n, rows] = query_tree(tree, np.ascontiguousarray(queries[n, rows]))[1]
