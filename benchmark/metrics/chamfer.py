"""Chamfer distance between padded batches of point sets, as docs/protocol.md defines it.

    chamfer(A, B) = 0.5 * (mean_{a in A} min_{b in B} |a - b| + mean_{b in B} min_{a in A} |b - a|)

with Euclidean (not squared) distances, in metres. Point sets are padded batches: ``a`` (N, P, 3)
and ``b`` (N, Q, 3) with optional valid-prefix lengths (N,); element ``n`` uses
``a[n, :a_lengths[n]]`` and ``b[n, :b_lengths[n]]`` and ignores the padding, whatever it holds.

Nearest neighbours are found without autograd by one of four interchangeable backends, then the
matched pairs are gathered and their distances computed in torch, so gradients flow to both
point sets (:func:`chamfer_loss`):

- ``"kdtree"``: ``pykdtree`` per batch element, float64 (CPU; elements run in parallel threads,
  the build and query release the GIL; pykdtree's own OpenMP threads default to one, see
  :func:`pykdtree_class`). Falls back to ``"scipy"`` where pykdtree is not installed.
- ``"scipy"``: scipy ``cKDTree`` per batch element, float64: the reference implementation the
  ``"kdtree"`` backend is tested against (the project's exact path before pykdtree).
- ``"tiled"``: brute force in torch over tiles of query points, so that the distance tile never
  holds more than ``max_tile_elements`` numbers (bounded memory; meant for CUDA, works on CPU).
- ``"naive"``: the full (N, P, Q) distance matrix with ``torch.cdist``; the reference for tests.
- ``"auto"``: ``"kdtree"`` for CPU tensors, ``"tiled"`` otherwise.

Both KD-tree backends are exact in float64: they return the same nearest neighbours (up to exact
ties), so the loss, its gradient and every metric are unchanged by the choice.
:class:`benchmark.metrics.static_chamfer.StaticChamfer` is :func:`chamfer_loss` against a point set that does not change between
calls (the observed points of a fit): their search structures are built once, not at every
optimiser step, and its neighbours come from compiled grids (:mod:`benchmark.metrics.grid_nn`),
exact as the trees are.

All backends return the same distances; where a query point has two equidistant nearest
neighbours they may pick different ones (same value, different gradient). In float32 the tiled
backend ranks candidates with ``|b|^2 - 2 a.b`` after centring each element on its mean, which
can swap two neighbours whose squared distances differ by less than about 1e-7 times the squared
extent of the cloud (about 1e-7 m^2 for a body; the returned
distance is still computed exactly from the chosen pair).
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from scipy.spatial import cKDTree

BACKENDS = ("auto", "kdtree", "scipy", "tiled", "naive")
REDUCTIONS = ("none", "mean", "sum")
DEFAULT_MAX_TILE_ELEMENTS = 2**26
DEFAULT_EPS = 1e-12  # m^2; floor under squared distances before sqrt in the loss (sqrt'(0) = inf)

# Measured on body-sized clouds (10k-14k points, 2 cores): sliding-midpoint trees with 32-point
# leaves built and queried fastest of the options tried (scipy defaults: leafsize 16, median splits).
_KDTREE_OPTIONS = dict(leafsize=32, balanced_tree=False, compact_nodes=True)
_PYKDTREE_LEAFSIZE = 16
_PYKDTREE = None  # the pykdtree KDTree class once imported; False when not installed


def pykdtree_class():
    """pykdtree's ``KDTree`` class, or None where pykdtree is not installed.

    pykdtree parallelises each query with OpenMP (its own libgomp, read once at import). This
    module already runs one batch element per thread, so unless the user set ``OMP_NUM_THREADS``
    the import makes pykdtree single-threaded (on 2 cores, two threads each running a team of two
    only oversubscribe). Results never depend on the thread count: every query is independent.
    """
    global _PYKDTREE
    if _PYKDTREE is None:
        had = "OMP_NUM_THREADS" in os.environ
        if not had:
            os.environ["OMP_NUM_THREADS"] = "1"
        try:
            from pykdtree.kdtree import KDTree
            _PYKDTREE = KDTree
        except ImportError:
            _PYKDTREE = False
        finally:
            if not had:
                del os.environ["OMP_NUM_THREADS"]
    return _PYKDTREE or None


def build_tree(points: np.ndarray):
    """A KD-tree on (n, 3) float64 points: pykdtree where installed, else scipy cKDTree.
    Query it with :func:`query_tree`."""
    kd = pykdtree_class()
    if kd is None:
        return cKDTree(points, **_KDTREE_OPTIONS)
    return kd(points, leafsize=_PYKDTREE_LEAFSIZE)


def query_tree(tree, queries: np.ndarray, k: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(distances, int64 indices) of the ``k`` nearest tree points of each (m, 3) float64 query
    ((m,) arrays for k = 1, else (m, k)), on one thread."""
    if isinstance(tree, cKDTree):
        d, i = tree.query(queries, k=k, workers=1)
        return d, np.asarray(i, dtype=np.int64)
    d, i = tree.query(queries, k=k)
    return d, i.astype(np.int64)


