"""SMPL-family model files: reading (.npz, .pkl with chumpy/sparse, Python-2 pickles), skinning
against a plain numpy reference, landmark selection, and model-file path resolution."""

from __future__ import annotations

import importlib.util
import pickle
import struct
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import roma
import scipy.sparse
import torch

from benchmark.body.landmarks import ray_exit_vertices, select_landmarks
from benchmark.body.resolve import ENV_VAR, candidate_files, load_body, resolve_body_model_file
from benchmark.body.smpl import SMPLBody
from benchmark.body.smpl_files import MissingKeyError, read_body_model_file
from benchmark.core.skeleton import JOINT_INDEX, JOINT_NAMES, LANDMARK_NAMES, MIRROR, PARENTS

# ----------------------------------------------------------------------------------------------
# Synthetic model files

# A T-pose skeleton in metres (y up, facing +z, left at +x), SMPL joint order.
BODY_JOINTS = {
    "pelvis": (0.0, 0.90, 0.0), "left_hip": (0.08, 0.82, 0.0), "right_hip": (-0.08, 0.82, 0.0),
    "spine1": (0.0, 1.00, 0.0), "left_knee": (0.09, 0.45, 0.0), "right_knee": (-0.09, 0.45, 0.0),
    "spine2": (0.0, 1.13, 0.0), "left_ankle": (0.09, 0.08, 0.0), "right_ankle": (-0.09, 0.08, 0.0),
    "spine3": (0.0, 1.20, 0.0), "left_foot": (0.10, 0.02, 0.10), "right_foot": (-0.10, 0.02, 0.10),
    "neck": (0.0, 1.45, 0.0), "left_collar": (0.07, 1.38, 0.0), "right_collar": (-0.07, 1.38, 0.0),
    "head": (0.0, 1.58, 0.0), "left_shoulder": (0.17, 1.40, 0.0), "right_shoulder": (-0.17, 1.40, 0.0),
    "left_elbow": (0.42, 1.40, 0.0), "right_elbow": (-0.42, 1.40, 0.0),
    "left_wrist": (0.67, 1.40, 0.0), "right_wrist": (-0.67, 1.40, 0.0),
}
SKELETON = np.array([BODY_JOINTS[n] for n in JOINT_NAMES])


def smpl_parents(model_type: str) -> list[int]:
    """The kinematic tree of SMPL (24), SMPL-H (52) or SMPL-X (55)."""
    if model_type == "smpl":
        return list(PARENTS) + [20, 21]
    hands = []
    for wrist, first in ((20, 22), (21, 37)) if model_type == "smplh" else ((20, 25), (21, 40)):
        for finger in range(5):
            base = first + 3 * finger
            hands += [wrist, base, base + 1]
    extra = [15, 15, 15] if model_type == "smplx" else []  # jaw, left eye, right eye
    return list(PARENTS) + extra + hands


def extra_joint_positions(parents: list[int], rng) -> np.ndarray:
    pos = list(SKELETON)
    for j in range(22, len(parents)):
        pos.append(pos[parents[j]] + rng.normal(0, 0.03, 3) + (0.04 * np.sign(pos[parents[j]][0]), 0, 0))
    return np.array(pos)


def make_model(model_type="smpl", num_betas=12, per_joint=10, seed=0, shapedirs_extra=0) -> dict:
    """A small random model in the SMPL file format, with vertices clustered around a body skeleton."""
    rng = np.random.default_rng(seed)
    parents = smpl_parents(model_type)
    J = len(parents)
    joints = extra_joint_positions(parents, rng)
    owner = np.repeat(np.arange(J), per_joint)
    V = owner.size
    v_template = joints[owner] + rng.normal(0, 0.04, (V, 3))
    regressor = np.zeros((J, V))
    for j in range(J):
        w = rng.uniform(0.5, 1.0, per_joint)
        regressor[j, owner == j] = w / w.sum()
    weights = rng.uniform(0, 1, (V, J)) ** 4
    weights[np.arange(V), owner] += 2.0
    weights /= weights.sum(1, keepdims=True)
    kintree = np.array([[2**32 - 1] + parents[1:], list(range(J))], dtype=np.int64)
    return {
        "v_template": v_template,
        "shapedirs": rng.normal(0, 0.01, (V, 3, num_betas + shapedirs_extra)),
        "posedirs": rng.normal(0, 0.01, (V, 3, 9 * (J - 1))),
        "J_regressor": regressor,
        "weights": weights,
        "kintree_table": kintree.astype(np.uint32),
        "f": rng.integers(0, V, (60, 3)).astype(np.uint32),
        "bs_style": "lbs",  # an extra key, ignored
    }


