"""Observation synthesis: surface sampling, scans, ground truth, landmarks, noisy joints.

A tiny rigid "box body" (every vertex skinned to the pelvis) stands in for the real body, so
posed vertices have a closed form: R(root) @ v + trans. The motions are a small stand-in with
the ``benchmark.core.motion.Motion`` interface (linear interpolation, exact for the test motions).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest
import roma
import torch
import trimesh

from benchmark.body.base import BodyModel, BodyOutput, RestState
from benchmark.body.lbs import forward_kinematics, linear_blend_skinning, skinning_transforms
from benchmark.core.motion_posing import capture_timestamps
from benchmark.data.observations import (
    GroundTruth,
    Landmarks,
    NoisyJoints,
    PointCloudSequence,
    ground_truth_at,
    make_landmarks,
    make_noisy_joints,
    make_scans,
    virtual_marker_indices,
)
from benchmark.core.skeleton import NUM_JOINTS
from benchmark.core.surface_sampling import farthest_point_indices, sample_surface

HALF = torch.tensor([0.2, 0.5, 0.1], dtype=torch.float64)  # box half extents (m)


class BoxBody(BodyModel):
    """A box mesh rigidly attached to the pelvis; shape = one scale factor."""

    name = "box"
    shape_dim = 1

    def __init__(self):
        super().__init__()
        mesh = trimesh.creation.box(extents=(2 * HALF).tolist()).subdivide().subdivide()
        self.register_buffer("template", torch.tensor(mesh.vertices, dtype=torch.float32))
        self.register_buffer("faces", torch.tensor(mesh.faces, dtype=torch.long))
        weights = torch.zeros(len(mesh.vertices), NUM_JOINTS)
        weights[:, 0] = 1.0
        self.register_buffer("weights", weights)
        joints = torch.zeros(NUM_JOINTS, 3)
        joints[:, 1] = torch.linspace(0.0, 0.4, NUM_JOINTS)  # pelvis at the origin
        self.register_buffer("rest", joints)
        self.register_buffer("landmark_indices", torch.arange(16) * 5)

    @property
    def num_vertices(self) -> int:
        return self.template.shape[0]

    def default_shape(self, batch_size: int = 1) -> torch.Tensor:
        return torch.ones(batch_size, 1)

    def prepare(self, shape):
        s = shape[:, :, None]
        return RestState(vertices=self.template * s, joints=self.rest * s)

    def skin(self, rest, rotations, trans):
        rj = rest.joints[:, None]
        g_rot, joints = forward_kinematics(rotations, rj)
        transforms = skinning_transforms(g_rot, joints, rj)
        verts = linear_blend_skinning(rest.vertices[:, None], self.weights, transforms)
        return BodyOutput(vertices=verts + trans[..., None, :], joints=joints + trans[..., None, :])


@dataclass
class StubMotion:
    """The Motion interface (poses (T,22,3), trans (T,3), timestamps (T,), shape (S,))."""

    poses: torch.Tensor
    trans: torch.Tensor
    timestamps: torch.Tensor
    shape: torch.Tensor | None = None

    def resample(self, timestamps):
        ts = torch.as_tensor(timestamps, dtype=torch.float64)
        src = self.timestamps
        i = torch.searchsorted(src, ts, right=True).clamp(1, len(src) - 1)
        w = ((ts - src[i - 1]) / (src[i] - src[i - 1])).clamp(0, 1)

        def lerp(x):
            wx = w.to(x.dtype).reshape(-1, *([1] * (x.dim() - 1)))
            return x[i - 1] * (1 - wx) + x[i] * wx

        return StubMotion(lerp(self.poses), lerp(self.trans), ts, self.shape)

    def rotmats(self):
        return roma.rotvec_to_rotmat(self.poses)


OMEGA = 1.3  # root yaw rate (rad/s)
VEL = torch.tensor([0.5, 0.0, -0.25], dtype=torch.float64)  # root velocity (m/s)


def analytic_root(t: torch.Tensor, start: torch.Tensor):
    """Yaw angle about y and translation of the test motion at times t (s)."""
    return OMEGA * t, start + t[..., None] * VEL


def make_motion(duration: float, start=(0.0, 1.0, 0.0), fps=30.0, seed=0, shape=None) -> StubMotion:
    T = int(round(duration * fps)) + 1
    ts = torch.arange(T, dtype=torch.float64) / fps
    g = torch.Generator().manual_seed(seed)
    poses = 0.3 * torch.randn(T, NUM_JOINTS, 3, generator=g)
    angle, trans = analytic_root(ts, torch.tensor(start, dtype=torch.float64))
    poses[:, 0] = 0.0
    poses[:, 0, 1] = angle.float()
    return StubMotion(poses, trans.float(), ts, shape)


def yaw(angle: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation about +y, written out by hand."""
    c, s = torch.cos(angle), torch.sin(angle)
    z, o = torch.zeros_like(angle), torch.ones_like(angle)
    return torch.stack([c, z, s, z, o, z, -s, z, c], dim=-1).reshape(*angle.shape, 3, 3)


