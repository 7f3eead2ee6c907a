"""Published numbers checked against values computed independently in the test (by hand or with a
few lines of numpy/torch): each test here catches a small, plausible bug that the rest of the default
suite let through (a hand mutation-testing audit; the bug each catches is named in its docstring).

- table1's evaluation (:func:`benchmark.protocols.completion_unit.evaluate` and its reference) on a
  one-triangle mesh: both Chamfer columns and MPJPE over every joint;
- table1's 30 fps output grid: frame 0 at the window start, ground truth at ``k / 30`` s;
- inbetween's scored frames: exactly the missing frames, the pelvis-centred pose, the acceleration
  centred on each missing frame;
- reconstruction's reference figures: V2V over every frame, the ground truth's root path length.
"""

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from benchmark.core.motion import Motion


# -------------------------------------------------------------------------------- table1 evaluation

def _triangle_unit():
    """One sequence, two output frames of a one-triangle mesh, a two-point ground-truth scan, four joints.

    Frame 0: vertices (0,0,0), (1,0,0), (0,1,0); scan points (0.2,0.2,0.5) (above the triangle's
    interior: 0.5 from its plane) and (1,0,0) (on a vertex). Frame 1: the mesh lifted by 0.1 in z,
    the same scan. Output joints: the ground truth's, the pelvis off by 0.3 m and joint 1 by 0.4 m.
    """
    from benchmark.protocols.unit_data import UnitData

    # each corner listed three times (9 vertices, one face): the means over vertices are those of the
    # three corners, and the reference's 8 nearest-vertex query has 8 vertices to find
    tri = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]).repeat(3, 1)
    verts = torch.stack([tri, tri + torch.tensor([0.0, 0.0, 0.1])])[None]  # (1, 2, 9, 3)
    scan = torch.tensor([[0.2, 0.2, 0.5], [1.0, 0.0, 0.0]])
    gt_points = scan.expand(1, 2, 2, 3).clone()
    gt_joints = torch.randn(1, 2, 4, 3, generator=torch.Generator().manual_seed(0))
    out_joints = gt_joints.clone()
    out_joints[..., 0, 0] += 0.3
    out_joints[..., 1, 1] -= 0.4
    body = SimpleNamespace(faces=torch.tensor([[0, 1, 2]]))
    output = SimpleNamespace(vertices=verts, joints=out_joints)
    data = UnitData(scans=None, out_t=torch.zeros(1, 2), gt_points=gt_points, gt_joints=gt_joints)
    return body, output, data


def _triangle_expected():
    """The per-sequence sums (metres, summed over the two frames), by hand."""
    sums = {"chamfer_m": 0.0, "chamfer_surface_m": 0.0, "mpjpe_m": 0.0}
    for z in (0.0, 0.1):
        v = np.array([[0, 0, z], [1, 0, z], [0, 1, z]], dtype=np.float64)
        s = np.array([[0.2, 0.2, 0.5], [1, 0, 0]], dtype=np.float64)
        d = np.linalg.norm(v[:, None] - s[None], axis=-1)  # (3 vertices, 2 scan points)
        vert_to_scan = d.min(1).mean()
        scan_to_vert = d.min(0).mean()
        # the first scan point projects inside the triangle: its surface distance is its height above
        # the plane; the second is at distance z from vertex (1, 0, z), the nearest surface point
        scan_to_surface = np.mean([0.5 - z, z])
        sums["chamfer_m"] += 0.5 * (vert_to_scan + scan_to_vert)
        sums["chamfer_surface_m"] += 0.5 * (vert_to_scan + scan_to_surface)
        sums["mpjpe_m"] += (0.3 + 0.4 + 0.0 + 0.0) / 4  # every joint counts, the pelvis included
    return sums


@pytest.mark.parametrize("which", ["evaluate", "evaluate_reference"])
def test_table1_evaluation_by_hand_on_one_triangle(which):
    """Catches: a Chamfer direction or its 0.5 dropped, the surface column not using the triangles,
    MPJPE over a joint subset (e.g. without the pelvis) or the wrong axis, frames miscounted."""
    from benchmark.protocols import completion_unit

    body, output, data = _triangle_unit()
    rows = getattr(completion_unit, which)(body, output, data, "cpu")
    assert len(rows) == 1 and rows[0]["frames"] == 2
    expected = _triangle_expected()
    assert set(rows[0]["sums"]) == set(expected)
    for key, value in expected.items():
        assert rows[0]["sums"][key] == pytest.approx(value, abs=1e-6), key
    # hand numbers for frame 0: sqrt(0.33) = 0.5745 from (0,0,0), 0 from (1,0,0), sqrt(0.93) from (0,1,0)
    f0 = 0.5 * ((math.sqrt(0.33) + 0.0 + math.sqrt(0.93)) / 3 + (math.sqrt(0.33) + 0.0) / 2)
    assert _triangle_expected()["chamfer_m"] > f0 > 0.4  # the reference above is not all zeros