def write_npz(path: Path, model: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **{k: v for k, v in model.items() if k != "bs_style"})
    return path


# Fake chumpy classes, registered as chumpy.ch.Ch and chumpy.reordering.Select only while pickling.
class Ch:
    def __init__(self, x):
        self.x = np.asarray(x)
        self._dirty_vars = set()
        self._itr = None

    def __getstate__(self):  # chumpy drops its weak dictionaries and pickles the rest of __dict__
        return dict(self.__dict__)


class Select(Ch):
    def __init__(self, a, idxs, preferred_shape):
        self.a, self.idxs, self.preferred_shape = a, np.asarray(idxs), preferred_shape
        self._dirty_vars = set()


class Opaque(Ch):
    """A chumpy expression node without an array: the reader must refuse it clearly."""

    def __init__(self):
        self.a, self.b = 1, 2


def _register_fake_chumpy(monkeypatch):
    modules = {name: types.ModuleType(name) for name in ("chumpy", "chumpy.ch", "chumpy.reordering", "chumpy.ch_ops")}
    for cls, module in ((Ch, "chumpy.ch"), (Select, "chumpy.reordering"), (Opaque, "chumpy.ch_ops")):
        cls.__module__, cls.__qualname__ = module, cls.__name__
        setattr(modules[module], cls.__name__, cls)
    for name, module in modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    return list(modules)


def _forget_fake_chumpy(monkeypatch, names):
    for name in names:
        monkeypatch.delitem(sys.modules, name)
    assert "chumpy" not in sys.modules and importlib.util.find_spec("chumpy") is None


def write_chumpy_pkl(path: Path, model: dict, monkeypatch, protocol=2) -> Path:
    """The model as an original-SMPL-style pickle: chumpy arrays and a sparse J_regressor."""
    names = _register_fake_chumpy(monkeypatch)
    data = dict(model)
    data["v_template"] = Ch(model["v_template"])
    posedirs = model["posedirs"]
    flat = posedirs.ravel()
    perm = np.random.default_rng(1).permutation(flat.size)
    source = np.empty_like(flat)
    source[perm] = flat  # Select(source, perm) == posedirs
    data["posedirs"] = Select(Ch(source), perm, posedirs.shape)
    data["shapedirs"] = Ch(model["shapedirs"])
    data["J_regressor"] = scipy.sparse.csc_matrix(model["J_regressor"])
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        pickle.dump(data, fh, protocol=protocol)
    _forget_fake_chumpy(monkeypatch, names)
    return path


class Python2Pickler(pickle._Pickler):
    """Writes what Python 2 wrote: byte strings as STRING opcodes and numpy.core module paths."""

    dispatch = dict(pickle._Pickler.dispatch)

    def save_py2_str(self, obj):
        n = len(obj)
        head = pickle.SHORT_BINSTRING + bytes([n]) if n < 256 else pickle.BINSTRING + struct.pack("<i", n)
        self.write(head + obj)
        self.memoize(obj)

    dispatch[bytes] = save_py2_str

    def save_global(self, obj, name=None):
        module = obj.__module__.replace("numpy._core", "numpy.core")
        self.write(pickle.GLOBAL + f"{module}\n{name or obj.__qualname__}\n".encode())
        self.memoize(obj)


def write_py2_pkl(path: Path, model: dict) -> Path:
    data = {k.encode(): (v.encode() if isinstance(v, str) else v) for k, v in model.items()}
    data[b"J_regressor"] = scipy.sparse.csc_matrix(model["J_regressor"])
    with open(path, "wb") as fh:
        Python2Pickler(fh, protocol=2).dump(data)
    return path


# ----------------------------------------------------------------------------------------------
# Plain reference: per-joint loops, full kinematic tree, every joint of the file