def to_box_frame(points: torch.Tensor, t: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
    """Undo the analytic root motion: (T, N, 3) world points -> the box's own frame."""
    angle, trans = analytic_root(t, start)
    R = yaw(angle)  # (T, 3, 3)
    return ((points.double() - trans[:, None]) @ R)  # R^T p for row vectors


def box_surface_residual(local: torch.Tensor) -> torch.Tensor:
    """0 exactly on the box surface: max_i |x_i| / h_i - 1."""
    return (local.abs() / HALF).amax(-1) - 1


# --------------------------------------------------------------------------- sample_surface
TWO_TRIANGLES_V = torch.tensor(
    [[0, 0, 0], [3, 0, 0], [0, 3, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1]], dtype=torch.float32
)
TWO_TRIANGLES_F = torch.tensor([[0, 1, 2], [3, 4, 5]])  # areas 4.5 and 0.5


def test_sample_surface_is_area_uniform_and_on_the_surface():
    N = 100_000
    g = torch.Generator().manual_seed(1)
    pts = sample_surface(TWO_TRIANGLES_V[None, None], TWO_TRIANGLES_F, N, g)[0, 0].double()
    assert pts.shape == (N, 3)
    on_big = pts[:, 2].abs() < 1e-6
    on_small = (pts[:, 2] - 1).abs() < 1e-6
    assert bool((on_big ^ on_small).all()), "every point lies in one of the two triangle planes"
    # the fraction on each triangle follows the area ratio 0.5 / 5.0
    frac = on_small.double().mean().item()
    sd = math.sqrt(0.1 * 0.9 / N)
    assert abs(frac - 0.1) < 5 * sd
    # inside the triangles
    big, small = pts[on_big], pts[on_small]
    assert bool((big[:, :2] >= -1e-6).all() & (big[:, :2].sum(-1) <= 3 + 1e-5).all())
    assert bool((small[:, :2] >= -1e-6).all() & (small[:, :2].sum(-1) <= 1 + 1e-6).all())
    # uniform inside a triangle: regions of known area get their share
    n = big.shape[0]
    half_corner = (big[:, :2].sum(-1) < 3 / math.sqrt(2)).double().mean().item()  # similar triangle, area 1/2
    assert abs(half_corner - 0.5) < 5 * math.sqrt(0.25 / n)
    strip = (big[:, 0] < 1).double().mean().item()  # area (4.5 - 2) / 4.5
    assert abs(strip - 2.5 / 4.5) < 5 * math.sqrt(0.25 / n)
    centroid = small.mean(0)
    sd_coord = math.sqrt(1 / 18)  # std of one coordinate of a uniform point in the unit right triangle
    expected = torch.tensor([1 / 3, 1 / 3, 1.0], dtype=torch.float64)
    assert torch.allclose(centroid, expected, atol=5 * sd_coord / math.sqrt(small.shape[0]))


def test_sample_surface_frames_are_independent_and_on_their_own_mesh():
    offsets = torch.tensor([[[0.0, 0, 0], [0.0, 0, 0], [10, 0, 0]], [[0, 10, 0], [0, 20, 0], [0, 0, 30]]])
    verts = TWO_TRIANGLES_V + offsets[:, :, None, :]  # (2, 3, 6, 3)
    pts = sample_surface(verts, TWO_TRIANGLES_F, 500, torch.Generator().manual_seed(0))
    assert pts.shape == (2, 3, 500, 3)
    local = pts - offsets[:, :, None, :]
    assert bool(((local[..., 2].abs() < 1e-5) | ((local[..., 2] - 1).abs() < 1e-5)).all())
    assert bool((local[..., :2] >= -1e-5).all() & (local[..., :2].sum(-1) <= 3 + 1e-4).all())
    # frames 0 and 1 of sequence 0 have the same mesh but fresh points
    assert not torch.allclose(pts[0, 0], pts[0, 1])
    again = sample_surface(verts, TWO_TRIANGLES_F, 500, torch.Generator().manual_seed(0))
    assert torch.equal(pts, again)


def test_sample_surface_noise_std_is_recovered():
    square = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    N, sigma = 60_000, 0.01
    noisy = sample_surface(square[None], faces, N, torch.Generator().manual_seed(3), noise_std=sigma)[0].double()
    z = noisy[:, 2]  # the surface is z = 0: z is pure noise
    assert abs(z.std().item() - sigma) < 0.02 * sigma
    assert abs(z.mean().item()) < 5 * sigma / math.sqrt(N)
    clean = sample_surface(square[None], faces, N, torch.Generator().manual_seed(3))[0].double()
    diff = noisy - clean  # same seed: the noise is drawn last
    assert torch.allclose(diff.std(0), torch.full((3,), sigma, dtype=torch.float64), rtol=0.02)


def test_sample_surface_errors():
    flat = torch.zeros(1, 6, 3)
    with pytest.raises(ValueError, match="zero or non-finite surface area"):
        sample_surface(flat, TWO_TRIANGLES_F, 10, None)
    with pytest.raises(ValueError, match="outside"):
        sample_surface(TWO_TRIANGLES_V, torch.tensor([[0, 1, 6]]), 10, None)
    with pytest.raises(ValueError, match="noise_std"):
        sample_surface(TWO_TRIANGLES_V, TWO_TRIANGLES_F, 10, None, noise_std=-1.0)


# --------------------------------------------------------------------------- scans and ground truth
def test_capture_timestamps_by_hand():
    m1, m2 = make_motion(1.0), make_motion(0.5)
    ts, mask = capture_timestamps([m1, m2], fps=50.0)
    assert ts.shape == (2, 51) and ts.dtype == torch.float64
    assert mask[0].all() and mask[1].sum() == 26 and not mask[1, 26:].any()
    assert torch.allclose(ts[0, :3], torch.tensor([0.0, 0.02, 0.04], dtype=torch.float64))
    ts, mask = capture_timestamps([m1], fps=50.0, duration=0.4)  # half-open window: 20 frames
    assert ts.shape == (1, 20) and abs(ts[0, -1].item() - 0.38) < 1e-12
    with pytest.raises(ValueError, match="motion 1 spans 0.5000 s"):
        capture_timestamps([m1, m2], fps=50.0, duration=0.9)


def test_make_scans_shapes_surface_and_ground_truth():
    body = BoxBody()
    starts = [torch.tensor([0.0, 1.0, 0.0]), torch.tensor([1.0, 0.5, 2.0])]
    motions = [make_motion(1.0, start=starts[0].tolist(), seed=1), make_motion(0.5, start=starts[1].tolist(), seed=2)]
    scans, gt = make_scans(body, motions, fps=50.0, num_points=400, seed=5)
    assert isinstance(scans, PointCloudSequence) and isinstance(gt, GroundTruth)
    assert scans.points.shape == (2, 51, 400, 3)
    assert scans.timestamps.dtype == torch.float64
    assert torch.equal(scans.frame_mask, gt.frame_mask)
    assert scans.frame_mask[1].sum() == 26
    assert torch.equal(scans.lengths, scans.frame_mask.long() * 400)
    assert bool((scans.points[1, 26:] == 0).all()), "padded frames hold no points"
    for b in range(2):
        n = int(scans.frame_mask[b].sum())
        t = scans.timestamps[b, :n]
        assert torch.allclose(t, torch.arange(n, dtype=torch.float64) / 50)
        local = to_box_frame(scans.points[b, :n], t, starts[b].double())
        assert box_surface_residual(local).abs().max() < 1e-5, "every point lies on the posed box"
        # every face of the box is hit (area-uniform sampling over the whole surface)
        face_hits = (local.abs() / HALF > 1 - 1e-5).sum((0, 1))
        assert bool((face_hits > 0).all())
        # ground truth vertices in closed form
        angle, trans = analytic_root(t, starts[b].double())
        expected = body.template.double() @ yaw(angle).transpose(-1, -2) + trans[:, None]
        assert torch.allclose(gt.vertices[b, :n].double(), expected, atol=1e-5)
        assert torch.allclose(gt.joints[b, :n, 0].double(), trans, atol=1e-5)
    # other timestamps: regenerate from the kept motions
    t30 = torch.arange(10, dtype=torch.float64) / 30
    later = gt.at(t30)
    angle, trans = analytic_root(t30, starts[1].double())
    expected = body.template.double() @ yaw(angle).transpose(-1, -2) + trans[:, None]
    assert later.vertices.shape == (2, 10, body.num_vertices, 3)
    assert torch.allclose(later.vertices[1].double(), expected, atol=1e-5)
    with pytest.raises(ValueError, match="motion 1 spans 0.0000 .. 0.5000 s"):
        gt.at(torch.tensor([0.0, 0.9]))
    # frames marked invalid may lie outside a motion; they are posed at its last frame
    ts = torch.tensor([[0.0, 0.9], [0.0, 0.9]], dtype=torch.float64)
    masked = ground_truth_at(body, motions, ts, frame_mask=torch.tensor([[True, True], [True, False]]))
    assert torch.allclose(masked.vertices[1, 1], gt.vertices[1, 25], atol=1e-5)


def test_make_scans_is_deterministic_and_chunk_independent():
    body = BoxBody()
    motions = [make_motion(0.3, seed=1), make_motion(0.4, seed=2), make_motion(0.2, seed=3)]
    a, _ = make_scans(body, motions, num_points=64, seed=11, noise_std=0.003)
    b, _ = make_scans(body, motions, num_points=64, seed=11, noise_std=0.003, chunk_frames=5)
    c, _ = make_scans(body, motions, num_points=64, seed=12, noise_std=0.003)
    assert torch.equal(a.points, b.points)
    assert not torch.allclose(a.points, c.points)


def test_a_seed_per_sequence_samples_each_sequence_whatever_the_batch():
    body = BoxBody()
    motions = [make_motion(0.3, seed=1), make_motion(0.3, seed=2)]
    both, _ = make_scans(body, motions, num_points=64, seed=[11, 12], noise_std=0.003)
    second, _ = make_scans(body, motions[1:], num_points=64, seed=[12], noise_std=0.003)
    assert torch.equal(both.points[1:], second.points)
    shared, _ = make_scans(body, motions, num_points=64, seed=11, noise_std=0.003)
    assert not torch.equal(shared.points[1:], second.points)  # one seed: sequence 1 draws after sequence 0
    with pytest.raises(ValueError, match=r"make_scans: `seed` must be an int or a list of 2 ints"):
        make_scans(body, motions, num_points=8, seed=[11, True])


def test_table1_data_seeds_by_sequence_give_a_sequence_its_data_in_any_batch():
    from benchmark.protocols.completion_unit import CompletionData
    from benchmark.protocols.unit_data import cell_degrade_seed

    spec = {"data": {"capture_fps": 50, "points_per_frame": 32, "scan_noise_std": 0.0, "window_s": 0.2,
                     "seeds": "sequence"}, "output_fps": 30}
    motions = {"a": make_motion(0.3, seed=1), "b": make_motion(0.3, seed=2)}
    source = CompletionData(spec, BoxBody(), motions, seed=7)
    both, alone = source.unit_data(["a", "b"]), source.unit_data(["b"])
    assert torch.equal(both.scans.points[1:], alone.scans.points)
    assert torch.equal(both.gt_points[1:], alone.gt_points)
    assert cell_degrade_seed(7, 100, 5, ["a", "b"], rule="sequence")[1] == cell_degrade_seed(7, 100, 5, ["b"], rule="sequence")[0]
    batch = CompletionData({**spec, "data": {**spec["data"], "seeds": "batch"}}, BoxBody(), motions, seed=7)
    assert not torch.equal(batch.unit_data(["a", "b"]).scans.points[1:], batch.unit_data(["b"]).scans.points)
    with pytest.raises(ValueError, match=r"field 'data.seeds' must be one of batch, sequence; got 'sequences'"):
        CompletionData({**spec, "data": {**spec["data"], "seeds": "sequences"}}, BoxBody(), motions, seed=7)


def test_shapes_follow_the_motions_and_mismatches_are_named():
    body = BoxBody()
    _, gt = make_scans(body, [make_motion(0.2, shape=torch.tensor([2.0]))], num_points=8)
    local = gt.vertices[0, 0] - gt.joints[0, 0, 0]  # the pelvis sits at the box centre; zero yaw at t = 0
    assert torch.allclose(local.abs().amax(0), 2 * HALF.float(), atol=1e-5), "the box is scaled by the motion's shape"
    with pytest.raises(ValueError, match=r"shape vector of size 3.*pass shapes="):
        make_scans(body, [make_motion(0.2, shape=torch.zeros(3))], num_points=8)


def test_make_landmarks():
    body = BoxBody()
    _, gt = make_scans(body, [make_motion(0.5), make_motion(0.3)], num_points=8)
    lm = make_landmarks(gt, body)
    assert isinstance(lm, Landmarks) and lm.positions.shape == (2, 26, 16, 3)
    m = gt.frame_mask
    assert torch.equal(lm.positions[m], gt.vertices[:, :, body.landmark_indices][m])
    assert bool((lm.positions[~m] == 0).all())
    assert torch.equal(lm.timestamps, gt.timestamps)
    noisy = make_landmarks(gt, body, noise_std=0.01, generator=torch.Generator().manual_seed(0))
    assert abs((noisy.positions[m] - lm.positions[m]).std().item() - 0.01) < 0.001
    with pytest.raises(ValueError, match="needs a torch.Generator"):
        make_landmarks(gt, body, noise_std=0.01)
    with pytest.raises(ValueError, match="pass timestamps"):
        make_landmarks(gt.vertices, body)
    direct = make_landmarks(gt.vertices, body, timestamps=gt.timestamps)
    assert torch.equal(direct.positions[m], lm.positions[m])


# --------------------------------------------------------------------------- noisy joints
def test_farthest_point_indices_by_hand():
    pts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [10, 0, 0]])
    # centroid 3.2 -> farthest is 10 (idx 4); then 0 (idx 0, 10 away); then 3 (min distance 3);
    # then 1 and 2 tie at distance 1: the lower index first
    assert farthest_point_indices(pts, 5).tolist() == [4, 0, 3, 1, 2]
    with pytest.raises(ValueError, match="count"):
        farthest_point_indices(pts, 6)