# -------------------------------------------------------------------------------- table1 output grid

def _accelerating_motion(accel: float = 2.0, seconds: float = 1.0, fps: float = 100.0) -> Motion:
    """Rest pose (every rotation zero), translation x = accel * t^2 / 2: the pelvis lies at
    rest_pelvis + trans, so its x difference between two instants tells the instants apart."""
    n = int(round(seconds * fps)) + 1
    t = torch.arange(n, dtype=torch.float64) / fps
    trans = torch.zeros(n, 3)
    trans[:, 0] = (0.5 * accel * t * t).float()
    return Motion(poses=torch.zeros(n, 22, 3), trans=trans, timestamps=t, shape=torch.full((6,), 0.5), body="anny",
                  source="accelerating")


def test_table1_ground_truth_is_at_the_30fps_output_frames_from_the_window_start(anny_body):
    """Catches: the output grid shifted by a frame (k + 1) / 30 or off the window start; the unit's
    ground-truth joints are then those of other instants."""
    from benchmark.protocols.completion_unit import CompletionData
    from benchmark.run.catalog import load_table_spec

    spec = load_table_spec("table1")
    spec = {**spec, "data": {**spec["data"], "window_s": 0.5, "points_per_frame": 50}}
    accel = 2.0
    data = CompletionData(spec, anny_body, {"m": _accelerating_motion(accel)}, seed=0).unit_data(["m"])
    n_out = 15  # 0.5 s at 30 fps
    assert spec["output_fps"] == 30
    assert data.out_t.shape == (1, n_out)
    assert torch.allclose(data.out_t[0], torch.arange(n_out, dtype=torch.float64) / 30.0, rtol=0, atol=1e-12)
    # the window starts at the motion's first frame (t = 0): pelvis x at output frame k minus at
    # frame 0 is accel * (k / 30)^2 / 2 (a shifted grid gives accel * ((k + 1)^2 - 1) / 1800)
    pelvis_x = data.gt_joints[0, :, 0, 0].double()
    k = torch.arange(n_out, dtype=torch.float64)
    expected = 0.5 * accel * (k / 30.0) ** 2
    assert torch.allclose(pelvis_x - pelvis_x[0], expected, atol=5e-4), (pelvis_x - pelvis_x[0], expected)


# -------------------------------------------------------------------------------- inbetween

def _waving_motion(seconds: float = 2.2, fps: float = 50.0) -> Motion:
    g = torch.Generator().manual_seed(5)
    n = int(round(seconds * fps))
    t = torch.arange(n, dtype=torch.float64) / fps
    amp = torch.rand(22, 3, generator=g) * 0.4
    phase = torch.rand(22, 3, generator=g) * 2 * math.pi
    poses = amp * torch.sin(2 * math.pi * 1.5 * t[:, None, None].float() + phase)
    trans = torch.stack([0.3 * t.float(), 0.05 * torch.sin(5 * t.float()), 1.1 * t.float()], -1)
    return Motion(poses=poses, trans=trans, timestamps=t, shape=torch.full((6,), 0.5), body="anny", source="wave")


