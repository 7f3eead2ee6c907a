import math

import numpy as np
import pytest
import torch

from benchmark.body.lbs import forward_kinematics
from benchmark.loaders.bvh import CMU_JOINT_MAP, CMU_UNIT_M, load_bvh
from benchmark.loaders.bvh_format import BVHSkeleton, cmu_skeleton, parse_bvh, write_bvh
from benchmark.core.motion import joint_positions
from benchmark.core.rotations import axis_angle_to_matrix, geodesic_distance
from benchmark.core.skeleton import JOINT_NAMES, PARENTS

ALWAYS_ZERO = ("LHipJoint", "RHipJoint", "LeftShoulder", "RightShoulder")


# ----------------------------------------------------------------------------- naive references
def rodrigues(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def minimal_rotation(t, d):
    """Rotation about t x d taking direction t to direction d (naive)."""
    t, d = np.asarray(t, float) / np.linalg.norm(t), np.asarray(d, float) / np.linalg.norm(d)
    c = np.cross(t, d)
    if np.linalg.norm(c) < 1e-12:
        return np.eye(3)
    return rodrigues(c, math.atan2(np.linalg.norm(c), float(t @ d)))


def naive_bvh_fk(sk: BVHSkeleton, local: np.ndarray, root_pos: np.ndarray):
    """(F, J, 3, 3) locals, (F, 3) root positions -> globals (F, J, 3, 3), positions (F, J, 3)."""
    F, J = local.shape[:2]
    G, P = np.zeros((F, J, 3, 3)), np.zeros((F, J, 3))
    for f in range(F):
        for j, p in enumerate(sk.parents):
            if p < 0:
                G[f, j], P[f, j] = local[f, j], root_pos[f]
            else:
                G[f, j] = G[f, p] @ local[f, j]
                P[f, j] = P[f, p] + G[f, p] @ sk.offsets[j]
    return G, P


def smooth_rotations(F, J, seed, scale=0.6):
    rng = np.random.default_rng(seed)
    t = np.arange(F)[:, None, None] / 120.0
    a, b = rng.normal(size=(1, J, 3)) * scale * 0.5, rng.normal(size=(1, J, 3)) * scale
    w, ph = rng.uniform(2, 6, size=(1, J, 3)), rng.uniform(0, 6, size=(1, J, 3))
    aa = a + b * np.sin(w * t + ph)
    return axis_angle_to_matrix(torch.from_numpy(aa)).numpy()


def expected_corrections(sk: BVHSkeleton, twist=None):
    """C_j per SMPL joint from the skeleton's offsets and the joint map's T-pose directions."""
    twist = twist or {}
    P = sk.rest_positions()
    C = np.tile(np.eye(3), (22, 1, 1))
    for j, name in enumerate(JOINT_NAMES):
        src = CMU_JOINT_MAP[name]
        if src.direction is None:
            continue
        anchor = sk.names.index(src.chain[-1])
        d = P[sk.names.index(src.tip)] - P[anchor]
        C[j] = minimal_rotation(src.direction, d) @ rodrigues(src.direction, math.radians(twist.get(name, 0.0)))
    return C


# ----------------------------------------------------------------------------- tests
def test_cmu_unit():
    assert abs(CMU_UNIT_M - 0.056444) < 1e-6
    assert abs(CMU_UNIT_M - 0.0254 / 0.45) < 1e-15


def test_cmu_round_trip_global_orientations_and_positions(tmp_path):
    sk = cmu_skeleton()
    J, F = len(sk.names), 24
    assert J == 31
    local = smooth_rotations(F, J, seed=1)
    for name in ALWAYS_ZERO:
        local[:, sk.names.index(name)] = np.eye(3)
    rng = np.random.default_rng(2)
    root = np.cumsum(rng.normal(scale=0.2, size=(F, 3)), axis=0) + [0.0, 17.0, 0.0]
    # frame 0: the converter's T-pose
    local_file = np.concatenate([np.tile(np.eye(3), (1, J, 1, 1)), local])
    root_file = np.concatenate([[[0.0, 17.0, 0.0]], root])
    path = write_bvh(tmp_path / "01_01.bvh", sk, local_file, root_file, frame_time=1 / 120)

    m = load_bvh(path)
    assert m.num_frames == F  # frame 0 dropped
    assert m.fps == pytest.approx(120.0) and float(m.timestamps[0]) == 0.0
    assert m.meta["dropped_first_frame"] is True and m.meta["unit_m"] == CMU_UNIT_M

    # the legs are splayed 20 degrees in the CMU rest pose
    assert m.meta["rest_correction_deg"]["left_hip"] == pytest.approx(20.0, abs=0.01)
    C = expected_corrections(sk)
    np.testing.assert_allclose(C[JOINT_NAMES.index("left_hip")], rodrigues([0, 0, 1], math.radians(20.0)), atol=1e-4)

    Gb, Pb = naive_bvh_fk(sk, local, root)
    rest = torch.tensor(m.meta["rest_joints"], dtype=torch.float64)
    G, _ = forward_kinematics(m.rotmats().double(), rest)
    for j, name in enumerate(JOINT_NAMES):
        last = sk.names.index(CMU_JOINT_MAP[name].chain[-1])
        expected = torch.from_numpy(Gb[:, last] @ C[j])
        err = geodesic_distance(G[:, j], expected).max().item()
        assert err < 1e-5, f"{name}: global orientation off by {err} rad"

    jp = joint_positions(m, rest.float()).double()
    for j, name in enumerate(JOINT_NAMES):
        if name == "head":  # folds Neck1, a bone with length and rotation: position not preserved
            continue
        anchor = sk.names.index(CMU_JOINT_MAP[name].chain[-1])
        np.testing.assert_allclose(jp[:, j].numpy(), Pb[:, anchor] * CMU_UNIT_M, atol=1e-5, err_msg=name)
    np.testing.assert_allclose(m.trans.double().numpy(), root * CMU_UNIT_M, atol=1e-6)


def test_any_rest_pose_and_twist_recover_smpl_rotations(tmp_path):
    """A non-CMU rest pose (A-pose arms, legs splayed forward and out, twisted arms): writing
    BVH rotations R_bvh = C_parent R_smpl C_j^T and loading must give back R_smpl."""
    sk = cmu_skeleton()
    offsets = sk.offsets.copy()
    ends = {k: v.copy() for k, v in sk.end_sites.items()}
    arm_l, arm_r = rodrigues([0, 0.3, 1.0], -0.6), rodrigues([0, -0.2, 1.0], 0.5)
    leg_l, leg_r = rodrigues([1, 0, 0.4], -0.3), rodrigues([1, 0, -0.3], -0.2)
    groups = [
        (("LeftForeArm", "LeftHand", "LeftHandIndex1", "LThumb"), arm_l),
        (("RightForeArm", "RightHand", "RightHandIndex1", "RThumb"), arm_r),
        (("LeftLeg", "LeftFoot", "LeftToeBase"), leg_l),
        (("RightLeg", "RightFoot", "RightToeBase"), leg_r),
    ]
    for names, Rg in groups:
        for n in names:
            i = sk.names.index(n)
            offsets[i] = Rg @ offsets[i]
            if i in ends:
                ends[i] = Rg @ ends[i]
    sk = BVHSkeleton(sk.names, sk.parents, offsets, sk.channels, ends)
    twist = {"left_shoulder": 30.0, "left_elbow": 30.0, "left_wrist": 30.0, "right_shoulder": -30.0}
    C = expected_corrections(sk, twist)

    F, J = 12, len(sk.names)
    R_smpl = smooth_rotations(F, 22, seed=5, scale=0.8)
    R_smpl[:, 1:] = smooth_rotations(F, 21, seed=6, scale=0.8)
    local = np.tile(np.eye(3), (F, J, 1, 1))
    extra = smooth_rotations(F, J, seed=7)  # for the first joint of 2-joint chains and the fingers
    for n in ("LeftHandIndex1", "RightHandIndex1", "LThumb", "RThumb"):
        local[:, sk.names.index(n)] = extra[:, sk.names.index(n)]
    for j, name in enumerate(JOINT_NAMES):
        Cp = C[PARENTS[j]] if PARENTS[j] >= 0 else np.eye(3)
        target = Cp @ R_smpl[:, j] @ C[j].T
        chain = [sk.names.index(b) for b in CMU_JOINT_MAP[name].chain]
        if len(chain) == 2 and sk.names[chain[0]] not in ALWAYS_ZERO:
            Q = extra[:, chain[0]]
            local[:, chain[0]] = Q
            target = np.swapaxes(Q, -1, -2) @ target
        local[:, chain[-1]] = target
    path = write_bvh(tmp_path / "apose.bvh", sk, local, np.zeros((F, 3)), frame_time=0.01)

    m = load_bvh(path, drop_first_frame=False, unit=0.01, rest_twist_deg=twist)
    assert m.fps == pytest.approx(100.0)
    err = geodesic_distance(m.rotmats().double(), torch.from_numpy(R_smpl))
    assert err.max().item() < 1e-5
    # without the twist, the twisted joints come out wrong (the twist is not in the offsets)
    m0 = load_bvh(path, drop_first_frame=False, unit=0.01)
    err0 = geodesic_distance(m0.rotmats().double(), torch.from_numpy(R_smpl))
    # shoulder: parent (collar) untwisted, so the error is exactly the twist angle
    np.testing.assert_allclose(err0[:, JOINT_NAMES.index("left_shoulder")].numpy(), math.radians(30.0), atol=1e-5)
    assert err0[:, JOINT_NAMES.index("left_hip")].max().item() < 1e-5


def test_unit_frame_drop_and_resampling(tmp_path):
    sk = cmu_skeleton()
    F, J = 121, len(sk.names)
    local = np.tile(np.eye(3), (F, J, 1, 1))
    root = np.zeros((F, 3))
    root[:, 1] = 10.0
    root[:, 2] = np.arange(F) * 0.5  # walks along +z, 0.5 unit per frame
    root[0] = [99.0, 99.0, 99.0]  # the T-pose frame, somewhere else
    path = write_bvh(tmp_path / "walk.bvh", sk, local, root, frame_time=0.008333)
    m = load_bvh(path)
    assert m.num_frames == 120
    np.testing.assert_allclose(m.trans[0].numpy(), [0.0, 10 * 0.056444, 0.5 * 0.056444], atol=1e-5)
    assert m.meta["fps"] == 120.0  # 1 / 0.008333 snapped to 120
    m_all = load_bvh(path, drop_first_frame=False)
    assert m_all.num_frames == 121 and m_all.trans[0, 0].item() == pytest.approx(99.0 * CMU_UNIT_M, rel=1e-6)
    m30 = load_bvh(path, fps=30.0)
    assert m30.num_frames == 30  # frames 1..120 span 119/120 s -> t = 0, 1/30, ..., 29/30
    # velocity 0.5 unit per 1/120 s -> z advances 2 units per 1/30 s
    np.testing.assert_allclose(np.diff(m30.trans[:, 2].numpy()), 2 * CMU_UNIT_M, atol=1e-5)


def test_parse_non_cmu_channel_order_by_hand(tmp_path):
    text = """HIERARCHY
ROOT root
{
  OFFSET 1 2 3
  CHANNELS 6 Xposition Yposition Zposition Xrotation Yrotation Zrotation
  JOINT child
  {
    OFFSET 0 1 0
    CHANNELS 3 Yrotation Xrotation Zrotation
    End Site
    {
      OFFSET 0 1 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.02
0 0 0 90 0 0   0 0 0
1 2 3 10 20 30 40 50 60
"""
    p = tmp_path / "tiny.bvh"
    p.write_text(text)
    d = parse_bvh(p)
    assert d.skeleton.names == ["root", "child"] and d.skeleton.parents == [-1, 0]
    assert d.frame_time == 0.02 and d.values.shape == (2, 9)
    np.testing.assert_allclose(d.skeleton.end_sites[1], [0, 1, 0])
    R = d.local_rotations().numpy()
    r = np.radians
    Rx = lambda a: rodrigues([1, 0, 0], a)
    Ry = lambda a: rodrigues([0, 1, 0], a)
    Rz = lambda a: rodrigues([0, 0, 1], a)
    np.testing.assert_allclose(R[0, 0], Rx(r(90)), atol=1e-12)
    np.testing.assert_allclose(R[1, 0], Rx(r(10)) @ Ry(r(20)) @ Rz(r(30)), atol=1e-12)
    np.testing.assert_allclose(R[1, 1], Ry(r(40)) @ Rx(r(50)) @ Rz(r(60)), atol=1e-12)
    np.testing.assert_allclose(d.root_positions(), [[1, 2, 3], [2, 4, 6]])

    p.write_text(text.replace("1 2 3 10 20 30 40 50 60\n", "1 2 3 10 20 30 40\n"))
    with pytest.raises(ValueError, match=r"tiny.bvh: MOTION holds 16 numbers, expected Frames \(2\) x channels \(9\) = 18"):
        parse_bvh(p)
    p.write_text(text.replace("Yrotation Xrotation Zrotation", "Yrotation Xrotation Wrotation"))
    with pytest.raises(ValueError, match=r"tiny.bvh:9: unknown channel 'Wrotation'"):
        parse_bvh(p)
    # a file written with a UTF-8 byte-order mark (some Windows exporters) reads the same
    p.write_text(text, encoding="utf-8-sig")
    np.testing.assert_array_equal(parse_bvh(p).values, d.values)
    # a BVH skeleton without the CMU joints needs its own joint map
    p.write_text(text)
    with pytest.raises(ValueError, match=r"maps to BVH joint 'Hips', which the file lacks.*joint_map"):
        load_bvh(p)


def test_axes_are_checked_from_offsets(tmp_path):
    sk = cmu_skeleton()
    mirrored = BVHSkeleton(sk.names, sk.parents, sk.offsets * [1, 1, -1], sk.channels,
                           {k: v * [1, 1, -1] for k, v in sk.end_sites.items()})  # faces -z
    F = 3
    path = write_bvh(tmp_path / "back.bvh", mirrored, np.tile(np.eye(3), (F, 31, 1, 1)), np.zeros((F, 3)), 1 / 120)
    with pytest.raises(ValueError, match=r"back.bvh: .*facing \+z"):
        load_bvh(path)
    assert load_bvh(path, check_axes=False).num_frames == 2
