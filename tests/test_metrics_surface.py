"""Point-to-surface Chamfer: exact point-triangle distances against hand cases and trimesh."""

import math

import numpy as np
import pytest
import torch
import trimesh

from benchmark.metrics import chamfer_distance, chamfer_surface_distance, point_triangle_distance
from benchmark.metrics.surface import _face_samples, _subdivision_centroids, points_to_surface_distance

TRI = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0]], dtype=torch.float64)


@pytest.mark.parametrize(
    "point, expected",
    [
        ((0.25, 0.25, 2.0), 2.0),  # above the interior
        ((0.25, 0.25, 0.0), 0.0),  # on the triangle
        ((0.5, -1.0, 0.0), 1.0),  # beside edge AB
        ((0.5, -1.0, 1.0), math.sqrt(2)),  # beside and above edge AB
        ((-1.0, 0.5, 0.0), 1.0),  # beside edge AC
        ((1.0, 1.0, 0.0), math.sqrt(0.5)),  # beside the hypotenuse BC
        ((1.0, 1.0, 3.0), math.sqrt(0.5 + 9)),
        ((-1.0, -1.0, 0.0), math.sqrt(2)),  # near vertex A
        ((2.0, -0.5, 0.0), math.sqrt(1.25)),  # near vertex B
        ((-0.5, 3.0, 1.0), math.sqrt(0.25 + 4 + 1)),  # near vertex C
    ],
)
def test_point_triangle_hand_cases(point, expected):
    p = torch.tensor(point, dtype=torch.float64)
    assert point_triangle_distance(p, TRI).item() == pytest.approx(expected, abs=1e-15)
    # Same answer whatever the corner order.
    for perm in ([1, 2, 0], [2, 1, 0]):
        assert point_triangle_distance(p, TRI[perm]).item() == pytest.approx(expected, abs=1e-15)