def morton_order(points: np.ndarray) -> np.ndarray:
    """A permutation of (n, 3) points along a Z-order (Morton) curve, 10 bits per axis.

    Queries issued in this order touch the same tree leaves one after another (cache locality);
    any order gives the same answers."""
    if points.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    lo = points.min(0)
    extent = float((points.max(0) - lo).max()) or 1.0
    q = np.clip((points - lo) * (1023.0 / extent), 0, 1023).astype(np.uint64)

    def spread(x):
        x = (x | (x << np.uint64(16))) & np.uint64(0x030000FF)
        x = (x | (x << np.uint64(8))) & np.uint64(0x0300F00F)
        x = (x | (x << np.uint64(4))) & np.uint64(0x030C30C3)
        return (x | (x << np.uint64(2))) & np.uint64(0x09249249)

    code = spread(q[:, 0]) | (spread(q[:, 1]) << np.uint64(1)) | (spread(q[:, 2]) << np.uint64(2))
    return np.argsort(code, kind="stable")


# ----------------------------------------------------------------------------- validation


def validate_points(x, name: str, caller: str) -> None:
    """Raise ValueError unless ``x`` is a floating (N, P, 3) tensor."""
    if not isinstance(x, torch.Tensor):
        raise ValueError(f"{caller}: `{name}` must be a torch.Tensor of shape (N, P, 3) in metres; got {type(x).__name__}.")
    if x.dim() != 3 or x.shape[-1] != 3:
        hint = f" Add a batch dimension with `{name}[None]`." if x.dim() == 2 and x.shape[-1] == 3 else ""
        raise ValueError(
            f"{caller}: `{name}` must have shape (N, P, 3) (batch, points, xyz in metres); got {tuple(x.shape)}.{hint}"
        )
    if not x.is_floating_point():
        raise ValueError(f"{caller}: `{name}` must be a floating-point tensor; got dtype {x.dtype}.")


def validate_lengths(lengths, name: str, caller: str, batch: int, size: int, device) -> torch.Tensor:
    """Return ``lengths`` as a (N,) long tensor on ``device`` (all ``size`` when None); raise on bad input.

    Every element must have at least one valid point: the Chamfer distance of an empty set is
    undefined, and a bad input never produces a number.
    """
    if lengths is None:
        if size < 1:
            raise ValueError(f"{caller}: the point dimension behind `{name}` is empty (size 0); every element needs points.")
        return torch.full((batch,), size, dtype=torch.long, device=device)
    if not isinstance(lengths, torch.Tensor):
        raise ValueError(f"{caller}: `{name}` must be a (N,) integer torch.Tensor of valid prefix lengths or None.")
    if lengths.shape != (batch,):
        raise ValueError(f"{caller}: `{name}` must have shape (N,) = ({batch},); got {tuple(lengths.shape)}.")
    if lengths.is_floating_point() or lengths.is_complex() or lengths.dtype == torch.bool:
        raise ValueError(f"{caller}: `{name}` must be an integer tensor (torch.long); got dtype {lengths.dtype}.")
    lo, hi = int(lengths.min()), int(lengths.max())
    if lo < 1 or hi > size:
        raise ValueError(
            f"{caller}: `{name}` must lie in [1, {size}] (at least one valid point, at most the padded size); "
            f"got values in [{lo}, {hi}]."
        )
    return lengths.to(device=device, dtype=torch.long)


def prefix_mask(lengths: torch.Tensor, size: int) -> torch.Tensor:
    """(N, size) bool, True on the valid prefix of each element."""
    return torch.arange(size, device=lengths.device)[None, :] < lengths[:, None]


