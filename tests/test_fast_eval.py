"""The table1 evaluation's fast path against its reference implementation (same numbers)."""

from types import SimpleNamespace

import pytest
import torch


def _unit(body, frames=3, seed=0):
    """Output meshes near the ground truth and one far off (1.5 m away, 40 degrees turned: the
    8-nearest-vertex candidates are then an upper bound, the case where pruning matters most)."""
    import roma

    from benchmark.protocols.unit_data import UnitData
    from benchmark.core.surface_sampling import sample_surface

    g = torch.Generator().manual_seed(seed)
    rest = body.prepare(body.default_shape(1))
    rot = roma.rotvec_to_rotmat(torch.randn(1, frames, 22, 3, generator=g) * 0.2)
    rot_out = roma.rotvec_to_rotmat(roma.rotmat_to_rotvec(rot) + torch.randn(1, frames, 22, 3, generator=g) * 0.05)
    rot_out[0, -1, 0] = roma.rotvec_to_rotmat(torch.tensor([0.0, 0.7, 0.0]))
    trans_out = torch.zeros(1, frames, 3)
    trans_out[0, -1] = torch.tensor([1.5, 0.1, -0.2])
    with torch.no_grad():
        gt = body.skin(rest, rot, torch.zeros(1, frames, 3))
        out = body.skin(rest, rot_out, trans_out)
        scan = sample_surface(gt.vertices, body.faces, 3000, g)
    data = UnitData(scans=None, out_t=torch.zeros(1, frames), gt_points=scan, gt_joints=gt.joints)
    return SimpleNamespace(vertices=out.vertices, joints=out.joints), data


@pytest.mark.parametrize("surface_points", [500, None])
def test_evaluate_matches_reference(anny_body, surface_points):
    from benchmark.protocols.completion_unit import evaluate, evaluate_reference

    output, data = _unit(anny_body)
    ref = evaluate_reference(anny_body, output, data, "cpu", surface_points=surface_points)
    for _ in range(2):  # the second call uses the cached scan trees
        got = evaluate(anny_body, output, data, "cpu", surface_points=surface_points)
        assert [r["frames"] for r in got] == [r["frames"] for r in ref]
        for x, y in zip(got, ref):
            for metric, value in y["sums"].items():
                assert x["sums"][metric] == pytest.approx(value, abs=1e-6 * y["frames"]), metric  # 1e-3 mm per frame
    assert len(data.cache) == 1


def test_scan_trees_follow_the_scans(anny_body):
    """A cache entry belongs to the scans it was built on: new scans get new trees."""
    from benchmark.protocols.completion_unit import evaluate, evaluate_reference

    output, data = _unit(anny_body, frames=2, seed=1)
    evaluate(anny_body, output, data, "cpu", surface_points=300)
    data.gt_points = data.gt_points + 0.01
    got = evaluate(anny_body, output, data, "cpu", surface_points=300)
    ref = evaluate_reference(anny_body, output, data, "cpu", surface_points=300)
    assert got[0]["sums"]["chamfer_m"] == pytest.approx(ref[0]["sums"]["chamfer_m"], abs=1e-9)
    assert len(data.cache) == 2  # the sets of both scans, up to SCAN_TREE_SETS (captures of different sizes: one per sequence)
    from benchmark.protocols import completion_unit

    for _ in range(completion_unit.SCAN_TREE_SETS + 3):
        data.gt_points = data.gt_points + 0.001
        evaluate(anny_body, output, data, "cpu", surface_points=300)
    assert len(data.cache) == completion_unit.SCAN_TREE_SETS  # the oldest go first


def test_surface_kernel_equals_array_path_bit_for_bit(anny_body, monkeypatch):
    """The compiled scan -> surface kernel and the array path give the same doubles (the table's
    numbers cannot depend on whether numba is installed); the far-off frame included."""
    import benchmark.metrics.surface_kernel as sk
    from benchmark.protocols.completion_unit import evaluate

    if not sk.HAVE_NUMBA:
        pytest.skip("numba is not installed: the evaluation runs its array path")
    output, data = _unit(anny_body, frames=3, seed=2)
    kernel = evaluate(anny_body, output, data, "cpu", surface_points=800)
    monkeypatch.setattr(sk, "HAVE_NUMBA", False)
    arrays = evaluate(anny_body, output, data, "cpu", surface_points=800)
    assert kernel == arrays


def test_surface_kernel_by_hand_and_degenerate_triangles():
    """Hand-checked distances: a point above a triangle's interior, one beyond a vertex, one beyond
    an edge; a zero-area (collinear) triangle is measured as its edges; the vertex distance wins
    when it is smaller, and a triangle far beyond the running minimum changes nothing."""
    import numpy as np

    import benchmark.metrics.surface_kernel as sk

    if not sk.HAVE_NUMBA:
        pytest.skip("numba is not installed")
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0],  # right triangle in z = 0
                      [5, 0, 0], [6, 0, 0], [7, 0, 0],  # collinear: zero area
                      [50, 50, 50], [51, 50, 50], [50, 51, 50]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]], dtype=np.int64)
    vertex_faces = np.full((9, 1), 3, dtype=np.int64)
    vertex_faces[:, 0] = [0, 0, 0, 1, 1, 1, 2, 2, 2]
    points = np.array([[0.2, 0.2, 0.5],   # above the interior: 0.5
                       [-1.0, -1.0, 0.0],  # beyond vertex A: sqrt(2)
                       [0.5, -2.0, 0.0],   # beyond edge AB: 2
                       [6.5, 3.0, 4.0],    # the zero-area triangle's segment [5, 7] x: 5
                       [0.2, 0.2, 0.5]])   # vertex distance 0.1 given: stays 0.1
    knn = np.array([[0, 6], [0, 6], [1, 6], [4, 6], [0, 6]], dtype=np.int64)
    vd = np.array([9.0, 9.0, 9.0, 9.0, 0.1])
    got = sk.scan_to_surface_knn(points, verts, faces, vertex_faces, knn, vd)
    assert got == pytest.approx([0.5, 2 ** 0.5, 2.0, 5.0, 0.1], abs=1e-12)
