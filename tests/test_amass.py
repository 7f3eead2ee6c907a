import math

import numpy as np
import pytest
import torch

from benchmark.body.lbs import forward_kinematics
from benchmark.loaders.amass import load_amass
from benchmark.core.rotations import axis_angle_to_matrix


def write_amass(path, T=40, width=156, rate_key="mocap_framerate", rate=120.0, gender="female", seed=0, **extra):
    rng = np.random.default_rng(seed)
    poses = 0.3 * rng.standard_normal((T, width))
    trans = rng.standard_normal((T, 3))
    arrays = dict(poses=poses, trans=trans, betas=rng.standard_normal(16), gender=gender, **{rate_key: np.array(rate)})
    arrays.update(extra)
    np.savez(path, **arrays)
    return poses, trans


@pytest.mark.parametrize(
    "width, rate_key, gender, body",
    [
        (156, "mocap_framerate", "female", "smplh"),
        (156, "mocap_framerate", np.array(b"male"), "smplh"),
        (165, "mocap_frame_rate", np.array("neutral"), "smplx"),
        (165, "mocap_frame_rate", np.array(b"female"), "smplx"),
    ],
)
def test_loads_smplh_and_smplx_spellings(tmp_path, width, rate_key, gender, body):
    p = tmp_path / "seq_poses.npz"
    poses, trans = write_amass(p, width=width, rate_key=rate_key, gender=gender)
    m = load_amass(p)
    assert m.num_frames == 40 and abs(m.fps - 120.0) < 1e-9
    assert m.body == body and m.shape.shape == (16,)
    expected_gender = gender if isinstance(gender, str) else np.asarray(gender).item()
    if isinstance(expected_gender, bytes):
        expected_gender = expected_gender.decode()
    assert m.meta["gender"] == expected_gender
    # body joints (1..21) untouched: columns 3:66
    np.testing.assert_allclose(m.poses[:, 1:].numpy(), poses[:, 3:66].reshape(40, 21, 3), atol=1e-6)
    # root: R_x(-90) @ R_root ; translation R @ trans (no rest pelvis given)
    Rx = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=float)
    R_root = axis_angle_to_matrix(torch.from_numpy(poses[:, :3])).numpy()
    np.testing.assert_allclose(axis_angle_to_matrix(m.poses[:, 0].double()).numpy(), Rx @ R_root, atol=1e-5)
    np.testing.assert_allclose(m.trans.numpy(), trans @ Rx.T, atol=1e-6)
    assert m.meta["pelvis_offset_compensated"] is False


def test_z_up_body_ends_up_y_up(tmp_path):
    # As in AMASS: a y-up body model (head above the pelvis at rest) made to stand along +z by
    # its root rotation Rx(+90 deg). After loading, the body must stand along +y.
    T = 3
    rest = torch.zeros(22, 3, dtype=torch.float64)
    for j, y in [(0, -0.2), (3, -0.1), (6, 0.05), (9, 0.1), (12, 0.3), (15, 0.45)]:
        rest[j] = torch.tensor([0.0, y, 0.02])
    poses = np.zeros((T, 156))
    poses[:, 0] = math.pi / 2
    poses[:, 3:66] = 0.05  # some body pose: must not matter for the up direction test below
    trans = np.tile([1.0, 2.0, 0.9], (T, 1))
    p = tmp_path / "stand_poses.npz"
    np.savez(p, poses=poses, trans=trans, betas=np.zeros(16), gender="male", mocap_framerate=np.array(60.0))

    def fk(aa, tr):
        _, j = forward_kinematics(axis_angle_to_matrix(aa.double()), rest)
        return j + tr.double()[:, None]

    file_joints = fk(torch.from_numpy(poses[:, :66]).reshape(T, 22, 3) * torch.tensor([1.0] + [0.0] * 21)[:, None],
                     torch.from_numpy(trans))
    up_file = file_joints[0, 15] - file_joints[0, 0]
    np.testing.assert_allclose((up_file / up_file.norm()).numpy(), [0, 0, 1], atol=1e-9)

    J0 = rest[0]
    m = load_amass(p, rest_pelvis=J0.numpy())
    root_only = m.poses.clone()
    root_only[:, 1:] = 0
    joints = fk(root_only, m.trans)
    up = joints[0, 15] - joints[0, 0]
    np.testing.assert_allclose((up / up.norm()).numpy(), [0, 1, 0], atol=1e-6)
    # exact pelvis: the file's pelvis J0 + trans, rotated into y-up by R = Rx(-90)
    Rx = torch.tensor([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=torch.float64)
    np.testing.assert_allclose(joints[0, 0].numpy(), (Rx @ file_joints[0, 0]).numpy(), atol=1e-6)
    # the whole posed body is the file's body rotated by R
    np.testing.assert_allclose(fk(m.poses, m.trans).numpy(),
                               (fk(torch.from_numpy(poses[:, :66]).reshape(T, 22, 3), torch.from_numpy(trans)) @ Rx.T).numpy(),
                               atol=1e-5)
    assert m.meta["pelvis_offset_compensated"] is True


def test_frame_rate_fix_from_yaml(tmp_path):
    d = tmp_path / "BMLhandball" / "S01_Expert"
    d.mkdir(parents=True)
    p = d / "Trial_upper_left_017_poses.npz"
    write_amass(p, T=25, rate=50.0)
    m = load_amass(p)
    assert abs(m.fps - 240.0) < 1e-9
    fix = m.meta["frame_rate_correction"]
    assert fix["stored"] == 50.0 and fix["corrected"] == 240.0 and fix["table_version"] == 1
    assert fix["rule"] == "*BMLhandball*"
    # a custom table, and switching corrections off
    table = tmp_path / "rates.yaml"
    table.write_text("version: 7\ncorrections:\n  - match: '*/S01_*/*'\n    fps: 100\n    reason: test\n")
    m = load_amass(p, frame_rate_table=table)
    assert abs(m.fps - 100.0) < 1e-9 and m.meta["frame_rate_correction"]["table_version"] == 7
    m = load_amass(p, frame_rate_table=None)
    assert abs(m.fps - 50.0) < 1e-9 and "frame_rate_correction" not in m.meta


def test_named_59fps_sequence(tmp_path):
    p = tmp_path / "20160930_50032_poses.npz"
    write_amass(p, T=10, rate=120.0)
    assert abs(load_amass(p).fps - 59.0) < 1e-9


def test_resample_by_exact_ratio(tmp_path):
    p = tmp_path / "seq_poses.npz"
    poses, trans = write_amass(p, T=121, rate=120.0)
    m = load_amass(p, fps=30.0)
    assert m.num_frames == 31
    # every 4th source frame coincides with an output frame (t = k/30 = 4k/120)
    Rx = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=float)
    np.testing.assert_allclose(m.trans.numpy(), (trans @ Rx.T)[::4], atol=1e-5)
    # 50 -> 30: t = 1/30 is 2/3 of the way between source frames 1 and 2
    p2 = tmp_path / "seq50_poses.npz"
    _, trans50 = write_amass(p2, T=51, rate=50.0)
    m = load_amass(p2, fps=30.0)
    tr = trans50 @ Rx.T
    np.testing.assert_allclose(m.trans[1].numpy(), tr[1] + (tr[2] - tr[1]) * 2 / 3, atol=1e-5)