def _validate_pair(a, b, a_lengths, b_lengths, caller: str, names=("a", "b")):
    na, nb = names
    validate_points(a, na, caller)
    validate_points(b, nb, caller)
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"{caller}: `{na}` and `{nb}` must have the same batch size N; got {a.shape[0]} and {b.shape[0]}.")
    if a.device != b.device or a.dtype != b.dtype:
        raise ValueError(
            f"{caller}: `{na}` and `{nb}` must share device and dtype; got {a.device}/{a.dtype} and {b.device}/{b.dtype}."
        )
    if a.shape[0] == 0:
        raise ValueError(f"{caller}: empty batch (N = 0).")
    al = validate_lengths(a_lengths, f"{na}_lengths", caller, a.shape[0], a.shape[1], a.device)
    bl = validate_lengths(b_lengths, f"{nb}_lengths", caller, b.shape[0], b.shape[1], b.device)
    return al, bl


def _validate_options(backend: str, max_tile_elements: int, caller: str) -> None:
    if backend not in BACKENDS:
        raise ValueError(f"{caller}: `backend` must be one of {BACKENDS}; got {backend!r}.")
    if not isinstance(max_tile_elements, int) or max_tile_elements < 1:
        raise ValueError(f"{caller}: `max_tile_elements` must be a positive int; got {max_tile_elements!r}.")


def clean_padding(x: torch.Tensor, lengths: torch.Tensor, name: str, caller: str):
    """Check the valid points are finite and zero the padding, so that whatever the padding holds
    (NaN included) never reaches a value or a gradient. Returns (x with zero padding, (N, P) mask)."""
    mask = prefix_mask(lengths, x.shape[1])
    finite = torch.isfinite(x.detach()).all(dim=-1)
    if not bool((finite | ~mask).all()):
        raise ValueError(f"{caller}: `{name}` holds NaN or inf at valid (unpadded) points.")
    return torch.where(mask[..., None], x, torch.zeros((), dtype=x.dtype, device=x.device)), mask


def resolve_backend(backend: str, device: torch.device) -> str:
    """``"auto"`` -> ``"kdtree"`` on CPU, ``"tiled"`` elsewhere; other names pass through
    (``"kdtree"`` itself runs scipy's cKDTree where pykdtree is not installed)."""
    if backend == "auto":
        return "kdtree" if torch.device(device).type == "cpu" else "tiled"
    return backend


# ----------------------------------------------------------------------------- backends


def cpu_threads() -> int:
    """Threads for the per-element KD-tree work: the CPU cores this process may run on, at most
    torch's thread count (a process told to use one torch thread, e.g. one of several parallel
    units, uses one thread here too)."""
    try:
        cores = max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        cores = max(1, os.cpu_count() or 1)
    return max(1, min(cores, torch.get_num_threads()))


def map_elements(fn, n_batch: int) -> list:
    """[fn(n) for n in range(n_batch)], one element per thread when there are several threads."""
    threads = min(cpu_threads(), n_batch)
    if threads > 1:
        with ThreadPoolExecutor(threads) as pool:
            return list(pool.map(fn, range(n_batch)))
    return [fn(n) for n in range(n_batch)]


