"""Points sampled over a triangle mesh: uniform-by-area surface samples per frame
(:func:`sample_surface`, the scans of :mod:`benchmark.data.observations`) and greedy farthest-point
subsets (:func:`farthest_point_indices`, the denoise table's virtual markers).

Randomness: :func:`sample_surface` takes a ``torch.Generator`` and draws on its device, then moves
the samples, so a CPU generator gives the same samples whatever device the mesh is on.
"""

from __future__ import annotations

import torch

# Frames per chunk when gathering sampled triangles (bounds the (chunk, N, 3) temporaries).
_SAMPLE_CHUNK_FRAMES = 64


def sample_surface(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    num_points: int,
    generator: torch.Generator | None,
    noise_std: float = 0.0,
) -> torch.Tensor:
    """Points sampled uniformly over the area of a triangle mesh, independently per frame.

    vertices: (..., V, 3) e.g. (B, T, V, 3) metres; faces: (F, 3) long; num_points: N.
    Each point picks a triangle with probability proportional to its area (in that frame's
    posed mesh), then uniform barycentric coordinates by the square-root trick:
    ``p = (1 - sqrt(r1)) a + sqrt(r1) (1 - r2) b + sqrt(r1) r2 c``, r1, r2 ~ U[0, 1).
    Optional isotropic Gaussian noise of std ``noise_std`` metres is added to each coordinate.

    Draw order (for reproducibility): triangle uniforms (..., N) float64, then barycentric
    uniforms (..., N, 2), then (only when noise_std > 0) the noise (..., N, 3); so the same seed
    gives the same noiseless points with or without noise. ``generator=None`` uses torch's
    global RNG (not reproducible across calls).
    Returns (..., N, 3) in the dtype and on the device of ``vertices``.
    """
    if vertices.dim() < 2 or vertices.shape[-1] != 3:
        raise ValueError(f"sample_surface: vertices must be (..., V, 3), got {tuple(vertices.shape)}")
    if faces.dim() != 2 or faces.shape[-1] != 3 or faces.shape[0] == 0:
        raise ValueError(f"sample_surface: faces must be a non-empty (F, 3) index tensor, got {tuple(faces.shape)}")
    if num_points < 0:
        raise ValueError(f"sample_surface: num_points must be >= 0, got {num_points}")
    if noise_std < 0:
        raise ValueError(f"sample_surface: noise_std is a standard deviation in metres, got {noise_std} < 0")
    lead = vertices.shape[:-2]
    V = vertices.shape[-2]
    faces = faces.to(device=vertices.device, dtype=torch.long)
    if int(faces.min()) < 0 or int(faces.max()) >= V:
        raise ValueError(f"sample_surface: faces index vertices outside [0, {V})")
    flat = vertices.reshape(-1, V, 3)
    K = flat.shape[0]

    gen_device = generator.device if generator is not None else torch.device("cpu")
    r_face = torch.rand(K, num_points, dtype=torch.float64, generator=generator, device=gen_device)
    r_bary = torch.rand(K, num_points, 2, dtype=vertices.dtype, generator=generator, device=gen_device)
    noise = None
    if noise_std > 0:
        noise = torch.randn(K, num_points, 3, dtype=vertices.dtype, generator=generator, device=gen_device)
    r_face = r_face.to(vertices.device)
    r_bary = r_bary.to(vertices.device)

    out = vertices.new_empty(K, num_points, 3)
    for start in range(0, K, _SAMPLE_CHUNK_FRAMES):
        v = flat[start : start + _SAMPLE_CHUNK_FRAMES]  # (k, V, 3)
        tri = v[:, faces]  # (k, F, 3, 3)
        a, b, c = tri.unbind(-2)
        area = torch.linalg.cross(b - a, c - a).norm(dim=-1).to(torch.float64)  # 2x area, (k, F)
        cdf = area.cumsum(-1)
        total = cdf[:, -1:]
        if not bool((total > 0).all()) or not bool(torch.isfinite(total).all()):
            bad = int(torch.nonzero(~(total[:, 0] > 0) | ~torch.isfinite(total[:, 0]))[0]) + start
            raise ValueError(
                f"sample_surface: frame {bad} (flattened over {tuple(lead)}) has zero or non-finite "
                "surface area; check the vertices (all zeros? NaN?)"
            )
        u = r_face[start : start + v.shape[0]] * total
        idx = torch.searchsorted(cdf, u, right=True).clamp_(max=faces.shape[0] - 1)  # (k, N)
        rows = torch.arange(v.shape[0], device=v.device)[:, None]
        corners = tri[rows, idx]  # (k, N, 3, 3)
        s = r_bary[start : start + v.shape[0], :, 0:1].sqrt()
        r2 = r_bary[start : start + v.shape[0], :, 1:2]
        out[start : start + v.shape[0]] = (
            (1 - s) * corners[..., 0, :] + s * (1 - r2) * corners[..., 1, :] + s * r2 * corners[..., 2, :]
        )
    if noise is not None:
        out = out + noise_std * noise.to(vertices.device)
    return out.reshape(*lead, num_points, 3)


def farthest_point_indices(points: torch.Tensor, count: int) -> torch.Tensor:
    """Greedy farthest-point subset of (P, 3) points: (count,) long indices.

    Starts at the point farthest from the centroid; each next point maximises its distance to
    the points already chosen (ties: the lowest index). Deterministic.
    """
    if points.dim() != 2 or points.shape[-1] != 3:
        raise ValueError(f"farthest_point_indices: points must be (P, 3), got {tuple(points.shape)}")
    P = points.shape[0]
    if not 1 <= count <= P:
        raise ValueError(f"farthest_point_indices: count must be in [1, {P}], got {count}")
    pts = points.to(torch.float64)
    chosen = torch.empty(count, dtype=torch.long, device=points.device)
    chosen[0] = torch.argmax((pts - pts.mean(0)).norm(dim=-1))
    dist = (pts - pts[chosen[0]]).norm(dim=-1)
    for i in range(1, count):
        chosen[i] = torch.argmax(dist)
        dist = torch.minimum(dist, (pts - pts[chosen[i]]).norm(dim=-1))
    return chosen