def test_inbetween_scores_exactly_the_missing_frames(anny_body):
    """The SLERP baseline's unit against a reference computed here: SLERP / LERP between the last
    context frame and the key frame, errors over the ``gap`` missing frames only, the local pose
    relative to joint 0 (the pelvis), the acceleration centred on each missing frame at 30 fps.
    Catches: the scored span off by one frame, the pelvis taken as another joint."""
    from benchmark.core.rotations import slerp_matrices
    from benchmark.core.work_units import plan_units
    from benchmark.protocols import inbetween, motion_fit
    from benchmark.run.catalog import get_profile, load_table_spec
    from priors.slerp import SlerpBaseline

    spec = load_table_spec("inbetween")
    src = inbetween.make_source(spec, anny_body, {"a": _waving_motion()}, seed=0)
    gap, ctx = 5, 10
    profile = {**get_profile("smoke"), "steps": 4}
    unit = next(u for u in plan_units(spec, profile, ["slerp"], ["a"], 0, "cpu", {"slerp": {}}) if u.cell == {"gap": gap})
    result = inbetween.run_unit(unit, spec, profile, SlerpBaseline(), anny_body, src, "cpu")
    row = result["per_sequence"][0]
    assert row["frames"] == gap

    clean = src.clean(["a"])
    key = ctx + gap
    fps = 30.0
    assert clean.fps == pytest.approx(fps)
    # reference output on frames ctx - 1 .. key (the missing frames and their two observed neighbours)
    w = (torch.arange(ctx - 1, key + 1, dtype=torch.float64) - (ctx - 1)) / (key - (ctx - 1))
    rot = slerp_matrices(clean.rotations[:, ctx - 1:ctx], clean.rotations[:, key:key + 1], w[None, :, None].float())
    t0, t1 = clean.trans[:, ctx - 1:ctx], clean.trans[:, key:key + 1]
    trans = t0 + w[None, :, None].to(t0) * (t1 - t0)
    joints = motion_fit.joints_of(anny_body, clean.shapes, rot, trans).double()[0]  # (gap + 2, 22, 3)
    gt = clean.joints[0, ctx - 1:key + 1].double()
    local, gt_local = joints - joints[:, :1], gt - gt[:, :1]
    missing = slice(1, -1)  # frames ctx .. key - 1
    expected = {
        "mpjpe_m": (joints[missing] - gt[missing]).norm(dim=-1).mean(-1).sum(),
        "mpjpe_local_m": (local[missing] - gt_local[missing]).norm(dim=-1).mean(-1).sum(),
        "accel_mps2": ((local[2:] - 2 * local[1:-1] + local[:-2]) * fps ** 2).norm(dim=-1).mean(-1).sum(),
        "gt_accel_mps2": ((gt_local[2:] - 2 * gt_local[1:-1] + gt_local[:-2]) * fps ** 2).norm(dim=-1).mean(-1).sum(),
    }
    assert float(expected["mpjpe_local_m"]) > 1e-3  # the gap is not trivially filled
    for name, value in expected.items():
        assert float(row["sums"][name]) == pytest.approx(float(value), rel=1e-4, abs=1e-7), name


# -------------------------------------------------------------------------------- reconstruction

class _TranslatingBody:
    """A stand-in body whose vertices are fixed offsets plus the translation (rotations ignored):
    the V2V of two posings is then the distance between their translations, frame by frame."""

    offsets = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.2, 0.0]])

    def prepare(self, shapes):
        return None

    def skin(self, rest, rot, trans, vertex_indices=None):
        return SimpleNamespace(vertices=trans[..., None, :] + self.offsets)


def test_v2v_sums_every_frame():
    """Catches: a chunked sum that drops a frame (the last, or one at a chunk edge)."""
    from benchmark.protocols.motion_fit import v2v_sums

    B, T = 2, 700  # more frames than one chunk of chunk_frames(2) = 256
    rot = torch.zeros(B, T, 22, 3, 3)
    trans_a = torch.zeros(B, T, 3)
    trans_b = torch.zeros(B, T, 3)
    trans_b[0, :, 0] = 0.01  # 1 cm at every frame
    trans_b[1, -1, 2] = 0.5  # only the last frame differs
    got = v2v_sums(_TranslatingBody(), None, rot, trans_a, rot, trans_b)
    assert got.tolist() == pytest.approx([0.01 * T, 0.5], rel=1e-6)


def test_root_path_length_is_the_path_not_the_displacement():
    """``gt_travel``: the ground-truth root's path length (a square walked back to its start is 4
    sides long, its displacement 0); ``root``: the mean root distance over frames."""
    from benchmark.protocols.reconstruction import root_path_errors

    square = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1], [0, 0, 0]], dtype=torch.float32)
    gt = torch.zeros(1, 5, 22, 3)
    gt[0, :, 0] = square
    fit = gt.clone()
    fit[0, :, 0, 1] += torch.tensor([0.0, 0.1, 0.2, 0.3, 0.4])  # the root off by 0..0.4 m in height
    err, travel = root_path_errors(fit, gt)
    assert travel == pytest.approx([4.0])
    assert err == pytest.approx([0.2])