def rodrigues(aa: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(aa)
    if angle < 1e-12:
        return np.eye(3)
    k = aa / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def reference_smpl(model: dict, betas: np.ndarray, body_aa: np.ndarray, trans: np.ndarray):
    """One frame: betas (S,), body_aa (22, 3), trans (3,) -> vertices (V, 3), joints (22, 3)."""
    parents = [int(p) for p in model["kintree_table"][0].astype(np.int64)]
    parents[0] = -1
    J = len(parents)
    S = betas.shape[0]
    v_shaped = model["v_template"] + model["shapedirs"][:, :, :S] @ betas
    rest = model["J_regressor"] @ v_shaped
    R = [rodrigues(body_aa[j]) if j < 22 else np.eye(3) for j in range(J)]
    feature = np.concatenate([(R[j] - np.eye(3)).ravel() for j in range(1, J)])
    v_posed = v_shaped + model["posedirs"] @ feature
    G = [None] * J
    for j in range(J):
        local = np.eye(4)
        local[:3, :3] = R[j]
        local[:3, 3] = rest[j] if parents[j] < 0 else rest[j] - rest[parents[j]]
        G[j] = local if parents[j] < 0 else G[parents[j]] @ local
    A = np.stack(G).copy()
    for j in range(J):
        A[j, :3, 3] = G[j][:3, 3] - G[j][:3, :3] @ rest[j]
    per_vertex = np.einsum("vj,jab->vab", model["weights"], A)
    verts = np.einsum("vab,vb->va", per_vertex[:, :3, :3], v_posed) + per_vertex[:, :3, 3]
    joints = np.stack([G[j][:3, 3] for j in range(22)])
    return verts + trans, joints + trans


def check_against_reference(body: SMPLBody, model: dict, seed: int = 0, B: int = 2, T: int = 3):
    rng = np.random.default_rng(seed)
    S = body.shape_dim
    betas = rng.normal(0, 1.5, (B, S))
    aa = rng.normal(0, 0.6, (B, T, 22, 3))
    trans = rng.normal(0, 1.0, (B, T, 3))
    assert body.v_template.dtype == torch.float64, "build the body with dtype=torch.float64 for this check"
    rot = roma.rotvec_to_rotmat(torch.from_numpy(aa))
    out = body(rot, torch.from_numpy(trans), torch.from_numpy(betas))
    assert out.vertices.shape == (B, T, model["v_template"].shape[0], 3)
    assert out.joints.shape == (B, T, 22, 3)
    for b in range(B):
        for t in range(T):
            v_ref, j_ref = reference_smpl(model, betas[b], aa[b, t], trans[b, t])
            np.testing.assert_allclose(out.vertices[b, t].numpy(), v_ref, atol=1e-10)
            np.testing.assert_allclose(out.joints[b, t].numpy(), j_ref, atol=1e-10)


# ----------------------------------------------------------------------------------------------
# Reading files and skinning


def test_npz_smpl_matches_reference(tmp_path):
    model = make_model("smpl")
    data = read_body_model_file(write_npz(tmp_path / "SMPL_NEUTRAL.npz", model))
    assert data.model_type == "smpl" and data.num_joints == 24 and data.num_betas == 12
    assert data.parents[0] == -1 and data.parents.tolist()[1:] == model["kintree_table"][0, 1:].tolist()
    body = SMPLBody(data, num_betas=10, dtype=torch.float64)
    assert body.shape_dim == 10 and body.num_vertices == model["v_template"].shape[0]
    assert body.faces.dtype == torch.long and body.faces.shape == (60, 3)
    assert torch.equal(body.faces, torch.from_numpy(model["f"].astype(np.int64)))
    assert body.landmark_indices.dtype == torch.long and body.landmark_indices.shape == (16,)
    assert torch.equal(body.default_shape(3), torch.zeros(3, 10, dtype=torch.float64))
    assert SMPLBody(data).v_template.dtype == torch.float32
    check_against_reference(body, model)


def test_zero_pose_is_the_shaped_rest_mesh(tmp_path):
    model = make_model("smpl", seed=3)
    body = SMPLBody.from_file(write_npz(tmp_path / "m.npz", model), num_betas=4, dtype=torch.float64)
    betas = torch.randn(2, 4, dtype=torch.float64)
    rest = body.prepare(betas)
    eye = torch.eye(3, dtype=torch.float64).expand(2, 1, 22, 3, 3)
    out = body.skin(rest, eye, torch.zeros(2, 1, 3, dtype=torch.float64))
    v_shaped = model["v_template"][..., None] + model["shapedirs"][:, :, :4] @ betas.numpy().T  # (V, 3, B)
    np.testing.assert_allclose(out.vertices[:, 0].numpy(), v_shaped.transpose(2, 0, 1), atol=1e-12)
    np.testing.assert_allclose(out.joints[:, 0].numpy(), rest.joints.numpy(), atol=1e-12)
    all_joints = np.einsum("jv,vcb->bjc", model["J_regressor"], v_shaped)
    np.testing.assert_allclose(rest.extra["all_joints"].numpy(), all_joints, atol=1e-12)
    np.testing.assert_allclose(body.rest_joints(betas).numpy(), all_joints[:, :22], atol=1e-12)


def test_shape_is_differentiable(tmp_path):
    body = SMPLBody.from_file(write_npz(tmp_path / "m.npz", make_model("smpl")))
    betas = torch.zeros(1, 10, requires_grad=True)
    rot = roma.rotvec_to_rotmat(torch.randn(1, 2, 22, 3) * 0.3)
    body(rot, shape=betas).vertices.square().sum().backward()
    assert betas.grad is not None and betas.grad.abs().sum() > 0


@pytest.mark.parametrize("protocol", [0, 2])  # 0: copyreg._reconstructor objects; 2: NEWOBJ
def test_pkl_with_chumpy_and_sparse_without_chumpy(tmp_path, monkeypatch, protocol):
    model = make_model("smpl", seed=1)
    pkl = write_chumpy_pkl(tmp_path / "SMPL_NEUTRAL.pkl", model, monkeypatch, protocol=protocol)
    from_pkl = read_body_model_file(pkl)
    from_npz = read_body_model_file(write_npz(tmp_path / "SMPL_NEUTRAL.npz", model))
    for key in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "parents", "faces"):
        np.testing.assert_array_equal(getattr(from_pkl, key), getattr(from_npz, key), err_msg=key)
    assert "chumpy" not in sys.modules
    check_against_reference(SMPLBody(from_pkl, num_betas=12, dtype=torch.float64), model, seed=5)


