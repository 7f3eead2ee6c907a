"""Side-by-side timing of the Chamfer backends, in one run (``python -m benchmark perf``).

Timings are only compared within one run, on one machine (never against numbers from another):
the result carries ratios to the naive backend next to the absolute times.
"""

from __future__ import annotations

import platform
import time

import torch

from benchmark.metrics.chamfer import DEFAULT_MAX_TILE_ELEMENTS, chamfer_loss

PERF_BACKENDS = ("kdtree", "tiled", "naive")


def synthetic_pair(frames: int, n_points: int, n_vertices: int, device: torch.device, seed: int):
    """Body-sized point clouds: ``a`` (frames, n_vertices, 3) requiring grad (the mesh vertices) and
    ``b`` (frames, n_points, 3) near the same surface (the observed points), metres."""
    gen = torch.Generator().manual_seed(seed)

    def ellipsoid_surface(n: int) -> torch.Tensor:  # (frames, n, 3), a 1.7 m x 0.5 m x 0.3 m body-sized shell
        d = torch.randn(frames, n, 3, generator=gen, dtype=torch.float64)
        d = d / d.norm(dim=-1, keepdim=True)
        return d * torch.tensor([0.25, 0.85, 0.15], dtype=torch.float64)

    a = ellipsoid_surface(n_vertices)
    b = ellipsoid_surface(n_points) + 0.003 * torch.randn(frames, n_points, 3, generator=gen, dtype=torch.float64)
    a = a.to(device=device, dtype=torch.float32).requires_grad_(True)
    return a, b.to(device=device, dtype=torch.float32)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _time_backend(a: torch.Tensor, b: torch.Tensor, backend: str, repeats: int, chunk: int,
                  max_tile_elements: int) -> float:
    """Best-of-``repeats`` seconds per frame of chamfer_loss forward + backward, ``chunk`` frames a call."""
    device = a.device
    best = float("inf")
    for _ in range(repeats):
        a.grad = None
        _sync(device)
        start = time.perf_counter()
        for i in range(0, a.shape[0], chunk):
            loss = chamfer_loss(a[i:i + chunk], b[i:i + chunk], backend=backend, reduction="sum",
                                max_tile_elements=max_tile_elements)
            loss.backward()
        _sync(device)
        best = min(best, time.perf_counter() - start)
    return best / a.shape[0]


def chamfer_perf(frames: int = 8, n_points: int = 10000, n_vertices: int = 13718, device: str = "cpu",
                 repeats: int = 2, brute_force_frames: int = 1, seed: int = 0,
                 max_tile_elements: int = DEFAULT_MAX_TILE_ELEMENTS) -> dict:
    """Time chamfer_loss forward + backward per frame for the kdtree, tiled and naive backends.

    ``a`` = ``n_vertices`` points requiring grad (mesh vertices), ``b`` = ``n_points`` observed
    points, both on a body-sized ellipsoid. kdtree runs all ``frames`` as one batch, and so does
    tiled on CUDA. The brute-force paths that are slow where they run (naive everywhere, tiled on
    CPU) run ``brute_force_frames`` frames, naive one frame a call (it materialises the full
    (P, Q) distance matrix). Times are best-of-``repeats``, after a warm-up call on CUDA. The
    backends' loss values are checked against naive on the first frame.

    Returns:
        dict with ``ms_per_frame`` {backend: ms}, ``speedup_vs_naive`` {backend: naive ms / ms},
        ``loss_max_abs_diff_m`` (largest loss difference to naive, metres), the sizes, frames
        timed per backend, the device and the torch version and thread count.
    """
    for name, value in (("frames", frames), ("n_points", n_points), ("n_vertices", n_vertices),
                        ("repeats", repeats), ("brute_force_frames", brute_force_frames)):
        if not isinstance(value, int) or value < 1:
            raise ValueError(f"chamfer_perf: `{name}` must be a positive int; got {value!r}.")
    dev = torch.device(device)
    a, b = synthetic_pair(frames, n_points, n_vertices, dev, seed)
    slow = min(brute_force_frames, frames)
    timed = {"kdtree": frames, "tiled": frames if dev.type == "cuda" else slow, "naive": slow}

    ms = {}
    for backend in PERF_BACKENDS:
        n = timed[backend]
        aa, bb = a[:n].detach().requires_grad_(True), b[:n]
        chunk = 1 if backend == "naive" else n
        if dev.type == "cuda":  # first-call costs (kernels, cuBLAS handles) are not the backend's speed
            _time_backend(aa[:1].detach().requires_grad_(True), bb[:1], backend, 1, 1, max_tile_elements)
        ms[backend] = 1e3 * _time_backend(aa, bb, backend, repeats, chunk, max_tile_elements)
    with torch.no_grad():
        values = {k: chamfer_loss(a[:1], b[:1], backend=k, max_tile_elements=max_tile_elements) for k in PERF_BACKENDS}
    diff = max(float((values[k] - values["naive"]).abs().max()) for k in PERF_BACKENDS)
    return {
        "what": "chamfer_loss forward + backward, ms per frame",
        "device": str(dev) if dev.type != "cuda" else f"{dev} ({torch.cuda.get_device_name(dev)})",
        "cpu": platform.processor() or platform.machine(),
        "torch_threads": torch.get_num_threads(),
        "n_points": n_points,
        "n_vertices": n_vertices,
        "frames_timed": timed,
        "repeats": repeats,
        "max_tile_elements": max_tile_elements,
        "ms_per_frame": ms,
        "speedup_vs_naive": {k: ms["naive"] / ms[k] for k in PERF_BACKENDS},
        "loss_max_abs_diff_m": diff,
        "torch": torch.__version__,
    }