def _pykdtree_indices(query: torch.Tensor, ref: torch.Tensor, qlen: list[int], rlen: list[int],
                      both: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
    """As :func:`_kdtree_indices` with pykdtree (float64, one thread per element)."""
    q_np = query.detach().to("cpu", torch.float64).numpy()
    r_np = ref.detach().to("cpu", torch.float64).numpy()
    n_batch, p, q = q_np.shape[0], q_np.shape[1], r_np.shape[1]
    idx_qr = np.full((n_batch, p), -1, dtype=np.int64)
    idx_rq = np.full((n_batch, q), -1, dtype=np.int64) if both else None

    def element(n: int) -> None:
        pq, pr = q_np[n, : qlen[n]], r_np[n, : rlen[n]]
        idx_qr[n, : qlen[n]] = query_tree(build_tree(pr), pq)[1]
        if both:
            idx_rq[n, : rlen[n]] = query_tree(build_tree(pq), pr)[1]

    map_elements(element, n_batch)
    out_qr = torch.from_numpy(idx_qr).to(query.device)
    out_rq = torch.from_numpy(idx_rq).to(query.device) if both else None
    return out_qr, out_rq


def _kdtree_indices(query: torch.Tensor, ref: torch.Tensor, qlen: list[int], rlen: list[int],
                    both: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Nearest neighbour of each valid query point in ``ref`` (and, if ``both``, of each valid ref
    point in ``query``) with scipy cKDTree. Returns long index tensors (N, P) [and (N, Q)], -1 at
    padded positions, on the inputs' device."""
    q_np = query.detach().to("cpu", torch.float64).numpy()
    r_np = ref.detach().to("cpu", torch.float64).numpy()
    n_batch, p, q = q_np.shape[0], q_np.shape[1], r_np.shape[1]
    idx_qr = np.full((n_batch, p), -1, dtype=np.int64)
    idx_rq = np.full((n_batch, q), -1, dtype=np.int64) if both else None
    threads = cpu_threads()
    # One batch element per thread when there are several; one element uses all cores in its query.
    workers = 1 if (n_batch > 1 and threads > 1) else -1

    def element(n: int) -> None:
        pq, pr = q_np[n, : qlen[n]], r_np[n, : rlen[n]]
        tree_r = cKDTree(pr, **_KDTREE_OPTIONS)
        if both:
            tree_q = cKDTree(pq, **_KDTREE_OPTIONS)
            # Query in the other tree's leaf order: neighbouring queries touch the same leaves.
            order_q, order_r = tree_q.indices, tree_r.indices
            idx_qr[n, order_q] = tree_r.query(pq[order_q], k=1, workers=workers)[1]
            idx_rq[n, order_r] = tree_q.query(pr[order_r], k=1, workers=workers)[1]
        else:
            idx_qr[n, : qlen[n]] = tree_r.query(pq, k=1, workers=workers)[1]

    if workers == 1:
        with ThreadPoolExecutor(min(threads, n_batch)) as pool:
            list(pool.map(element, range(n_batch)))
    else:
        for n in range(n_batch):
            element(n)
    out_qr = torch.from_numpy(idx_qr).to(query.device)
    out_rq = torch.from_numpy(idx_rq).to(query.device) if both else None
    return out_qr, out_rq


def _tile_shape(n_batch: int, p: int, q: int, max_tile_elements: int) -> tuple[int, int, int]:
    """(batch, query, ref) tile sizes whose product is at most ``max_tile_elements``."""
    tq = min(q, max_tile_elements)
    tp = min(p, max(1, max_tile_elements // tq))
    tb = min(n_batch, max(1, max_tile_elements // (tq * tp)))
    return tb, tp, tq


def _tiled_indices(query: torch.Tensor, ref: torch.Tensor, qlen: torch.Tensor, rlen: torch.Tensor,
                   max_tile_elements: int) -> torch.Tensor:
    """Brute-force nearest neighbour in torch, tile by tile; (N, P) long, -1 at padded queries.

    Ranks ``|r|^2 - 2 q.r`` (the squared distance minus the per-query constant ``|q|^2``) with one
    batched matmul per tile, after centring each element on the mean of its valid ref points.
    """
    n_batch, p, _ = query.shape
    q = ref.shape[1]
    with torch.no_grad():
        rmask = prefix_mask(rlen, q)
        # Padding is zero here (see clean_padding), so the plain sum is the sum of valid points.
        centre = ref.sum(1, keepdim=True) / rlen[:, None, None].to(ref.dtype)
        qc, rc = query - centre, ref - centre
        r_sq = rc.square().sum(-1).masked_fill(~rmask, math.inf)  # (N, Q)
        rc_t = rc.transpose(1, 2)  # (N, 3, Q)
        best_idx = torch.empty((n_batch, p), dtype=torch.long, device=query.device)
        tb, tp, tq = _tile_shape(n_batch, p, q, max_tile_elements)
        for b0 in range(0, n_batch, tb):
            b1 = min(b0 + tb, n_batch)
            for p0 in range(0, p, tp):
                p1 = min(p0 + tp, p)
                best_val = None
                for q0 in range(0, q, tq):
                    q1 = min(q0 + tq, q)
                    score = torch.baddbmm(r_sq[b0:b1, None, q0:q1], qc[b0:b1, p0:p1], rc_t[b0:b1, :, q0:q1], alpha=-2.0)
                    val, arg = score.min(dim=-1)
                    arg = arg + q0
                    if best_val is None:
                        best_val, best_arg = val, arg
                    else:
                        better = val < best_val
                        best_val = torch.where(better, val, best_val)
                        best_arg = torch.where(better, arg, best_arg)
                best_idx[b0:b1, p0:p1] = best_arg
        return best_idx.masked_fill(~prefix_mask(qlen, p), -1)


def _naive_indices(query: torch.Tensor, ref: torch.Tensor, qlen: torch.Tensor, rlen: torch.Tensor) -> torch.Tensor:
    """Full (N, P, Q) Euclidean distance matrix and argmin; (N, P) long, -1 at padded queries."""
    with torch.no_grad():
        dist = torch.cdist(query, ref, compute_mode="donot_use_mm_for_euclid_dist")
        dist = dist.masked_fill(~prefix_mask(rlen, ref.shape[1])[:, None, :], math.inf)
        idx = dist.argmin(dim=-1)
        return idx.masked_fill(~prefix_mask(qlen, query.shape[1]), -1)


def nearest_indices(query, ref, qlen, rlen, backend, max_tile_elements, both):
    """Dispatch to a backend; returns (idx query->ref, idx ref->query or None)."""
    if backend == "kdtree" and pykdtree_class() is not None:
        return _pykdtree_indices(query, ref, qlen.tolist(), rlen.tolist(), both)
    if backend in ("kdtree", "scipy"):
        return _kdtree_indices(query, ref, qlen.tolist(), rlen.tolist(), both)
    fn = (lambda x, y, xl, yl: _tiled_indices(x, y, xl, yl, max_tile_elements)) if backend == "tiled" else _naive_indices
    idx_qr = fn(query, ref, qlen, rlen)
    idx_rq = fn(ref, query, rlen, qlen) if both else None
    return idx_qr, idx_rq


# ----------------------------------------------------------------------------- public API


def nearest_neighbors(query: torch.Tensor, ref: torch.Tensor, query_lengths: torch.Tensor | None = None,
                      ref_lengths: torch.Tensor | None = None, backend: str = "auto",
                      max_tile_elements: int = DEFAULT_MAX_TILE_ELEMENTS) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest valid ``ref`` point of every valid ``query`` point (no autograd).

    Args:
        query: (N, P, 3) padded query points, metres.
        ref: (N, Q, 3) padded reference points, metres.
        query_lengths, ref_lengths: (N,) long valid-prefix lengths, or None (all valid).
        backend: "auto" | "kdtree" | "scipy" | "tiled" | "naive" (see module docstring).
        max_tile_elements: largest distance tile of the tiled backend, in elements.

    Returns:
        distances (N, P) Euclidean distances in metres, NaN at padded query positions;
        indices (N, P) long indices into ``ref[n]``, -1 at padded query positions.
    """
    caller = "nearest_neighbors"
    _validate_options(backend, max_tile_elements, caller)
    qlen, rlen = _validate_pair(query, ref, query_lengths, ref_lengths, caller, names=("query", "ref"))
    query, qmask = clean_padding(query.detach(), qlen, "query", caller)
    ref, _ = clean_padding(ref.detach(), rlen, "ref", caller)
    backend = resolve_backend(backend, query.device)
    idx, _ = nearest_indices(query, ref, qlen, rlen, backend, max_tile_elements, both=False)
    with torch.no_grad():
        nn = torch.gather(ref, 1, idx.clamp_min(0)[..., None].expand(-1, -1, 3))
        dist = (query - nn).norm(dim=-1).masked_fill(~qmask, math.nan)
    return dist, idx


def directed_mean(x: torch.Tensor, y: torch.Tensor, idx: torch.Tensor, xmask: torch.Tensor, xlen: torch.Tensor,
                   squared: bool, eps: float) -> torch.Tensor:
    """(N,) mean over valid x of the (squared) distance to its matched y point, differentiable in x and y."""
    nn = torch.gather(y, 1, idx.clamp_min(0)[..., None].expand(-1, -1, 3))
    sq = (x - nn).square().sum(-1)
    if squared:
        d = sq
    elif eps > 0:
        d = sq.clamp_min(eps).sqrt()
    else:
        d = sq.sqrt()
    d = torch.where(xmask, d, torch.zeros((), dtype=d.dtype, device=d.device))
    return d.sum(dim=1) / xlen.to(d.dtype)


def chamfer_loss(a: torch.Tensor, b: torch.Tensor, a_lengths: torch.Tensor | None = None,
                 b_lengths: torch.Tensor | None = None, squared: bool = False, backend: str = "auto",
                 reduction: str = "none", max_tile_elements: int = DEFAULT_MAX_TILE_ELEMENTS,
                 eps: float = DEFAULT_EPS) -> torch.Tensor:
    """Differentiable Chamfer distance, ``0.5 * (mean_a min_b d + mean_b min_a d)``.

    Nearest neighbours are found without autograd (``backend``), then the matched pairs are
    gathered and their distances computed in torch: gradients flow to ``a`` and ``b`` (whichever
    requires grad). Padded positions get zero gradient, whatever values they hold.

    Args:
        a: (N, P, 3) padded points, metres (e.g. mesh vertices at the observed frames).
        b: (N, Q, 3) padded points, metres (e.g. the observed points), same device and dtype.
        a_lengths, b_lengths: (N,) long valid-prefix lengths (each in [1, P] / [1, Q]) or None.
        squared: use squared distances (m^2) instead of Euclidean ones (m). The reported metric
            never squares (docs/protocol.md); an optimisation loss may.
        backend: "auto" | "kdtree" | "scipy" | "tiled" | "naive" (see module docstring).
        reduction: "none" -> (N,) one value per element; "mean" / "sum" -> scalar over elements.
        max_tile_elements: largest distance tile of the tiled backend, in elements.
        eps: floor (m^2) under squared distances before the square root, so coincident points give
            a zero gradient instead of NaN; the value is then at least sqrt(eps) (1e-6 m by default).

    Returns:
        (N,) or scalar tensor, metres (m^2 when ``squared``).
    """
    return _chamfer(a, b, a_lengths, b_lengths, squared, backend, reduction, max_tile_elements, eps, "chamfer_loss")


def apply_reduction(value: torch.Tensor, reduction: str) -> torch.Tensor:
    """(N,) per-element values reduced as ``reduction`` ("none", "mean" or "sum") says."""
    if reduction == "mean":
        return value.mean()
    if reduction == "sum":
        return value.sum()
    return value


def _chamfer(a, b, a_lengths, b_lengths, squared, backend, reduction, max_tile_elements, eps, caller):
    _validate_options(backend, max_tile_elements, caller)
    if reduction not in REDUCTIONS:
        raise ValueError(f"{caller}: `reduction` must be one of {REDUCTIONS}; got {reduction!r}.")
    if not eps >= 0:
        raise ValueError(f"{caller}: `eps` must be >= 0; got {eps!r}.")
    al, bl = _validate_pair(a, b, a_lengths, b_lengths, caller)
    a, amask = clean_padding(a, al, "a", caller)
    b, bmask = clean_padding(b, bl, "b", caller)
    backend = resolve_backend(backend, a.device)
    idx_ab, idx_ba = nearest_indices(a.detach(), b.detach(), al, bl, backend, max_tile_elements, both=True)
    value = 0.5 * (directed_mean(a, b, idx_ab, amask, al, squared, eps)
                   + directed_mean(b, a, idx_ba, bmask, bl, squared, eps))
    return apply_reduction(value, reduction)


def chamfer_distance(a: torch.Tensor, b: torch.Tensor, a_lengths: torch.Tensor | None = None,
                     b_lengths: torch.Tensor | None = None, backend: str = "auto",
                     max_tile_elements: int = DEFAULT_MAX_TILE_ELEMENTS) -> torch.Tensor:
    """The reported Chamfer metric of docs/protocol.md, one value per batch element (no autograd).

    ``0.5 * (mean_{a} min_{b} |a - b| + mean_{b} min_{a} |b - a|)``, Euclidean distances.

    Args:
        a: (N, P, 3) padded points, metres.
        b: (N, Q, 3) padded points, metres, same device and dtype.
        a_lengths, b_lengths: (N,) long valid-prefix lengths or None (all valid).
        backend: "auto" | "kdtree" | "scipy" | "tiled" | "naive" (see module docstring).
        max_tile_elements: largest distance tile of the tiled backend, in elements.

    Returns:
        (N,) tensor, metres, dtype and device of ``a``.
    """
    with torch.no_grad():
        return _chamfer(a, b, a_lengths, b_lengths, False, backend, "none", max_tile_elements, 0.0,
                        "chamfer_distance")