def test_shape_file_and_missing_keys(tmp_path):
    p = tmp_path / "shape.npz"
    np.savez(p, betas=np.zeros(16), gender="male")
    with pytest.raises(ValueError, match="shape file"):
        load_amass(p)
    p = tmp_path / "seq_poses.npz"
    np.savez(p, poses=np.zeros((5, 156)), trans=np.zeros((5, 3)))
    with pytest.raises(KeyError, match=r"seq_poses.npz: missing key 'mocap_framerate'"):
        load_amass(p)
    np.savez(p, poses=np.zeros((5, 156)), mocap_framerate=np.array(120.0))
    with pytest.raises(KeyError, match=r"seq_poses.npz: missing key 'trans'"):
        load_amass(p)
    np.savez(p, poses=np.zeros((5, 100)), trans=np.zeros((5, 3)), mocap_framerate=np.array(120.0))
    with pytest.raises(ValueError, match=r"key 'poses' has shape \(5, 100\)"):
        load_amass(p)


def test_a_data_folder_skips_amass_shape_files(tmp_path):
    """An AMASS subject folder holds shape.npz (betas, gender) beside its sequences: --data reads
    the sequences and leaves the shape file out; a folder of shape files only is refused."""
    from benchmark.data.table_data import load_motions

    sub = tmp_path / "CMU" / "01"
    sub.mkdir(parents=True)
    write_amass(sub / "01_01_poses.npz")
    np.savez(sub / "shape.npz", betas=np.zeros(16), gender="male")
    np.savez(sub / "01_02_shape.npz", betas=np.zeros(16), gender="male")
    motions = load_motions(str(tmp_path / "CMU"), 0.1)
    assert list(motions) == ["01/01_01_poses.npz"]
    (sub / "01_01_poses.npz").unlink()
    with pytest.raises(FileNotFoundError, match=r"only AMASS shape files .*shape\.npz"):
        load_motions(str(tmp_path / "CMU"), 0.1)


@pytest.mark.parametrize("field, value, message", [
    ("mocap_framerate", np.array([]), r"key 'mocap_framerate' must hold one number"),
    ("mocap_framerate", np.array("sixty"), r"key 'mocap_framerate' must hold one number"),
    ("betas", np.array("none"), r"key 'betas' must hold the body's shape coefficients"),
])
def test_a_malformed_field_is_named(tmp_path, field, value, message):
    p = tmp_path / "seq_poses.npz"
    write_amass(p, **{field: value})
    with pytest.raises(ValueError, match=rf"seq_poses\.npz: {message}"):
        load_amass(p)
