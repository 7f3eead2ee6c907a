"""The embedded default body: Anny (PyPI ``anny``) re-rigged to the SMPL 22-joint convention.

Why the ``cmu_mb`` rig: its 31 bones are the CMU motion-capture skeleton, which maps onto the
SMPL-22 joints one to one for every SMPL joint (Hips, LeftUpLeg, LeftLeg, LeftFoot, LeftToeBase,
LowerBack, Spine, Spine1, Neck, Head, LeftShoulder, LeftArm, LeftForeArm, LeftHand, ...), with only
a handful of extra bones (LHipJoint/RHipJoint, Neck1, thumb and two finger bones per hand) to fold
in. The ``anny``/``makehuman`` rigs have 160+ bones (a five-bone spine, face and finger bones) whose
spine joints do not line up with SMPL's three; ``game_engine``/``mixamo`` lack a separate toe or
collar chain in places. ``cmu_mb`` is the cleanest map.

Construction (all per shape, differentiable in the 6 phenotype parameters):

1. Anny's rest model for the shape (its rest mesh, bone heads and bone frames), rotated from Anny's
   z-up, facing -y frame into the project's world (y up, facing +z, left at +x).
2. A T-pose: legs straight down, arms horizontal along +x (left) and -x (right), hands continuing
   the arms, feet pointing forward (+z) with their pitch kept; spine, neck, head and collars keep
   Anny's upright rest. Each SMPL joint gets a rigid "T-posing" transform ``A_j`` (a minimal swing
   of its segment onto the target direction, composed down the chain), and the finer Anny bones
   ride rigidly with the SMPL joint they fold into, so their skinning weights simply add onto it.
3. The T-pose is lifted so that the lowest vertex (the soles) lies on y = 0.

Posing a frame: world-aligned local rotations -> FK over the T-pose joints gives per-joint
transforms ``M_j``; each vertex is skinned by ``sum_j w_j (M_j A_j)`` applied to Anny's rest
vertex. This is exactly Anny's own linear blend skinning for the equivalent Anny bone poses
(tested against ``anny.Anny.forward``), and the zero pose is the T-pose.
"""

from __future__ import annotations

import copy
import logging
import warnings
from pathlib import Path

import torch

from benchmark.body.base import BodyModel, BodyOutput, RestState
from benchmark.body.lbs import forward_kinematics, linear_blend_skinning, shared_rest_blend_skinning
from benchmark.core.rotations import rotation_between
from benchmark.core.skeleton import JOINT_INDEX, JOINT_NAMES, NUM_JOINTS, PARENTS

log = logging.getLogger(__name__)

PHENOTYPE_LABELS = ("gender", "age", "muscle", "weight", "height", "proportions")

# SMPL joint -> the cmu_mb bone whose head is the joint.
JOINT_BONES = {
    "pelvis": "Hips", "left_hip": "LeftUpLeg", "right_hip": "RightUpLeg", "spine1": "LowerBack",
    "left_knee": "LeftLeg", "right_knee": "RightLeg", "spine2": "Spine",
    "left_ankle": "LeftFoot", "right_ankle": "RightFoot", "spine3": "Spine1",
    "left_foot": "LeftToeBase", "right_foot": "RightToeBase", "neck": "Neck",
    "left_collar": "LeftShoulder", "right_collar": "RightShoulder", "head": "Head",
    "left_shoulder": "LeftArm", "right_shoulder": "RightArm", "left_elbow": "LeftForeArm",
    "right_elbow": "RightForeArm", "left_wrist": "LeftHand", "right_wrist": "RightHand",
}
# The finer bones and the SMPL joint their weights are summed onto.
FOLDED_BONES = {
    "LHipJoint": "pelvis", "RHipJoint": "pelvis", "Neck1": "neck",
    "LThumb": "left_wrist", "LeftFingerBase": "left_wrist", "LeftHandFinger1": "left_wrist",
    "RThumb": "right_wrist", "RightFingerBase": "right_wrist", "RightHandFinger1": "right_wrist",
}

