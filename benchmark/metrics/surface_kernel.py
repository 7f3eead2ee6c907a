"""Compiled scan -> surface distance for the evaluation (numba), bit-identical to the array path.

:func:`scan_to_surface_knn` is the per-frame kernel behind
:func:`benchmark.protocols.completion_unit.evaluate`'s surface Chamfer column: for each scan point,
the minimum of its nearest-vertex distance and its exact distance to every triangle incident to
its ``k`` nearest mesh vertices. It does the float64 operations of
:func:`benchmark.metrics.surface.distance_to_prepared_soa` (Ericson's closest point on a triangle,
the same expressions in the same order, no fused multiply-add, no reassociation: numba compiles
without ``fastmath``), so every distance it keeps is the same double, and the minimum of the same
set is the same double. What it saves is work, never a candidate that could be the minimum:

- a triangle met through several of the ``k`` vertices is measured once (a per-triangle stamp);
- the nearest vertex's triangles come first, so the running minimum is tight early, and a triangle
  is skipped when a lower bound on its distance (to its centroid's sphere: ``|p - c| - r``) exceeds
  the running minimum by more than 1e-9 m: such a triangle can never lower it;
- the triangles' constants are computed in compiled code, once per frame.

Without numba (``HAVE_NUMBA`` False) the caller keeps the array path; the tests compare both with
the reference on the same meshes.
"""

from __future__ import annotations

import math

import numpy as np

try:  # numba is a dependency (pyproject); the array path remains for platforms without it
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None
    HAVE_NUMBA = False

EPS64 = float(np.finfo(np.float64).eps)
SKIP_SLACK_M = 1e-9  # a triangle is skipped only when its lower bound exceeds the running minimum by this


def _sdiv(num, den):
    """num / den with den = 0 read as 1 (``surface._safe_div``)."""
    return num / (1.0 if den == 0.0 else den)


