import numpy as np
import pytest
import torch

from benchmark.core.motion import Motion, joint_positions, stack_motions
from benchmark.core.rotations import axis_angle_to_matrix, geodesic_distance


def make_motion(T=12, fps=30.0, seed=0, t0=0.0):
    g = torch.Generator().manual_seed(seed)
    poses = 0.4 * torch.randn(T, 22, 3, generator=g)
    trans = torch.randn(T, 3, generator=g)
    ts = t0 + torch.arange(T, dtype=torch.float64) / fps
    return Motion(poses, trans, ts, shape=torch.randn(10, generator=g), body="anny", source="test", meta={"k": 1})


def test_properties():
    m = make_motion(T=121, fps=30.0)
    assert m.num_frames == 121
    assert abs(m.fps - 30.0) < 1e-9
    assert abs(m.span - 4.0) < 1e-12
    assert abs(m.duration - 121 / 30) < 1e-12
    assert abs(make_motion(T=120, fps=30.0).duration - 4.0) < 1e-12
    R = m.rotmats()
    assert R.shape == (121, 22, 3, 3)
    np.testing.assert_allclose(R[5, 7].numpy(), axis_angle_to_matrix(m.poses[5, 7]).numpy(), atol=1e-6)
    assert m.poses.dtype == torch.float32 and m.timestamps.dtype == torch.float64


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(poses=torch.zeros(5, 24, 3)), r"field 'poses' has shape \(5, 24, 3\), expected \(T, 22, 3\)"),
        (dict(poses=torch.zeros(5, 66)), r"reshape"),
        (dict(trans=torch.zeros(4, 3)), r"field 'trans'"),
        (dict(timestamps=torch.tensor([0.0, 0.1, 0.1, 0.3, 0.4])), r"field 'timestamps' is not strictly increasing at index 1"),
        (dict(trans=torch.full((5, 3), float("nan"))), r"field 'trans' has 15 non-finite"),
        (dict(shape=torch.zeros(2, 3)), r"field 'shape'"),
    ],
)
def test_validation_names_the_field(kwargs, message):
    base = dict(poses=torch.zeros(5, 22, 3), trans=torch.zeros(5, 3), timestamps=torch.arange(5) / 10.0)
    base.update(kwargs)
    with pytest.raises(ValueError, match=message):
        Motion(**base)


def test_resample_slerp_midpoint_and_linear_translation():
    poses = torch.zeros(2, 22, 3)
    poses[0, 3] = torch.tensor([0.0, 0.0, 0.2])  # spine1: 0.2 rad about z
    poses[1, 3] = torch.tensor([0.0, 0.0, 1.0])  # 1.0 rad about z
    poses[1, 5] = torch.tensor([1.2, 0.0, 0.0])  # right knee: 0 -> 1.2 rad about x
    trans = torch.tensor([[0.0, 1.0, 0.0], [2.0, 1.0, -4.0]])
    m = Motion(poses, trans, torch.tensor([1.0, 2.0], dtype=torch.float64))
    r = m.resample([1.0, 1.25, 1.5, 2.0])
    np.testing.assert_allclose(r.poses[2, 3].numpy(), [0, 0, 0.6], atol=1e-6)
    np.testing.assert_allclose(r.poses[1, 5].numpy(), [0.3, 0, 0], atol=1e-6)
    np.testing.assert_allclose(r.trans[1].numpy(), [0.5, 1.0, -1.0], atol=1e-6)
    np.testing.assert_allclose(r.poses[0].numpy(), poses[0].numpy(), atol=1e-6)
    np.testing.assert_allclose(r.poses[3].numpy(), poses[1].numpy(), atol=1e-6)
    # outside the span: clamped to the end frames
    c = m.resample([0.0, 3.0])
    np.testing.assert_allclose(c.trans.numpy(), trans.numpy(), atol=1e-6)
    np.testing.assert_allclose(c.poses.numpy(), poses.numpy(), atol=1e-6)


def naive_resample(m: Motion, new_t):
    """Per-frame reference: bracket by a linear scan, interpolate the rotation as
    R0 exp(w log(R0^T R1)) with scipy, translation linearly."""
    from scipy.spatial.transform import Rotation as Rot

    t = m.timestamps.numpy()
    out_p, out_t = [], []
    for s in new_t:
        i = max(0, min(len(t) - 2, int(np.searchsorted(t, s, side="right")) - 1))
        w = min(1.0, max(0.0, (s - t[i]) / (t[i + 1] - t[i])))
        R0 = Rot.from_rotvec(m.poses[i].double().numpy())
        R1 = Rot.from_rotvec(m.poses[i + 1].double().numpy())
        rel = (R0.inv() * R1).as_rotvec()
        out_p.append((R0 * Rot.from_rotvec(w * rel)).as_matrix())
        out_t.append((1 - w) * m.trans[i].double().numpy() + w * m.trans[i + 1].double().numpy())
    return np.stack(out_p), np.stack(out_t)


@pytest.mark.parametrize("src_fps", [120.0, 50.0])
def test_resample_non_integer_ratio_matches_naive(src_fps):
    m = make_motion(T=int(src_fps) + 1, fps=src_fps, seed=3)  # 1 s of motion
    r = m.resample_fps(30.0)
    assert r.num_frames == 31
    np.testing.assert_allclose(r.timestamps.numpy(), np.arange(31) / 30.0, atol=1e-12)
    R_ref, t_ref = naive_resample(m, r.timestamps.numpy())
    err = geodesic_distance(r.rotmats().double(), torch.from_numpy(R_ref))
    assert err.max().item() < 1e-5
    np.testing.assert_allclose(r.trans.numpy(), t_ref, atol=1e-5)
    assert r.meta["resampled"]["to_fps"] == 30.0
    if src_fps == 50.0:
        # t = 1/30 lies 2/3 of the way from frame 1 to frame 2 at 50 fps
        np.testing.assert_allclose(r.trans[1].numpy(), (m.trans[1] + (m.trans[2] - m.trans[1]) * (2 / 3)).numpy(), atol=1e-5)