def test_python2_pickle_needs_latin1(tmp_path):
    model = make_model("smpl", seed=2)
    pkl = write_py2_pkl(tmp_path / "basicModel_neutral.pkl", model)
    assert b"numpy.core.multiarray" in pkl.read_bytes()
    with pytest.raises(UnicodeDecodeError):  # what a plain pickle.load does with such a file
        with open(pkl, "rb") as fh:
            pickle.load(fh)
    data = read_body_model_file(pkl)
    np.testing.assert_array_equal(data.v_template, model["v_template"])
    np.testing.assert_array_equal(data.J_regressor, model["J_regressor"])
    np.testing.assert_array_equal(data.posedirs, model["posedirs"])


def test_unreadable_chumpy_node_is_refused_clearly(tmp_path, monkeypatch):
    model = make_model("smpl")
    names = _register_fake_chumpy(monkeypatch)
    model["weights"] = Opaque()
    path = tmp_path / "bad.pkl"
    path.write_bytes(pickle.dumps(model, protocol=2))
    _forget_fake_chumpy(monkeypatch, names)
    with pytest.raises(ValueError, match=r"bad\.pkl: key 'weights'.*chumpy\.ch_ops\.Opaque.*'x'"):
        read_body_model_file(path)


def test_missing_key_names_file_and_key(tmp_path):
    model = make_model("smpl")
    del model["weights"]
    path = write_npz(tmp_path / "nokey.npz", model)
    with pytest.raises(MissingKeyError) as err:
        read_body_model_file(path)
    assert str(path) in str(err.value) and "'weights'" in str(err.value)


def test_bad_shapes_and_betas_are_refused(tmp_path):
    model = make_model("smpl")
    model["posedirs"] = model["posedirs"][:, :, :-9]
    with pytest.raises(ValueError, match=r"key 'posedirs' has shape .*expected"):
        read_body_model_file(write_npz(tmp_path / "a.npz", model))
    path = write_npz(tmp_path / "b.npz", make_model("smpl"))
    with pytest.raises(ValueError, match="num_betas=13 but the file holds 12"):
        SMPLBody.from_file(path, num_betas=13)