def _segment(px, py, pz, ax, ay, az, bx, by, bz):
    """``surface._point_segment_distance`` for one point and one segment."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    t = _sdiv(apx * abx + apy * aby + apz * abz, abx * abx + aby * aby + abz * abz)
    t = min(max(t, 0.0), 1.0)
    dx, dy, dz = apx - t * abx, apy - t * aby, apz - t * abz
    return math.sqrt(dx * dx + dy * dy + dz * dz)


def _prepare(verts, faces, tri, bound):
    """Per-triangle constants (``surface.prepare_triangles_soa``: a, ab, ac, |ab|^2, |ac|^2,
    ab.ac, degenerate flag) into ``tri`` (F, 13), and the centroid-sphere bound (cx, cy, cz, r)
    into ``bound`` (F, 4)."""
    for f in range(faces.shape[0]):
        ia, ib, ic = faces[f, 0], faces[f, 1], faces[f, 2]
        ax, ay, az = verts[ia, 0], verts[ia, 1], verts[ia, 2]
        bx, by, bz = verts[ib, 0], verts[ib, 1], verts[ib, 2]
        cx, cy, cz = verts[ic, 0], verts[ic, 1], verts[ic, 2]
        abx, aby, abz = bx - ax, by - ay, bz - az
        acx, acy, acz = cx - ax, cy - ay, cz - az
        bcx, bcy, bcz = cx - bx, cy - by, cz - bz
        ab2 = abx * abx + aby * aby + abz * abz
        ac2 = acx * acx + acy * acy + acz * acz
        abac = abx * acx + aby * acy + abz * acz
        nx, ny, nz = aby * acz - abz * acy, abz * acx - abx * acz, abx * acy - aby * acx
        area2 = nx * nx + ny * ny + nz * nz
        scale = max(max(ab2, ac2), bcx * bcx + bcy * bcy + bcz * bcz)
        tri[f, 0], tri[f, 1], tri[f, 2] = ax, ay, az
        tri[f, 3], tri[f, 4], tri[f, 5] = abx, aby, abz
        tri[f, 6], tri[f, 7], tri[f, 8] = acx, acy, acz
        tri[f, 9], tri[f, 10], tri[f, 11] = ab2, ac2, abac
        tri[f, 12] = 1.0 if area2 <= EPS64 * (scale * scale) else 0.0
        gx, gy, gz = (ax + bx + cx) / 3.0, (ay + by + cy) / 3.0, (az + bz + cz) / 3.0
        r2 = (ax - gx) ** 2 + (ay - gy) ** 2 + (az - gz) ** 2
        r2 = max(r2, (bx - gx) ** 2 + (by - gy) ** 2 + (bz - gz) ** 2)
        r2 = max(r2, (cx - gx) ** 2 + (cy - gy) ** 2 + (cz - gz) ** 2)
        # the radius is rounded up a little so that the bound stays a lower bound after rounding
        bound[f, 0], bound[f, 1], bound[f, 2], bound[f, 3] = gx, gy, gz, math.sqrt(r2) * (1.0 + 1e-12)


def _triangle_distance(px, py, pz, tri, f):
    """``surface.distance_to_prepared_soa`` for one point and one prepared triangle (NaN -> inf)."""
    ax, ay, az = tri[f, 0], tri[f, 1], tri[f, 2]
    abx, aby, abz = tri[f, 3], tri[f, 4], tri[f, 5]
    acx, acy, acz = tri[f, 6], tri[f, 7], tri[f, 8]
    ab2, ac2, abac = tri[f, 9], tri[f, 10], tri[f, 11]
    apx, apy, apz = px - ax, py - ay, pz - az
    if tri[f, 12] > 0.0:  # (nearly) zero area: the three edges
        bx, by, bz = ax + abx, ay + aby, az + abz
        cx, cy, cz = ax + acx, ay + acy, az + acz
        d = min(min(_segment(px, py, pz, ax, ay, az, bx, by, bz), _segment(px, py, pz, bx, by, bz, cx, cy, cz)),
                _segment(px, py, pz, cx, cy, cz, ax, ay, az))
        return d if d == d else math.inf
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    d3, d4 = d1 - ab2, d2 - abac
    d5, d6 = d1 - abac, d2 - ac2
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    # the array path's last matching region wins: vertex A, vertex B, edge AB, vertex C, edge AC,
    # edge BC, interior
    if d1 <= 0.0 and d2 <= 0.0:
        v, w = 0.0, 0.0
    elif d3 >= 0.0 and d4 <= d3:
        v, w = 1.0, 0.0
    elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v, w = _sdiv(d1, d1 - d3), 0.0
    elif d6 >= 0.0 and d5 <= d6:
        v, w = 0.0, 1.0
    elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        v, w = 0.0, _sdiv(d2, d2 - d6)
    elif va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
        t = _sdiv(d4 - d3, (d4 - d3) + (d5 - d6))
        v, w = 1.0 - t, t
    else:
        denom = va + vb + vc
        v, w = _sdiv(vb, denom), _sdiv(vc, denom)
    dx = apx - v * abx - w * acx
    dy = apy - v * aby - w * acy
    dz = apz - v * abz - w * acz
    d = math.sqrt(dx * dx + dy * dy + dz * dz)
    return d if d == d else math.inf


def _scan_to_surface_knn(points, verts, faces, vertex_faces, knn, vertex_distance):
    n_points, k = knn.shape
    n_faces = faces.shape[0]
    width = vertex_faces.shape[1]
    tri = np.empty((n_faces, 13))
    bound = np.empty((n_faces, 4))
    _prepare(verts, faces, tri, bound)
    stamp = np.full(n_faces, -1, dtype=np.int64)
    best = vertex_distance.copy()
    for p in range(n_points):
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        b = best[p]
        for j in range(k):
            vtx = knn[p, j]
            for s in range(width):
                f = vertex_faces[vtx, s]
                if f >= n_faces:
                    break  # padding (the faces of a vertex come first)
                if stamp[f] == p:
                    continue
                stamp[f] = p
                gx, gy, gz = px - bound[f, 0], py - bound[f, 1], pz - bound[f, 2]
                if math.sqrt(gx * gx + gy * gy + gz * gz) - bound[f, 3] > b + SKIP_SLACK_M:
                    continue
                d = _triangle_distance(px, py, pz, tri, f)
                if d < b:
                    b = d
        best[p] = b
    return best


if HAVE_NUMBA:
    _jit = numba.njit(cache=True, nogil=True)
    _sdiv = _jit(_sdiv)
    _segment = _jit(_segment)
    _prepare = _jit(_prepare)
    _triangle_distance = _jit(_triangle_distance)
    _scan_to_surface_knn = _jit(_scan_to_surface_knn)


def scan_to_surface_knn(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, vertex_faces: np.ndarray,
                        knn: np.ndarray, vertex_distance: np.ndarray) -> np.ndarray:
    """(P,) float64: per scan point, min(vertex distance, exact distance to the triangles incident
    to its ``knn`` vertices). points (P, 3), vertices (V, 3) (float64, or float32 read exactly as
    float64), faces (F, 3) int64, vertex_faces (V, width) int64 (each row's faces first, then
    padding >= F), knn (P, k) int64, vertex_distance (P,) float64. Needs numba (``HAVE_NUMBA``)."""
    if not HAVE_NUMBA:
        raise RuntimeError("scan_to_surface_knn needs numba (pip install numba); the evaluation falls back to "
                           "its array path without it")
    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    i64 = lambda a: np.ascontiguousarray(a, dtype=np.int64)  # noqa: E731
    return _scan_to_surface_knn(f64(points), f64(vertices), i64(faces), i64(vertex_faces), i64(knn),
                                f64(vertex_distance))