def test_point_triangle_degenerate():
    segment = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]], dtype=torch.float64)  # collinear corners
    p = torch.tensor([[1.0, 1.0, 0.0], [3.0, 0.0, 0.0], [-1.0, 0.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(point_triangle_distance(p, segment), torch.tensor([1.0, 1.0, math.sqrt(2)],
                                                                                 dtype=torch.float64))
    point_tri = torch.ones(3, 3, dtype=torch.float64)  # all corners equal
    assert point_triangle_distance(torch.zeros(3, dtype=torch.float64), point_tri).item() == pytest.approx(math.sqrt(3))


def test_point_triangle_matches_trimesh_random():
    rng = np.random.default_rng(0)
    tris = rng.normal(size=(4000, 3, 3))
    tris[:200, 2] = tris[:200, 1] + 1e-9 * rng.normal(size=(200, 3))  # nearly degenerate slivers
    pts = rng.normal(size=(4000, 3)) * 1.5
    ref = np.linalg.norm(trimesh.triangles.closest_point(tris, pts) - pts, axis=1)
    got = point_triangle_distance(torch.from_numpy(pts), torch.from_numpy(tris)).numpy()
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)


def test_point_triangle_broadcasts():
    pts = torch.randn(5, 1, 3, dtype=torch.float64)
    tris = torch.randn(1, 7, 3, 3, dtype=torch.float64)
    full = point_triangle_distance(pts, tris)
    assert full.shape == (5, 7)
    assert full[2, 3].item() == point_triangle_distance(pts[2, 0], tris[0, 3]).item()


def test_subdivision_covers_triangle():
    for m in (1, 2, 3, 5):
        bary = _subdivision_centroids(m)
        assert bary.shape == (m * m, 3)
        np.testing.assert_allclose(bary.sum(1), 1.0)
        assert (bary > 0).all()
    rng = np.random.default_rng(1)
    tris = rng.normal(size=(30, 3, 3))
    samples, face_ids, radii = _face_samples(tris, radius=0.3)
    # Every point of every face lies within its sample's radius of one of the face's samples.
    w = rng.dirichlet(np.ones(3), size=(30, 200))
    pts = np.einsum("fsk,fkd->fsd", w, tris)
    for f in range(30):
        mine = face_ids == f
        d = np.linalg.norm(pts[f][:, None] - samples[mine][None], axis=-1) - radii[mine][None]
        assert (d.min(1) <= 1e-12).all()
    assert radii.max() <= 0.3 + 1e-12


def brute_force_surface(points, vertices, faces):
    """Independent reference: trimesh's exact closest point on every face, min over faces."""
    tris = vertices[faces]
    p = np.repeat(points, len(faces), axis=0)
    t = np.tile(tris, (len(points), 1, 1))
    return np.linalg.norm(trimesh.triangles.closest_point(t, p) - p, axis=1).reshape(len(points), len(faces)).min(1)


def distorted_sphere():
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    v = mesh.vertices.copy()
    v[:, 0] *= 1.7
    v[v[:, 1] > 0.15] *= 1.4  # mixed face sizes, and a few stretched faces
    return v, mesh.faces


@pytest.mark.parametrize("k", [1, 4, 16, 10**6])
@pytest.mark.parametrize("scale", [0.05, 0.3, 1.5])
def test_points_to_surface_matches_brute_force(k, scale):
    v, f = distorted_sphere()
    pts = np.random.default_rng(2).normal(size=(150, 3)) * scale
    got = points_to_surface_distance(pts, v, f, k=k)
    np.testing.assert_allclose(got, brute_force_surface(pts, v, f), rtol=0, atol=1e-12)


def test_chamfer_surface_matches_reference_with_padding():
    v, f = distorted_sphere()
    rng = np.random.default_rng(3)
    n_v, n_p = len(v), 120
    verts = np.stack([v, v * 1.05 + 0.01])
    verts = np.concatenate([verts, np.full((2, 5, 3), np.nan)], axis=1)  # 5 padded vertices (NaN)
    pts = rng.normal(size=(2, n_p, 3)) * 0.3
    point_lengths = torch.tensor([n_p, 80])
    got = chamfer_surface_distance(torch.from_numpy(pts), torch.from_numpy(verts), torch.from_numpy(f),
                                   vertex_lengths=torch.tensor([n_v, n_v]), point_lengths=point_lengths)
    for n in range(2):
        p = pts[n, : int(point_lengths[n])]
        vv = verts[n, :n_v]
        to_surface = brute_force_surface(p, vv, f).mean()
        to_points = np.linalg.norm(vv[:, None] - p[None], axis=-1).min(1).mean()
        assert got[n].item() == pytest.approx(0.5 * (to_surface + to_points), abs=1e-12)


def test_surface_chamfer_below_vertex_chamfer_and_zero_on_surface():
    v, f = distorted_sphere()
    mesh = trimesh.Trimesh(v, f, process=False)
    on_surface = trimesh.sample.sample_surface(mesh, 400, seed=4)[0]
    pts = torch.from_numpy(on_surface)[None]
    verts = torch.from_numpy(v)[None]
    faces = torch.from_numpy(f)
    surface = chamfer_surface_distance(pts, verts, faces)
    vertex = chamfer_distance(pts, verts)
    assert surface.item() < vertex.item()
    # The points -> surface half vanishes for points on the surface.
    assert points_to_surface_distance(on_surface, v, f).max() < 1e-12


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda p, v, f: chamfer_surface_distance(p[0], v, f), r"`points` must have shape \(N, P, 3\)"),
        (lambda p, v, f: chamfer_surface_distance(p, v[:1], f), "same non-zero batch size"),
        (lambda p, v, f: chamfer_surface_distance(p, v, f[:, :2]), r"`faces` must be a non-empty \(F, 3\)"),
        (lambda p, v, f: chamfer_surface_distance(p, v, f.double()), "integer tensor"),
        (lambda p, v, f: chamfer_surface_distance(p, v, f, vertex_lengths=torch.tensor([3, 4])),
         "faces must index valid vertices"),
        (lambda p, v, f: chamfer_surface_distance(p, v, f, point_lengths=torch.tensor([0, 4])), "point_lengths"),
        (lambda p, v, f: chamfer_surface_distance(p * math.nan, v, f), "NaN or inf"),
    ],
)
def test_errors(call, match):
    points = torch.rand(2, 4, 3, dtype=torch.float64)
    verts = torch.rand(2, 4, 3, dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    with pytest.raises(ValueError, match=match):
        call(points, verts, faces)