def test_smplh_amass_layout_matches_full_tree_reference(tmp_path, monkeypatch):
    """52 joints with finger chains: the folded 22-joint skinning equals the full-tree reference."""
    model = make_model("smplh", num_betas=16, per_joint=4, seed=4)
    write_npz(tmp_path / "root" / "smplh" / "neutral" / "model.npz", model)
    monkeypatch.delenv(ENV_VAR, raising=False)
    body = load_body("smplh", path=tmp_path / "root", num_betas=16, dtype=torch.float64)
    assert body.model_type == "smplh" and body.num_file_joints == 52 and body.shape_dim == 16
    check_against_reference(body, model, seed=7, B=1, T=2)


def test_smplx_file_shape_space_and_reference(tmp_path):
    model = make_model("smplx", num_betas=10, per_joint=3, seed=6, shapedirs_extra=10)  # 10 shape + 10 expr
    data = read_body_model_file(write_npz(tmp_path / "SMPLX_NEUTRAL.npz", model))
    assert data.model_type == "smplx" and data.num_joints == 55 and data.num_betas == 10
    check_against_reference(SMPLBody(data, dtype=torch.float64), model, seed=8, B=1, T=2)


def test_load_body_refuses_another_model_type(tmp_path):
    write_npz(tmp_path / "smplh" / "SMPLH_MALE.npz", make_model("smpl"))
    with pytest.raises(ValueError, match="asked for a 'smplh' model but the file holds 'smpl'"):
        load_body("smplh", gender="male", path=tmp_path)


# ----------------------------------------------------------------------------------------------
# Landmarks