# T-pose targets: joint -> (bone whose head ends the segment, or None for the bone's own tail,
# target world direction, keep_pitch). Joints not listed keep Anny's rest orientation.
_UP, _DOWN, _LEFT, _RIGHT, _FWD = (0, 1, 0), (0, -1, 0), (1, 0, 0), (-1, 0, 0), (0, 0, 1)
TPOSE_TARGETS = {
    "left_hip": ("LeftLeg", _DOWN, False), "right_hip": ("RightLeg", _DOWN, False),
    "left_knee": ("LeftFoot", _DOWN, False), "right_knee": ("RightFoot", _DOWN, False),
    "left_ankle": ("LeftToeBase", _FWD, True), "right_ankle": ("RightToeBase", _FWD, True),
    "left_foot": (None, _FWD, True), "right_foot": (None, _FWD, True),
    "left_shoulder": ("LeftForeArm", _LEFT, False), "right_shoulder": ("RightForeArm", _RIGHT, False),
    "left_elbow": ("LeftHand", _LEFT, False), "right_elbow": ("RightHand", _RIGHT, False),
    "left_wrist": ("LeftHandFinger1", _LEFT, False), "right_wrist": ("RightHandFinger1", _RIGHT, False),
}

# Anny's frame (z up, facing -y, left at +x) -> world (y up, facing +z, left at +x).
ANNY_TO_WORLD = ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0))


class AnnyCacheError(ValueError):
    """A file of Anny's model cache (``$ANNY_CACHE_DIR``, default ``~/.cache/anny``) that cannot be read."""


def _make_anny(rig: str = "cmu_mb"):
    import anny
    from safetensors import SafetensorError

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return anny.Anny(rig=rig)
        except SafetensorError as exc:  # anny reads its cache with safetensors; the error names no file
            raise _cache_error(exc) from exc


def damaged_cache_files(folder: str | Path) -> dict[Path, str]:
    """Every ``*.safetensors`` under ``folder`` that safetensors cannot open, with the reason."""
    from safetensors import safe_open

    bad = {}
    for file in sorted(Path(folder).rglob("*.safetensors")):
        try:
            with safe_open(str(file), framework="pt") as fh:
                fh.keys()
        except Exception as exc:  # noqa: BLE001 - any failure to open is "damaged"
            bad[file] = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return bad


def _cache_error(exc: BaseException) -> AnnyCacheError:
    """The file anny was reading when ``exc`` was raised (from its ``load_safetensors(path)`` frame),
    any other damaged file of the cache, and the fix."""
    from anny.paths import get_anny_cache_path

    cache = Path(get_anny_cache_path())
    bad = damaged_cache_files(cache)
    tb, reading = exc.__traceback__, None
    while tb is not None:
        if tb.tb_frame.f_code.co_name == "load_safetensors" and "path" in tb.tb_frame.f_locals:
            reading = Path(tb.tb_frame.f_locals["path"])
        tb = tb.tb_next
    if reading is not None:
        bad.setdefault(reading, str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__)
    if not bad:
        return AnnyCacheError(f"Anny's model cache {cache} cannot be read ({type(exc).__name__}: {exc}); fix: delete "
                              f"the folder (rm -r {cache}) and rerun: Anny rebuilds it (~1 min)")
    files = sorted(bad, key=lambda f: (f != reading, str(f)))
    what = "; ".join(f"{f} ({bad[f]})" for f in files)
    return AnnyCacheError(
        f"Anny's model cache file{'s' if len(files) > 1 else ''} {what}: damaged, probably cut short while Anny was "
        f"building it (an interrupted first run); fix: delete {'them' if len(files) > 1 else 'it'} "
        f"(rm {' '.join(str(f) for f in files)}) or the whole cache folder {cache}, then rerun: Anny rebuilds it "
        "(~1 min). If another process is building the cache right now, wait for it to finish instead"
    )