def naive_farthest_points(points: list[tuple[float, float, float]], count: int) -> list[int]:
    """Max-min selection written with plain loops (the reference for farthest_point_indices)."""
    c = [sum(p[i] for p in points) / len(points) for i in range(3)]
    chosen = [max(range(len(points)), key=lambda k: (math.dist(points[k], c), -k))]
    while len(chosen) < count:
        def spread(k):
            return min(math.dist(points[k], points[j]) for j in chosen)
        chosen.append(max(range(len(points)), key=lambda k: (spread(k), -k)))
    return chosen


def test_virtual_markers_match_a_naive_farthest_point_selection():
    body = BoxBody()
    idx = virtual_marker_indices(body, count=20)
    assert len(set(idx.tolist())) == 20
    reference = naive_farthest_points([tuple(map(float, v)) for v in body.template.double()], 20)
    # the box has many exact distance ties; compare the spread of the chosen sets, then the sets
    chosen = body.template.double()[idx]
    ref = body.template.double()[reference]
    assert torch.allclose(torch.pdist(chosen).min(), torch.pdist(ref).min())
    assert idx.tolist() == reference


def test_make_noisy_joints():
    body = BoxBody()
    motions = [make_motion(1.0, seed=4), make_motion(0.6, seed=5)]
    sigma = 0.1
    obs, gt = make_noisy_joints(motions, sigma, seed=7, body=body, marker_indices=torch.tensor([0, 3, 50, 97]))
    assert isinstance(obs, NoisyJoints)
    assert obs.rotations.shape == (2, 31, NUM_JOINTS, 3) and obs.markers.shape == (2, 31, 4, 3)
    m = obs.frame_mask
    assert m[1].sum() == 19 and torch.equal(m, gt.frame_mask)
    clean = torch.stack([torch.cat([mo.poses, mo.poses[-1:].expand(31 - len(mo.poses), -1, -1)]) for mo in motions])
    noise = (obs.rotations - clean)[m]
    assert abs(noise.std().item() - sigma) < 0.05 * sigma
    assert abs(noise.mean().item()) < 5 * sigma / math.sqrt(noise.numel())
    # markers: the box posed with the noisy root rotation (closed form), clean translation
    R = roma.rotvec_to_rotmat(obs.rotations[:, :, 0].double())  # (2, T, 3, 3)
    expected = body.template[obs.marker_indices].double() @ R.transpose(-1, -2) + obs.trans[..., None, :].double()
    assert torch.allclose(obs.markers[m].double(), expected[m], atol=1e-5)
    assert torch.allclose(obs.trans[0].double(), torch.stack([mo.trans for mo in motions[:1]])[0].double(), atol=1e-6)
    # ground truth is the clean motion
    angle, trans = analytic_root(gt.timestamps[0], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    expected = body.template.double() @ yaw(angle).transpose(-1, -2) + trans[:, None]
    assert torch.allclose(gt.vertices[0].double(), expected, atol=1e-5)
    # deterministic from the seed
    again, _ = make_noisy_joints(motions, sigma, seed=7, body=body, marker_indices=torch.tensor([0, 3, 50, 97]))
    other, _ = make_noisy_joints(motions, sigma, seed=8, body=body, marker_indices=torch.tensor([0, 3, 50, 97]))
    assert torch.equal(obs.rotations, again.rotations) and torch.equal(obs.markers, again.markers)
    assert not torch.allclose(obs.rotations[m], other.rotations[m])
    # default markers: 43 farthest-point vertices
    default, _ = make_noisy_joints(motions[:1], 0.0, body=body)
    assert default.marker_indices.shape == (43,)
    assert torch.equal(default.marker_indices, virtual_marker_indices(body))
    with pytest.raises(ValueError, match="marker_indices"):
        make_noisy_joints(motions, sigma, body=body, marker_indices=torch.tensor([98]))


def test_works_with_the_project_motion_class():
    motion = pytest.importorskip("benchmark.core.motion")
    stub = make_motion(0.5, start=(0.3, 1.0, -0.2), seed=3)
    real = motion.Motion(poses=stub.poses, trans=stub.trans, timestamps=stub.timestamps)
    body = BoxBody()
    scans, gt = make_scans(body, [real], num_points=200, seed=2)
    _, gt_stub = make_scans(body, [stub], num_points=200, seed=2)
    # the root turns about a fixed axis, so SLERP and the stub's linear interpolation agree
    assert torch.allclose(gt.vertices, gt_stub.vertices, atol=1e-5)
    local = to_box_frame(scans.points[0], scans.timestamps[0], torch.tensor([0.3, 1.0, -0.2], dtype=torch.float64))
    assert box_surface_residual(local).abs().max() < 1e-5
