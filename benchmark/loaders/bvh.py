"""BVH motion files -> :class:`Motion` on the SMPL 22-joint skeleton (the file format itself, parser
and a small writer, is :mod:`benchmark.loaders.bvh_format`).

Defaults are tuned to the CMU motion-capture database in its widely used 31-joint BVH conversion
(Hips, LHipJoint, LeftUpLeg, ..., LeftHandIndex1, LThumb, ...), and every CMU specific is a
parameter, so other BVH files load too:

- Units: one CMU length unit is 1/0.45 inch = 0.0254 / 0.45 m = 0.056444 m (``unit``).
- Frame 0 of every CMU file is a T-pose the converter added: dropped (``drop_first_frame``).
- Channels ``Zrotation Yrotation Xrotation`` in degrees mean R = Rz @ Ry @ Rx (any order string
  is read the same way). Nominal rate 120 fps, from ``Frame Time`` (snapped to an integer rate
  when within 1e-4 relative).
- Axes: the file's own OFFSETs say y up (head above hips), left at +x (LeftUpLeg x > 0) and
  facing +z (toes at +z) -- the harness's convention, so no global axis change. The loader checks
  this on the file's offsets (``check_axes``) instead of assuming it.
- Joint map (``joint_map``): each SMPL joint takes the composed rotation of a chain of BVH
  joints ("folding" a joint composes its rotation into the SMPL joint, so the global orientation
  of the SMPL joint's children is preserved): Hips -> pelvis; LHipJoint+LeftUpLeg -> left_hip;
  LeftLeg -> left_knee; LeftFoot -> left_ankle; LeftToeBase -> left_foot; LowerBack -> spine1;
  Spine -> spine2; Spine1 -> spine3; Neck -> neck; Neck1+Head -> head; LeftShoulder ->
  left_collar; LeftArm -> left_shoulder; LeftForeArm -> left_elbow; LeftHand+LeftFingerBase ->
  left_wrist (the CMU wrist twist sits at LeftHand, the wrist bend at LeftFingerBase); fingers
  and thumbs dropped; the same for the right side.
- Rest pose: BVH rotations are relative to the file's rest pose, which is not the SMPL T-pose
  (CMU legs are splayed 20 deg outward). For each SMPL joint whose map entry names a segment
  (``tip``) and its T-pose ``direction``, the correction C_j is the minimal rotation taking the
  SMPL T-pose direction to the file's rest direction of that segment (from the OFFSETs),
  optionally preceded by a twist about the bone (``rest_twist_deg``; offsets cannot show a twist).
  Then R_smpl_j = C_parent^T (folded BVH rotation) C_j, i.e. the global orientation of the SMPL
  joint is the BVH one times C_j. Defaults: hips/knees straight down, shoulders/elbows/wrists
  along +x (left) / -x (right), spine1/spine2 up. Neck, head, collars, ankles and feet are not
  corrected (their global orientation is copied): the SMPL T-pose itself has a forward neck,
  raised clavicles and forward-pointing feet, so their CMU directions are not a rest-pose
  convention to undo. The CMU arms are horizontal with the thumbs in the horizontal plane (the
  palms face down as in SMPL), so no twist is applied by default.

The SMPL rest joints implied by the file (its own bone lengths, in the SMPL T-pose) are stored in
``meta["rest_joints"]`` (metres); with them, :func:`benchmark.core.motion.joint_positions` reproduces
the file's joint positions (exactly, when the folded joints LHipJoint/RHipJoint and Neck1 carry
no rotation). ``trans`` = Hips world position x unit - rest pelvis, so the pelvis lands where the
file puts it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np
import torch

from benchmark.loaders.bvh_format import (
    BVHData,
    BVHSkeleton,
    parse_bvh,
)
from benchmark.core.motion import Motion
from benchmark.core.plausibility import MIN_MOTION_FRAMES, check_motion
from benchmark.core.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    rotation_between,
)
from benchmark.core.skeleton import JOINT_INDEX, JOINT_NAMES, PARENTS

__all__ = [
    "CMU_JOINT_MAP",
    "CMU_UNIT_M",
    "END",
    "JointSource",
    "Retarget",
    "load_bvh",
    "retarget_to_smpl",
]

CMU_UNIT_M = 0.0254 / 0.45  # one CMU length unit (1/0.45 inch) in metres = 0.056444...
END = "end"  # `tip` value meaning "the anchor joint's End Site"


# ---------------------------------------------------------------------------- SMPL mapping
@dataclass(frozen=True)
class JointSource:
    """Where one SMPL joint comes from in a BVH skeleton.

    chain: BVH joints whose local rotations compose (parent first) into the SMPL joint; the first
        one's BVH parent must be the last joint of the SMPL parent's chain. The last one is the
        anchor: the SMPL joint sits at its position.
    tip: a BVH joint (or END for the anchor's End Site) giving the rest direction anchor -> tip
        of the segment the SMPL joint rotates; None = no rest correction.
    direction: that segment's direction in the SMPL T-pose (world axes).
    """

    chain: tuple[str, ...]
    tip: str | None = None
    direction: tuple[float, float, float] | None = None


_DOWN, _UP, _LEFT, _RIGHT = (0.0, -1.0, 0.0), (0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)

CMU_JOINT_MAP: dict[str, JointSource] = {
    "pelvis": JointSource(("Hips",)),
    "left_hip": JointSource(("LHipJoint", "LeftUpLeg"), "LeftLeg", _DOWN),
    "right_hip": JointSource(("RHipJoint", "RightUpLeg"), "RightLeg", _DOWN),
    "spine1": JointSource(("LowerBack",), "Spine", _UP),
    "left_knee": JointSource(("LeftLeg",), "LeftFoot", _DOWN),
    "right_knee": JointSource(("RightLeg",), "RightFoot", _DOWN),
    "spine2": JointSource(("Spine",), "Spine1", _UP),
    "left_ankle": JointSource(("LeftFoot",)),
    "right_ankle": JointSource(("RightFoot",)),
    "spine3": JointSource(("Spine1",)),
    "left_foot": JointSource(("LeftToeBase",)),
    "right_foot": JointSource(("RightToeBase",)),
    "neck": JointSource(("Neck",)),
    "left_collar": JointSource(("LeftShoulder",)),
    "right_collar": JointSource(("RightShoulder",)),
    "head": JointSource(("Neck1", "Head")),
    "left_shoulder": JointSource(("LeftArm",), "LeftForeArm", _LEFT),
    "right_shoulder": JointSource(("RightArm",), "RightForeArm", _RIGHT),
    "left_elbow": JointSource(("LeftForeArm",), "LeftHand", _LEFT),
    "right_elbow": JointSource(("RightForeArm",), "RightHand", _RIGHT),
    "left_wrist": JointSource(("LeftHand", "LeftFingerBase"), "LeftHandIndex1", _LEFT),
    "right_wrist": JointSource(("RightHand", "RightFingerBase"), "RightHandIndex1", _RIGHT),
}


@dataclass
class Retarget:
    """A BVH skeleton mapped onto SMPL-22 (see module docstring)."""

    chains: list[list[int]]  # per SMPL joint, BVH joint indices (parent first)
    corrections: torch.Tensor  # (22, 3, 3) float64 rest corrections C_j
    rest_joints: torch.Tensor  # (22, 3) float64 SMPL T-pose joints, file units

    def local_rotations(self, bvh_local: torch.Tensor) -> torch.Tensor:
        """(F, J_bvh, 3, 3) BVH local rotations -> (F, 22, 3, 3) SMPL local rotations,
        R_j = C_parent^T (product of the chain) C_j."""
        folded = []
        for chain in self.chains:
            R = bvh_local[:, chain[0]]
            for b in chain[1:]:
                R = R @ bvh_local[:, b]
            folded.append(R)
        folded = torch.stack(folded, dim=1)
        C = self.corrections.to(folded)
        C_par = torch.stack([C[p] if p >= 0 else torch.eye(3, dtype=C.dtype) for p in PARENTS])
        return C_par.transpose(-1, -2) @ folded @ C


def retarget_to_smpl(
    skeleton: BVHSkeleton,
    joint_map: Mapping[str, JointSource] = CMU_JOINT_MAP,
    rest_twist_deg: Mapping[str, float] | None = None,
    where: str = "BVH",
) -> Retarget:
    """Resolve ``joint_map`` against ``skeleton`` and compute the rest corrections and the SMPL
    rest joints (see module docstring). rest_twist_deg: {smpl joint: degrees} twist about the
    joint's T-pose segment direction, applied before the swing (for rest poses whose bones are
    rolled about their own length, which offsets cannot show)."""
    rest_twist_deg = dict(rest_twist_deg or {})
    missing = [n for n in JOINT_NAMES if n not in joint_map]
    if missing:
        raise ValueError(f"{where}: joint_map lacks SMPL joints {missing}")
    unknown = set(rest_twist_deg) - set(JOINT_NAMES)
    if unknown:
        raise ValueError(f"{where}: rest_twist_deg names unknown SMPL joints {sorted(unknown)}")
    P = torch.from_numpy(skeleton.rest_positions())

    def idx(name, smpl):
        if name not in skeleton.names:
            raise ValueError(
                f"{where}: SMPL joint {smpl!r} maps to BVH joint {name!r}, which the file lacks "
                f"(joints: {', '.join(skeleton.names)}). Fix: name the joints as the CMU skeleton does (Hips, "
                "LeftUpLeg, ...: benchmark.loaders.bvh.CMU_JOINT_MAP), which `data convert` and `complete` read; "
                "or, from Python, load_bvh(path, joint_map=...) with this skeleton's joints for each SMPL joint"
            )
        return skeleton.names.index(name)

    chains, C = [], []
    for j, smpl in enumerate(JOINT_NAMES):
        src = joint_map[smpl]
        chain = [idx(b, smpl) for b in src.chain]
        if not chain:
            raise ValueError(f"{where}: SMPL joint {smpl!r} has an empty chain")
        p = PARENTS[j]
        expected_parent = chains[p][-1] if p >= 0 else -1
        for k, b in enumerate(chain):
            want = expected_parent if k == 0 else chain[k - 1]
            if skeleton.parents[b] != want:
                got = skeleton.parents[b]
                raise ValueError(
                    f"{where}: joint_map chain for {smpl!r} is not connected: BVH joint "
                    f"{skeleton.names[b]!r} has parent {skeleton.names[got] if got >= 0 else None!r}, "
                    f"expected {skeleton.names[want] if want >= 0 else None!r}"
                )
        chains.append(chain)
        anchor = chain[-1]
        Cj = torch.eye(3, dtype=torch.float64)
        twist = rest_twist_deg.get(smpl, 0.0)
        if src.tip is not None and src.direction is not None:
            if src.tip == END:
                if anchor not in skeleton.end_sites:
                    raise ValueError(f"{where}: {smpl!r}: BVH joint {skeleton.names[anchor]!r} has no End Site")
                seg = torch.from_numpy(skeleton.end_sites[anchor])
            else:
                seg = P[idx(src.tip, smpl)] - P[anchor]
            if seg.norm() < 1e-9:
                raise ValueError(f"{where}: {smpl!r}: zero-length rest segment to {src.tip!r}")
            t = torch.tensor(src.direction, dtype=torch.float64)
            t = t / t.norm()
            Cj = rotation_between(t, seg)
            if twist:
                Cj = Cj @ axis_angle_to_matrix(t * math.radians(twist))
        elif twist:
            raise ValueError(f"{where}: rest_twist_deg[{smpl!r}] needs a joint_map entry with tip and direction")
        C.append(Cj)
    C = torch.stack(C)
    anchors = [c[-1] for c in chains]
    rest = torch.zeros(22, 3, dtype=torch.float64)
    rest[0] = P[anchors[0]]
    for j in range(1, 22):
        p = PARENTS[j]
        rest[j] = rest[p] + C[p].T @ (P[anchors[j]] - P[anchors[p]])
    return Retarget(chains, C, rest)


def _check_axes(rest: torch.Tensor, where: str) -> None:
    I = JOINT_INDEX
    problems = []
    if not rest[I["left_hip"], 0] > rest[I["right_hip"], 0]:
        problems.append("left hip is not at +x of the right hip (left must be +x)")
    if not rest[I["head"], 1] > rest[I["pelvis"], 1]:
        problems.append("head is not above the pelvis (y must be up)")
    toes = rest[[I["left_foot"], I["right_foot"]], 2] - rest[[I["left_ankle"], I["right_ankle"]], 2]
    if not (toes > 0).all():
        problems.append("toes are not in front of the ankles (the body must face +z)")
    if problems:
        raise ValueError(
            f"{where}: rest skeleton does not follow the harness axes (y up, facing +z, left +x): "
            + "; ".join(problems)
            + ". Convert the file to these axes, or pass check_axes=False if you know better."
        )


def load_bvh(
    path,
    fps: float | None = None,
    unit: float = CMU_UNIT_M,
    drop_first_frame: bool = True,
    joint_map: Mapping[str, JointSource] = CMU_JOINT_MAP,
    rest_twist_deg: Mapping[str, float] | None = None,
    rest_pelvis=None,
    check_axes: bool = True,
) -> Motion:
    """Load a BVH file as a SMPL-22 :class:`Motion` (see the module docstring).

    fps: resample to this rate (exact ratio, SLERP); None keeps the file's rate.
    unit: metres per file length unit (CMU: 0.0254 / 0.45 = 0.056444; a cm file: 0.01).
    drop_first_frame: drop frame 0 (the CMU converter's added T-pose).
    joint_map / rest_twist_deg: SMPL joint sources and rest corrections (CMU defaults).
    rest_pelvis: (3,) metres, the rest pelvis of the body model the motion will drive; trans is
        set so the pelvis lands on the file's Hips. Default: the file's own rest pelvis
        (meta["rest_joints"][0]).
    """
    path = Path(path)
    data = parse_bvh(path)
    where = str(path)
    values = data.values
    # the skeleton first (a file the joint map cannot read is that error, whatever its frames)
    retarget = retarget_to_smpl(data.skeleton, joint_map, rest_twist_deg, where)
    if check_axes:
        _check_axes(retarget.rest_joints, where)
    if drop_first_frame:
        if data.num_frames - 1 < MIN_MOTION_FRAMES:
            raise ValueError(
                f"{where}: 'Frames: {data.num_frames}': the loader drops frame 0 (the T-pose the CMU converter adds "
                f"to every file), which leaves {max(data.num_frames - 1, 0)}, and a motion needs at least "
                f"{MIN_MOTION_FRAMES}. Fix: export the whole take; for a file without that added T-pose, repeat its "
                "first frame line at the top of the MOTION data and add 1 to 'Frames:' (from Python: "
                "load_bvh(path, drop_first_frame=False))"
            )
        data = BVHData(data.skeleton, data.frame_time, values[1:])
    elif data.num_frames < 1:
        raise ValueError(f"{where}: 'Frames: 0': the file holds no motion; export the whole take")

    rot = retarget.local_rotations(data.local_rotations())
    poses = matrix_to_axis_angle(rot)
    rest_joints = retarget.rest_joints * unit
    pelvis = rest_joints[0] if rest_pelvis is None else torch.as_tensor(np.asarray(rest_pelvis, np.float64)).reshape(3)
    trans = torch.from_numpy(data.root_positions()) * unit - pelvis

    rate = 1.0 / data.frame_time
    if abs(rate - round(rate)) < 1e-4 * rate:
        rate = float(round(rate))
    timestamps = torch.arange(data.num_frames, dtype=torch.float64) / rate
    sk = data.skeleton
    ignored_pos = [sk.names[j] for j in range(1, len(sk.names)) if any(c.lower().endswith("position") for c in sk.channels[j])]
    meta = {
        "format": "bvh",
        "file": where,
        "unit_m": unit,
        "frame_time": data.frame_time,
        "fps": rate,
        "dropped_first_frame": drop_first_frame,
        "rest_joints": rest_joints.tolist(),
        "rest_pelvis_used": pelvis.tolist(),
        "rest_correction_deg": {
            n: math.degrees(float(a)) for n, a in zip(JOINT_NAMES, matrix_to_axis_angle(retarget.corrections).norm(dim=-1))
        },
        "rest_twist_deg": dict(rest_twist_deg or {}),
    }
    if ignored_pos:
        meta["ignored_position_channels"] = ignored_pos
    motion = Motion(poses=poses.float(), trans=trans.float(), timestamps=timestamps, source=f"bvh:{path}", meta=meta)
    check_motion(motion, where, time_field="Frame Time",
                 time_fix="'Frame Time' is the seconds per frame (1/120 = 0.0083333 for 120 fps)",
                 trans_field="root position channels",
                 trans_fix=(f"the loader reads lengths in CMU units ({unit:.6g} m each): write the file in those units "
                            "(from Python: load_bvh(path, unit=METRES_PER_FILE_UNIT))"))
    if fps is not None:
        motion = motion.resample_fps(float(fps))
    return motion