class AnnyBody(BodyModel):
    """The embedded default body (see module docstring). Shape = 6 phenotype parameters in [0, 1]."""

    name = "anny"
    shape_dim = len(PHENOTYPE_LABELS)

    def __init__(self, anny_model=None, dtype: torch.dtype = torch.float32):
        super().__init__()
        self._targets: dict = {}  # the T-pose's constant target directions, per (direction, dtype, device)
        model = anny_model if anny_model is not None else _make_anny()
        if tuple(model.phenotype_labels) != PHENOTYPE_LABELS:
            raise ValueError(f"unexpected Anny phenotype labels {model.phenotype_labels}, expected {PHENOTYPE_LABELS}")
        self.anny = model.to(dtype)
        for p in self.anny.parameters():
            p.requires_grad_(False)
        bones = list(model.bone_labels)
        self.bone_labels = tuple(bones)
        bone_index = {b: i for i, b in enumerate(bones)}
        missing = [b for b in list(JOINT_BONES.values()) + list(FOLDED_BONES) if b not in bone_index]
        if missing:
            raise ValueError(f"Anny rig {bones} lacks the bones {missing} that the SMPL-22 map needs")

        # Which SMPL joint each Anny bone's weights go to.
        bone_to_joint = torch.empty(len(bones), dtype=torch.long)
        for j, b in JOINT_BONES.items():
            bone_to_joint[bone_index[b]] = JOINT_INDEX[j]
        for b, j in FOLDED_BONES.items():
            bone_to_joint[bone_index[b]] = JOINT_INDEX[j]
        unmapped = set(bones) - set(JOINT_BONES.values()) - set(FOLDED_BONES)
        if unmapped:
            raise ValueError(f"Anny bones {sorted(unmapped)} have no SMPL-22 joint to fold into")
        self.register_buffer("bone_to_joint", bone_to_joint, persistent=False)
        self.register_buffer(
            "joint_bones", torch.tensor([bone_index[JOINT_BONES[n]] for n in JOINT_NAMES]), persistent=False
        )

        V = model.template_vertices.shape[0]
        idx = model.vertex_bone_indices.long()
        w = model.vertex_bone_weights.to(dtype)
        dense = torch.zeros(V, NUM_JOINTS, dtype=dtype)
        dense.scatter_add_(1, bone_to_joint[idx], w)
        self.register_buffer("weights", dense, persistent=False)
        self.register_buffer("faces", model.get_triangular_faces().long().clone(), persistent=False)
        self.register_buffer("anny_to_world", torch.tensor(ANNY_TO_WORLD, dtype=dtype), persistent=False)

        # T-pose target table as index tensors.
        targets = []
        for name in JOINT_NAMES:
            if name in TPOSE_TARGETS:
                end, direction, keep_pitch = TPOSE_TARGETS[name]
                targets.append((JOINT_INDEX[name], -1 if end is None else bone_index[end], direction, keep_pitch))
        self._tpose_targets = targets

        with torch.no_grad():
            rest = self.prepare(self.default_shape(1))
            from benchmark.body.landmarks import select_landmarks

            tpose = self.skin(rest, torch.eye(3, dtype=dtype).expand(1, 1, NUM_JOINTS, 3, 3),
                              torch.zeros(1, 1, 3, dtype=dtype))
            landmarks = select_landmarks(tpose.vertices[0, 0], tpose.joints[0, 0])
        self.register_buffer("landmark_indices", landmarks.long(), persistent=False)

    # ------------------------------------------------------------------ interface
    @property
    def num_vertices(self) -> int:
        return self.weights.shape[0]

    def default_shape(self, batch_size: int = 1) -> torch.Tensor:
        return self.weights.new_full((batch_size, self.shape_dim), 0.5)

    def _anny_rest(self, shape: torch.Tensor) -> dict:
        """Anny's own rest model for a (B, 6) phenotype batch, in Anny's frame."""
        local = shape.new_zeros(1, len(self.anny.local_change_labels))
        facial = shape.new_zeros(1, len(self.anny.facial_action_labels))
        coeffs = self.anny._get_phenotype_blendshape_coefficients(shape, local, facial)
        return self.anny.get_rest_model(coeffs)

    def prepare(self, shape: torch.Tensor) -> RestState:
        if shape.dim() != 2 or shape.shape[1] != self.shape_dim:
            raise ValueError(f"anny body: shape must be (batch, 6) phenotypes {PHENOTYPE_LABELS}, got {tuple(shape.shape)}")
        shape = shape.to(self.weights.dtype)
        anny_rest = self._anny_rest(shape)
        C = self.anny_to_world
        verts = anny_rest["rest_vertices"] @ C.T  # (B, V, 3) world frame
        heads = anny_rest["rest_bone_heads"] @ C.T  # (B, K, 3)
        tails = anny_rest.get("rest_bone_tails")
        if tails is None:
            raise ValueError("anny rig without bone tails: the T-pose needs them (use the cmu_mb rig)")
        tails = tails @ C.T

        B = shape.shape[0]
        jh = heads[:, self.joint_bones]  # (B, 22, 3) rest joint heads
        eye = torch.eye(3, dtype=verts.dtype, device=verts.device)
        G = [None] * NUM_JOINTS  # world T-posing rotation per joint
        P = [None] * NUM_JOINTS  # T-pose joint position
        target_of = {j: (end, d, kp) for j, end, d, kp in self._tpose_targets}
        for j in range(NUM_JOINTS):
            p = PARENTS[j]
            if p < 0:
                G[j] = eye.expand(B, 3, 3)
                P[j] = jh[:, j]
                continue
            P[j] = P[p] + (G[p] @ (jh[:, j] - jh[:, p])[..., None])[..., 0]
            if j not in target_of:
                G[j] = G[p]
                continue
            end, direction, keep_pitch = target_of[j]
            end_pos = tails[:, self.joint_bones[j]] if end < 0 else heads[:, end]
            current = (G[p] @ (end_pos - jh[:, j])[..., None])[..., 0]
            if keep_pitch:  # point the segment straight forward, keeping its rise/fall
                horiz = current[:, [0, 2]].norm(dim=-1, keepdim=True)
                target = torch.cat([torch.zeros_like(horiz), current[:, 1:2], horiz], dim=-1)
            else:  # a constant: made on the device once, not copied from the host at every call
                key = (tuple(direction), verts.dtype, verts.device)
                if key not in self._targets:
                    self._targets[key] = torch.tensor(direction, dtype=verts.dtype, device=verts.device)
                target = self._targets[key].expand_as(current)
            G[j] = rotation_between(current, target) @ G[p]
        G = torch.stack(G, dim=1)  # (B, 22, 3, 3)
        P = torch.stack(P, dim=1)  # (B, 22, 3)
        t = P - (G @ jh[..., None])[..., 0]
        A = torch.cat([G, t[..., None]], dim=-1)  # (B, 22, 3, 4): Anny rest -> T-pose, per joint

        # Lift onto the floor: the T-pose's lowest vertex at y = 0.
        tpose = linear_blend_skinning(verts, self.weights, A)
        floor = tpose[..., 1].amin(dim=-1)  # (B,)
        lift = torch.zeros_like(P)
        lift[..., 1] = -floor[:, None]
        A = torch.cat([G, (t + lift)[..., None]], dim=-1)
        return RestState(vertices=verts, joints=P + lift, pre_transforms=A)

    def _joint_transforms(self, rest: RestState, rotations: torch.Tensor):
        """Per-joint skinning transforms S_j = M_j A_j (B, T, 22, 3, 4) acting on Anny's rest
        vertices, with M_j = [R_j | p_j - R_j J_j] from FK; and the posed joints (B, T, 22, 3)."""
        rest_joints = rest.joints[:, None]  # (B, 1, 22, 3)
        g_rot, joints = forward_kinematics(rotations.to(rest.vertices.dtype), rest_joints)
        A = rest.pre_transforms[:, None]  # (B, 1, 22, 3, 4)
        rot = g_rot @ A[..., :3]
        tr = (g_rot @ (A[..., 3] - rest_joints)[..., None])[..., 0] + joints
        return torch.cat([rot, tr[..., None]], dim=-1), joints

    def skin(self, rest: RestState, rotations: torch.Tensor, trans: torch.Tensor,
             vertex_indices: torch.Tensor | None = None) -> BodyOutput:
        trans = trans.to(rest.vertices.dtype)
        S, joints = self._joint_transforms(rest, rotations)
        rest_vertices, weights = rest.vertices, self.weights
        if vertex_indices is not None and S.shape[0] == rest_vertices.shape[0]:
            # a subset (the fits' loss vertices, every step): one GEMM per sequence, rounded differently
            # from the reference form; the whole mesh (observations, scores) keeps the reference form,
            # so the data and the scores do not depend on this speed path
            verts = shared_rest_blend_skinning(rest_vertices[:, vertex_indices], weights[vertex_indices], S)
        else:
            if vertex_indices is not None:
                rest_vertices, weights = rest_vertices[:, vertex_indices], weights[vertex_indices]
            verts = linear_blend_skinning(rest_vertices[:, None], weights, S)
        return BodyOutput(vertices=verts + trans[..., None, :], joints=joints + trans[..., None, :])

    # ------------------------------------------------------------------ reference
    def anny_bone_poses(self, rest: RestState, rotations: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
        """World bone poses (B*T, K, 4, 4), in Anny's frame, equivalent to an SMPL-convention pose.

        Feeding these to ``anny.Anny.forward(..., pose_parameterization="world")`` reproduces this
        body's vertices (rotated back to Anny's frame); the tests use it as the reference.
        """
        B, T = rotations.shape[:2]
        S, _ = self._joint_transforms(rest, rotations)
        S = S.clone()
        S[..., 3] = S[..., 3] + trans.to(S)[..., None, :]  # world-frame skinning transform per joint
        S_bone = S[:, :, self.bone_to_joint]  # (B, T, K, 3, 4)
        C = self.anny_to_world
        # Anny frame: S_anny = C^T S C (rotation C^T R C, translation C^T t).
        R_a = C.T @ S_bone[..., :3] @ C
        t_a = (C.T @ S_bone[..., 3:])
        S_anny = torch.cat([R_a, t_a], dim=-1)
        shape_rest = self._anny_rest_poses(rest)  # (B, K, 4, 4) Anny rest bone poses (Anny frame)
        bottom = S_anny.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(*S_anny.shape[:-2], 1, 4)
        S_h = torch.cat([S_anny, bottom], dim=-2)
        W = S_h @ shape_rest[:, None]
        return W.reshape(B * T, *W.shape[2:])

    def _anny_rest_poses(self, rest: RestState) -> torch.Tensor:
        if rest.extra is None or "anny_rest_bone_poses" not in rest.extra:
            raise ValueError("prepare(..., keep_anny=True) is needed for the Anny reference poses")
        return rest.extra["anny_rest_bone_poses"]

    def prepare_with_anny(self, shape: torch.Tensor) -> RestState:
        rest = self.prepare(shape)
        rest.extra = {"anny_rest_bone_poses": self._anny_rest(shape.to(self.weights.dtype))["rest_bone_poses"]}
        return rest


_CACHED: dict = {}


def load_anny_body(device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32) -> AnnyBody:
    """The embedded body, built once per process (Anny's first build caches under ANNY_CACHE_DIR).

    One body per (device, dtype), each its own copy: ``nn.Module.to`` moves a module in place, so a
    load on another device or dtype must not move the cached float32 CPU body under its other users."""
    key = (str(device), dtype)
    if key not in _CACHED:
        if "cpu" not in _CACHED:
            log.info("building the embedded Anny body (first use builds Anny's cache, ~1 min)")
            _CACHED["cpu"] = AnnyBody(dtype=torch.float32)
        body = _CACHED["cpu"]
        _CACHED[key] = copy.deepcopy(body).to(device=device, dtype=dtype) if key != ("cpu", torch.float32) else body
    return _CACHED[key]


__all__ = ["AnnyBody", "load_anny_body", "PHENOTYPE_LABELS", "JOINT_BONES", "FOLDED_BONES"]