def primitive_body():
    """A T-pose body of rings, a head sphere and feet; returns vertices, joints, expected landmarks."""
    verts, named = [], {}

    def add(p, name=None):
        if name:
            named[name] = len(verts)
        verts.append(np.asarray(p, dtype=float))

    def ring(center, u, w, radius, count=8, names=None):
        for k in range(count):
            a = 2 * np.pi * k / count
            add(center + radius * (np.cos(a) * u + np.sin(a) * w), (names or {}).get(k))

    X, Y, Z = np.eye(3)
    j = {n: SKELETON[i] for n, i in JOINT_INDEX.items()}
    for y in np.linspace(0.85, 1.40, 12):  # torso: elliptic rings, x semi-axis 0.14, z semi-axis 0.10
        for k in range(16):
            a = 2 * np.pi * k / 16
            name = None
            if np.isclose(y, j["pelvis"][1]) and k in (0, 8):
                name = "pelvis_front" if k == 0 else "pelvis_back"
            add((0.14 * np.sin(a), y, 0.10 * np.cos(a)), name)
    sternum_y = (j["spine3"][1] + j["neck"][1]) / 2
    add((0.0, sternum_y, 0.10), "sternum")
    for side, s in (("left", 1.0), ("right", -1.0)):
        for a, b in (("shoulder", "elbow"), ("elbow", "wrist")):  # arm rings in the y-z plane: k=0 +y, k=2 +z
            for t in np.linspace(0, 1, 6)[(a == "elbow"):]:
                c = (1 - t) * j[f"{side}_{a}"] + t * j[f"{side}_{b}"]
                names = {}
                if t == 0:
                    names = {0: f"{side}_shoulder"}  # top of the ring at the shoulder joint
                elif t == 1:
                    names = {0: f"{side}_elbow"} if b == "elbow" else {2: f"{side}_wrist"}  # top / front
                ring(c, Y, Z, 0.05, names=names)
        for a, b in (("hip", "knee"), ("knee", "ankle")):  # leg rings in the x-z plane: k=0 +x, k=4 -x
            for t in np.linspace(0, 1, 6)[(a == "knee"):]:
                c = (1 - t) * j[f"{side}_{a}"] + t * j[f"{side}_{b}"]
                names = {(0 if s > 0 else 4): f"{side}_{b}"} if t == 1 else {}
                ring(c, X, Z, 0.05, names=names)
        ax = j[f"{side}_ankle"][0]
        for dx in (-0.04, 0.04):  # foot box and a toe tip
            for y in (0.0, 0.04):
                for z in (-0.05, 0.18):
                    add((ax + dx, y, z))
        add((ax, 0.02, 0.22), f"{side}_toe")
    for k in range(40):  # head: sphere of radius 0.1 around the head joint, top point included
        phi, theta = np.pi * (k // 8 + 1) / 6, 2 * np.pi * (k % 8) / 8
        add(j["head"] + 0.1 * np.array([np.sin(phi) * np.cos(theta), np.cos(phi), np.sin(phi) * np.sin(theta)]))
    add(j["head"] + (0, 0.1, 0), "head")
    return torch.tensor(np.stack(verts)), torch.tensor(SKELETON), named


def test_select_landmarks_on_a_primitive_body():
    verts, joints, named = primitive_body()
    got = select_landmarks(verts, joints)
    assert got.dtype == torch.long and got.shape == (16,)
    expected = [named[n] for n in LANDMARK_NAMES]
    assert got.tolist() == expected, {n: (g, e) for n, g, e in zip(LANDMARK_NAMES, got.tolist(), expected) if g != e}


def test_ray_exit_prefers_the_top_of_a_head_whose_joint_sits_low():
    """Joint 0.05 m above the bottom of an ellipsoid head (0.08 m wide, 0.20 m tall): the upward ray
    must leave through the top (0.15 m away), not the temple (about 0.10 m away at 45 degrees)."""
    phi = torch.linspace(0, np.pi, 25, dtype=torch.float64)[:, None]
    theta = torch.linspace(0, 2 * np.pi, 17, dtype=torch.float64)[None, :-1]
    pts = torch.stack([0.08 * phi.sin() * theta.cos(), 0.10 * phi.cos() + 0 * theta,
                       0.08 * phi.sin() * theta.sin()], -1).reshape(-1, 3)
    origin = torch.tensor([[0.0, -0.05, 0.0]], dtype=torch.float64)
    up = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    top = int(pts[:, 1].argmax())
    assert ray_exit_vertices(pts, origin, up).tolist() == [top]


def test_select_landmarks_is_mirror_symmetric_on_an_irregular_mesh():
    rng = np.random.default_rng(0)
    verts, joints, _ = primitive_body()
    verts = verts + torch.from_numpy(rng.normal(0, 0.004, verts.shape))  # asymmetric, no ties
    flip = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    got = select_landmarks(verts, joints)
    mirrored = select_landmarks(verts * flip, (joints * flip)[list(MIRROR)])
    swap = [LANDMARK_NAMES.index(n.replace("left_", "@").replace("right_", "left_").replace("@", "right_"))
            for n in LANDMARK_NAMES]
    assert mirrored.tolist() == got[swap].tolist()


def test_select_landmarks_rejects_bad_input():
    with pytest.raises(ValueError, match=r"joints must be \(22, 3\)"):
        select_landmarks(torch.zeros(10, 3), torch.zeros(24, 3))
    with pytest.raises(ValueError, match="no mesh vertex within 85 degrees"):
        select_landmarks(torch.zeros(10, 3) + torch.tensor([0.0, -5.0, 0.0]), torch.tensor(SKELETON))


# ----------------------------------------------------------------------------------------------
# Path resolution


@pytest.fixture
def roots(tmp_path, monkeypatch):
    """Three roots (flag, env, user dir), with the environment pointing at the last two."""
    flag, env, data_home = tmp_path / "flag", tmp_path / "env", tmp_path / "xdg"
    user = data_home / "motion-benchmark" / "body_models"
    for root in (flag, env, user):
        root.mkdir(parents=True)
    monkeypatch.setenv(ENV_VAR, str(env))
    monkeypatch.setenv("XDG_DATA_HOME", str(data_home))
    return flag, env, user


def _touch(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")
    return path


def test_resolution_order_flag_env_user(roots):
    flag, env, user = roots
    u = _touch(user / "smpl" / "SMPL_NEUTRAL.pkl")
    assert resolve_body_model_file("smpl") == u
    e = _touch(env / "smpl" / "SMPL_NEUTRAL.npz")
    assert resolve_body_model_file("smpl") == e
    f = _touch(flag / "smpl" / "SMPL_NEUTRAL.pkl")
    assert resolve_body_model_file("smpl", path=flag) == f
    assert resolve_body_model_file("smpl", path=f) == f  # a file given directly
    folder_itself = _touch(flag / "only_smpl" / "SMPL_NEUTRAL.npz")
    assert resolve_body_model_file("smpl", path=flag / "only_smpl") == folder_itself
    assert resolve_body_model_file("smplh", gender="female", path=_touch(flag / "smplh/female/model.npz").parents[2]) \
        == flag / "smplh" / "female" / "model.npz"


def test_pkl_preferred_for_smpl_npz_for_smplx(roots):
    _, env, _ = roots
    for ext in (".pkl", ".npz"):
        _touch(env / "smpl" / f"SMPL_MALE{ext}")
        _touch(env / "smplx" / f"SMPLX_MALE{ext}")
    assert resolve_body_model_file("smpl", "male").suffix == ".pkl"
    assert resolve_body_model_file("smplx", "male").suffix == ".npz"


def test_missing_file_error_lists_every_path_tried(roots):
    flag, env, user = roots
    with pytest.raises(FileNotFoundError) as err:
        resolve_body_model_file("smplh", gender="male")
    message = str(err.value)
    for root in (env, user):
        for candidate in candidate_files(root, "smplh", "male"):
            assert str(candidate) in message
    assert "smplh/neutral/model.npz" in message and "SMPL_NEUTRAL.pkl" in message and ENV_VAR in message
    # An explicit path is authoritative: its candidates are listed, the other roots are not searched.
    _touch(env / "smplh" / "SMPLH_MALE.npz")
    with pytest.raises(FileNotFoundError) as err:
        resolve_body_model_file("smplh", gender="male", path=flag)
    assert all(str(c) in str(err.value) for c in candidate_files(flag, "smplh", "male"))
    assert str(env / "smplh") not in str(err.value)
    with pytest.raises(FileNotFoundError, match="typo.pkl"):
        resolve_body_model_file("smpl", path=flag / "typo.pkl")


def test_unknown_kind_or_gender():
    with pytest.raises(ValueError, match="unknown body-model kind"):
        resolve_body_model_file("mano")
    with pytest.raises(ValueError, match="unknown gender"):
        resolve_body_model_file("smpl", gender="other")


def test_a_model_files_gender_names_the_body_and_a_contradiction_is_refused(tmp_path, monkeypatch):
    """``smplh=.../male/model.npz`` is the male model, named so (it was called smplh-neutral); the
    same file asked for as ``:neutral`` is refused, naming the file and the fix."""
    from benchmark.body import get_body
    from benchmark.body.resolve import file_gender

    assert [file_gender(p) for p in ("r/smplh/male/model.npz", "SMPL_FEMALE.pkl", "SMPLX_NEUTRAL.npz", "x/model.npz")] \
        == ["male", "female", "neutral", None]
    male = write_npz(tmp_path / "root" / "smplh" / "male" / "model.npz", make_model("smplh", num_betas=16, per_joint=2))
    monkeypatch.delenv(ENV_VAR, raising=False)
    assert get_body(f"smplh={male}").name == "smplh-male"
    assert get_body(f"smplh={male}:male").name == "smplh-male"
    with pytest.raises(ValueError, match=r"male/model\.npz: its name says the male model, but the body asked for is "
                                         r"smplh:neutral; point to the neutral file, or drop ':neutral'"):
        get_body(f"smplh={male}:neutral")


def test_a_pkl_reads_where_numpy_has_no_numpy_core_module_yet(tmp_path, monkeypatch):
    """numpy 1.24-1.26 (allowed by the project) has ``numpy.core`` and no ``numpy._core``: an original
    SMPL ``.pkl`` naming numpy's classes still reads (it failed with "No module named 'numpy._core'")."""
    import importlib

    from benchmark.body import smpl_files

    model = make_model("smpl", num_betas=10, per_joint=2, seed=3)
    path = write_chumpy_pkl(tmp_path / "SMPL_NEUTRAL.pkl", model, monkeypatch)
    real = importlib.import_module

    def numpy_1(name, *args):
        if name.startswith("numpy._core"):
            raise ModuleNotFoundError(f"No module named {name!r}")
        if name.startswith("numpy.core"):
            return real("numpy._core" + name[len("numpy.core"):])
        return real(name, *args)

    monkeypatch.setattr(smpl_files.importlib, "import_module", numpy_1)
    data = read_body_model_file(path)
    assert data.model_type == "smpl" and np.allclose(data.v_template, model["v_template"])