def test_window():
    m = make_motion(T=150, fps=30.0, t0=2.0)
    w = m.window(3.0, 4.0)
    assert w.num_frames == 120
    assert abs(float(w.timestamps[0]) - 3.0) < 1e-9
    np.testing.assert_allclose(w.poses.numpy(), m.poses[30:150].numpy())
    assert m.window(3.0, 2.0).num_frames == 60
    with pytest.raises(ValueError, match="outside"):
        m.window(3.1, 4.0)


def test_save_load_round_trip(tmp_path):
    m = make_motion(T=20, fps=50.0)
    m.meta["nested"] = {"a": [1, 2], "arr": np.arange(3)}
    p = m.save(tmp_path / "m.npz")
    with np.load(p, allow_pickle=False) as z:
        assert set(z.files) >= {"poses", "trans", "timestamps", "fps", "shape", "body", "source"}
        assert z["source"].shape == () and z["source"].dtype.kind == "U"
        assert abs(float(z["fps"]) - 50.0) < 1e-9
    m2 = Motion.load(p)
    assert torch.equal(m2.poses, m.poses) and torch.equal(m2.trans, m.trans)
    assert torch.equal(m2.timestamps, m.timestamps) and torch.equal(m2.shape, m.shape)
    assert m2.body == "anny" and m2.source == "test"
    assert m2.meta == {"k": 1, "nested": {"a": [1, 2], "arr": [0, 1, 2]}}


def test_load_errors_name_file_and_field(tmp_path):
    p = tmp_path / "motion.npz"
    np.savez(p, poses=np.zeros((10, 24, 3)), trans=np.zeros((10, 3)), timestamps=np.arange(10) / 30.0)
    with pytest.raises(ValueError, match=r"motion.npz: field 'poses' has shape \(10, 24, 3\), expected \(T, 22, 3\)"):
        Motion.load(p)
    np.savez(p, poses=np.zeros((10, 22, 3)), timestamps=np.arange(10) / 30.0)
    with pytest.raises(KeyError, match=r"motion.npz: missing field 'trans'"):
        Motion.load(p)
    np.savez(p, poses=np.zeros((10, 22, 3)), trans=np.zeros((10, 3)), timestamps=np.arange(10) / 30.0, fps=60.0)
    with pytest.raises(ValueError, match=r"field 'fps' = 60.0 disagrees"):
        Motion.load(p)
    np.savez(p, poses=np.zeros((10, 22, 3)), trans=np.zeros((10, 3)), timestamps=np.arange(10) / 30.0,
             source=np.array(["a", None], dtype=object))
    with pytest.raises(ValueError, match=r"motion.npz: cannot read without pickle"):
        Motion.load(p)
    np.savez(p, poses=np.zeros((10, 22, 3)), trans=np.zeros((10, 3)), fps=25.0, shape=np.array("abc"))
    with pytest.raises(ValueError, match=r"motion.npz: field 'shape' has non-numeric dtype"):
        Motion.load(p)
    # fps alone is enough for a hand-written file
    np.savez(p, poses=np.zeros((10, 22, 3)), trans=np.zeros((10, 3)), fps=25.0)
    m = Motion.load(p)
    np.testing.assert_allclose(m.timestamps.numpy(), np.arange(10) / 25.0)


def test_stack_and_joint_positions_match_naive_fk():
    a, b = make_motion(T=6, seed=1), make_motion(T=6, seed=2)
    rot, trans, ts = stack_motions([a, b])
    assert rot.shape == (2, 6, 22, 3, 3) and trans.shape == (2, 6, 3) and ts.shape == (2, 6)
    rest = torch.randn(22, 3)
    jp = joint_positions(a, rest)
    assert jp.shape == (6, 22, 3)
    # naive FK, one frame and joint at a time
    from benchmark.core.skeleton import PARENTS

    R = a.rotmats().double()
    for t in [0, 5]:
        G, P = [None] * 22, [None] * 22
        for j, p in enumerate(PARENTS):
            if p < 0:
                G[j], P[j] = R[t, j], rest[j].double()
            else:
                G[j] = G[p] @ R[t, j]
                P[j] = P[p] + G[p] @ (rest[j] - rest[p]).double()
        np.testing.assert_allclose(jp[t].numpy(), (torch.stack(P) + a.trans[t].double()).numpy(), atol=1e-5)
    jb = joint_positions([a, b], rest)
    assert jb.shape == (2, 6, 22, 3)
    np.testing.assert_allclose(jb[0].numpy(), jp.numpy(), atol=1e-6)
    jb2 = joint_positions((rot, trans), torch.stack([rest, rest]))
    np.testing.assert_allclose(jb2.numpy(), jb.numpy(), atol=1e-6)
    with pytest.raises(ValueError, match="motion 1"):
        stack_motions([a, make_motion(T=7)])


def test_save_is_byte_deterministic(tmp_path):
    import time

    import torch

    from benchmark.core.motion import Motion

    m = Motion(poses=torch.zeros(3, 22, 3), trans=torch.zeros(3, 3),
               timestamps=torch.arange(3, dtype=torch.float64) / 30, source="x", meta={"a": 1})
    a = m.save(tmp_path / "a.npz")
    time.sleep(1.1)
    b = m.save(tmp_path / "b.npz")
    assert a.read_bytes() == b.read_bytes()
    assert Motion.load(b).source == "x"
