"""BVH motion files -> :class:`Motion` on the SMPL 22-joint skeleton; and a small BVH writer.

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
``meta["rest_joints"]`` (metres); with them, :func:`benchmark.motion.joint_positions` reproduces
the file's joint positions (exactly, when the folded joints LHipJoint/RHipJoint and Neck1 carry
no rotation). ``trans`` = Hips world position x unit - rest pelvis, so the pelvis lands where the
file puts it.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np
import torch

from benchmark.motion import Motion
from benchmark.rotations import (
    axis_angle_to_matrix,
    euler_to_matrix,
    matrix_to_axis_angle,
    matrix_to_euler,
    rotation_between,
)
from benchmark.skeleton import JOINT_INDEX, JOINT_NAMES, PARENTS

CMU_UNIT_M = 0.0254 / 0.45  # one CMU length unit (1/0.45 inch) in metres = 0.056444...
END = "end"  # `tip` value meaning "the anchor joint's End Site"

_CHANNEL_RE = re.compile(r"^([XYZ])(position|rotation)$", re.IGNORECASE)


# ---------------------------------------------------------------------------- data structures
@dataclass
class BVHSkeleton:
    """Joints in file (depth-first) order. Offsets are in file units, relative to the parent."""

    names: list[str]
    parents: list[int]
    offsets: np.ndarray  # (J, 3) float64
    channels: list[tuple[str, ...]]  # per joint, e.g. ("Zrotation", "Yrotation", "Xrotation")
    end_sites: dict[int, np.ndarray] = field(default_factory=dict)  # joint index -> (3,) offset

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"BVH skeleton has no joint {name!r} (joints: {', '.join(self.names)})") from None

    @property
    def num_channels(self) -> int:
        return sum(len(c) for c in self.channels)

    def rest_positions(self) -> np.ndarray:
        """(J, 3) joint positions with every rotation zero (file units; root at its OFFSET)."""
        P = np.zeros((len(self.names), 3))
        for j, p in enumerate(self.parents):
            P[j] = self.offsets[j] + (P[p] if p >= 0 else 0.0)
        return P

    def column_slices(self) -> list[tuple[int, int]]:
        """(start, stop) of each joint's channels in a frame row."""
        out, c = [], 0
        for ch in self.channels:
            out.append((c, c + len(ch)))
            c += len(ch)
        return out


@dataclass
class BVHData:
    skeleton: BVHSkeleton
    frame_time: float  # seconds
    values: np.ndarray  # (F, C) float64 channel values in file order (degrees, file units)

    @property
    def num_frames(self) -> int:
        return int(self.values.shape[0])

    def local_rotations(self) -> torch.Tensor:
        """(F, J, 3, 3) float64 local rotations; identity for joints without rotation channels.

        Joints sharing one channel order are converted in one batched call."""
        sk = self.skeleton
        F, J = self.num_frames, len(sk.names)
        out = torch.eye(3, dtype=torch.float64).expand(F, J, 3, 3).clone()
        groups: dict[str, list[tuple[int, list[int]]]] = {}
        for j, ((start, _), chans) in enumerate(zip(sk.column_slices(), sk.channels)):
            cols = [start + k for k, c in enumerate(chans) if c.lower().endswith("rotation")]
            if cols:
                order = "".join(sk.channels[j][k - start][0].upper() for k in cols)
                groups.setdefault(order, []).append((j, cols))
        vals = torch.from_numpy(np.deg2rad(self.values))
        for order, members in groups.items():
            idx = [j for j, _ in members]
            angles = vals[:, [c for _, cols in members for c in cols]].reshape(F, len(idx), len(order))
            if len(order) == 3:
                R = euler_to_matrix(angles, order)
            else:  # 1 or 2 rotation channels: compose elementary rotations in written order
                R = torch.eye(3, dtype=torch.float64).expand(F, len(idx), 3, 3)
                for k, axis in enumerate(order):
                    R = R @ _elementary(axis, angles[..., k])
            out[:, idx] = R
        return out

    def root_positions(self) -> np.ndarray:
        """(F, 3) root world positions in file units: root OFFSET + its position channels."""
        sk = self.skeleton
        start, _ = sk.column_slices()[0]
        pos = np.broadcast_to(sk.offsets[0], (self.num_frames, 3)).copy()
        for k, c in enumerate(sk.channels[0]):
            m = _CHANNEL_RE.match(c)
            if m and m.group(2).lower() == "position":
                pos[:, "XYZ".index(m.group(1).upper())] += self.values[:, start + k]
        return pos


def _elementary(axis: str, angle: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    o, z = torch.ones_like(angle), torch.zeros_like(angle)
    rows = {
        "X": ((o, z, z), (z, c, -s), (z, s, c)),
        "Y": ((c, z, s), (z, o, z), (-s, z, c)),
        "Z": ((c, -s, z), (s, c, z), (z, z, o)),
    }[axis]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


# ---------------------------------------------------------------------------- parsing
def parse_bvh(path) -> BVHData:
    """Parse a BVH file (HIERARCHY with ROOT/JOINT/OFFSET/CHANNELS/End Site; MOTION with
    ``Frames:`` and ``Frame Time:``). Errors name the file and the line."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such BVH file") from None
    m = re.search(r"^\s*MOTION\s*$", text, re.MULTILINE)
    if m is None:
        raise ValueError(f"{path}: no MOTION section (a BVH file has HIERARCHY ... then MOTION ...)")
    toks = [(t, n + 1) for n, line in enumerate(text[: m.start()].splitlines()) for t in line.split()]
    skeleton = _parse_hierarchy(toks, path)
    motion_line = text[: m.start()].count("\n") + 1

    body = text[m.end():]
    fm = re.match(r"\s*Frames:\s*(\d+)\s*Frame\s+Time:\s*(\S+)", body)
    if fm is None:
        raise ValueError(f"{path}:{motion_line}: expected 'Frames: N' and 'Frame Time: dt' after MOTION")
    n_frames, frame_time = int(fm.group(1)), _float(fm.group(2), path, "Frame Time")
    if not frame_time > 0:
        raise ValueError(f"{path}: 'Frame Time' must be positive, got {frame_time}")
    try:
        flat = np.array(body[fm.end():].split(), dtype=np.float64)
    except ValueError as e:
        raise ValueError(f"{path}: non-numeric value in the MOTION data ({e})") from None
    C = skeleton.num_channels
    if flat.size != n_frames * C:
        raise ValueError(
            f"{path}: MOTION holds {flat.size} numbers, expected Frames ({n_frames}) x channels ({C}) "
            f"= {n_frames * C}; the file is truncated or its CHANNELS do not match the data"
        )
    values = flat.reshape(n_frames, C)
    if not np.isfinite(values).all():
        raise ValueError(f"{path}: MOTION data contains NaN/inf")
    return BVHData(skeleton, frame_time, values)


def _float(s, path, what):
    try:
        return float(s)
    except ValueError:
        raise ValueError(f"{path}: {what}: expected a number, got {s!r}") from None


def _parse_hierarchy(toks, path) -> BVHSkeleton:
    pos = 0

    def take(expected=None):
        nonlocal pos
        if pos >= len(toks):
            raise ValueError(f"{path}: unexpected end of HIERARCHY" + (f", expected {expected!r}" if expected else ""))
        tok, line = toks[pos]
        pos += 1
        if expected is not None and tok.lower() != expected.lower():
            raise ValueError(f"{path}:{line}: expected {expected!r}, got {tok!r}")
        return tok, line

    names, parents, offsets, channels, end_sites = [], [], [], [], {}

    def offset():
        take("OFFSET")
        return [_float(take()[0], path, "OFFSET") for _ in range(3)]

    def joint(parent):
        name, line = take()
        if name in names:
            raise ValueError(f"{path}:{line}: duplicate joint name {name!r}")
        j = len(names)
        names.append(name)
        parents.append(parent)
        offsets.append([0.0, 0.0, 0.0])
        channels.append(())
        take("{")
        while True:
            tok, line = take()
            low = tok.lower()
            if low == "offset":
                pos_back()
                offsets[j] = offset()
            elif low == "channels":
                n = int(_float(take()[0], path, "CHANNELS count"))
                chans = tuple(take()[0] for _ in range(n))
                for c in chans:
                    if not _CHANNEL_RE.match(c):
                        raise ValueError(f"{path}:{line}: unknown channel {c!r} (expected X/Y/Z position/rotation)")
                channels[j] = chans
            elif low == "joint":
                joint(j)
            elif low == "end":
                take("Site")
                take("{")
                end_sites[j] = np.array(offset())
                take("}")
            elif tok == "}":
                return
            else:
                raise ValueError(f"{path}:{line}: unexpected {tok!r} in joint {name!r}")

    def pos_back():
        nonlocal pos
        pos -= 1

    take("HIERARCHY")
    take("ROOT")
    joint(-1)
    if pos != len(toks):
        tok, line = toks[pos]
        raise ValueError(f"{path}:{line}: unexpected {tok!r} after the root joint (one ROOT per file)")
    return BVHSkeleton(names, parents, np.array(offsets, dtype=np.float64), channels, end_sites)


# ---------------------------------------------------------------------------- writing
def write_bvh(path, skeleton: BVHSkeleton, rotations, root_positions, frame_time: float, decimals: int = 6) -> Path:
    """Write a BVH file.

    rotations: (F, J, 3, 3) local rotations in the skeleton's joint order (entries of joints
        without rotation channels are ignored); written as Euler degrees in each joint's
        channel order. root_positions: (F, 3) root world positions in file units (the root's
        position channels hold root_positions - root OFFSET). frame_time: seconds.
    """
    path = Path(path)
    R = torch.as_tensor(rotations, dtype=torch.float64)
    root = np.asarray(root_positions, dtype=np.float64)
    F, J = R.shape[:2]
    if R.shape != (F, len(skeleton.names), 3, 3) or root.shape != (F, 3):
        raise ValueError(
            f"write_bvh: rotations must be (F, {len(skeleton.names)}, 3, 3) and root_positions (F, 3), "
            f"got {tuple(R.shape)} and {root.shape}"
        )
    cols = []
    for j, chans in enumerate(skeleton.channels):
        rot = [c[0].upper() for c in chans if c.lower().endswith("rotation")]
        euler = None
        if len(rot) == 3:
            euler = np.rad2deg(matrix_to_euler(R[:, j], "".join(rot)).numpy())
        elif rot:
            raise ValueError(f"write_bvh: joint {skeleton.names[j]!r} needs 3 rotation channels, has {chans}")
        k_rot = 0
        for c in chans:
            axis = "XYZ".index(c[0].upper())
            if c.lower().endswith("position"):
                cols.append(root[:, axis] - skeleton.offsets[0, axis] if j == 0 else np.zeros(F))
            else:
                cols.append(euler[:, k_rot])
                k_rot += 1
    values = np.stack(cols, axis=1) if cols else np.zeros((F, 0))

    children = [[] for _ in skeleton.names]
    for j, p in enumerate(skeleton.parents):
        if p >= 0:
            children[p].append(j)
    order: list[int] = []
    lines = ["HIERARCHY"]
    fmt = f"{{:.{decimals}f}}"

    def emit(j, depth):
        order.append(j)
        ind = "  " * depth
        kind = "ROOT" if skeleton.parents[j] < 0 else "JOINT"
        lines.append(f"{ind}{kind} {skeleton.names[j]}")
        lines.append(f"{ind}{{")
        lines.append(f"{ind}  OFFSET " + " ".join(fmt.format(v) for v in skeleton.offsets[j]))
        if skeleton.channels[j]:
            lines.append(f"{ind}  CHANNELS {len(skeleton.channels[j])} " + " ".join(skeleton.channels[j]))
        for c in children[j]:
            emit(c, depth + 1)
        if j in skeleton.end_sites:
            lines.extend([f"{ind}  End Site", f"{ind}  {{",
                      f"{ind}    OFFSET " + " ".join(fmt.format(v) for v in skeleton.end_sites[j]), f"{ind}  }}"])
        lines.append(f"{ind}}}")

    emit(0, 0)
    if len(order) != J:
        raise ValueError("write_bvh: skeleton is not one tree rooted at joint 0")
    slices = skeleton.column_slices()
    col_order = [c for j in order for c in range(*slices[j])]
    lines += ["MOTION", f"Frames: {F}", f"Frame Time: {frame_time:.7f}"]
    body = "\n".join(" ".join(fmt.format(v) for v in row) for row in values[:, col_order])
    path.write_text("\n".join(lines) + "\n" + body + "\n")
    return path


def cmu_skeleton() -> BVHSkeleton:
    """A CMU-like 31-joint skeleton in file units: the offsets of one subject of the common CMU
    BVH conversion (legs splayed 20 deg outward, arms horizontal along +-x, y up, facing +z)."""
    zyx = ("Zrotation", "Yrotation", "Xrotation")
    spec = [  # name, parent, offset, end site
        ("Hips", None, (0, 0, 0), None),
        ("LHipJoint", "Hips", (0, 0, 0), None),
        ("LeftUpLeg", "LHipJoint", (1.85590, -1.73949, 0.84976), None),
        ("LeftLeg", "LeftUpLeg", (2.36836, -6.50702, 0), None),
        ("LeftFoot", "LeftLeg", (2.53268, -6.95849, 0), None),
        ("LeftToeBase", "LeftFoot", (0.15935, -0.43781, 1.94506), (0, 0, 1.00661)),
        ("RHipJoint", "Hips", (0, 0, 0), None),
        ("RightUpLeg", "RHipJoint", (-1.68297, -1.73949, 0.84976), None),
        ("RightLeg", "RightUpLeg", (-2.44709, -6.72334, 0), None),
        ("RightFoot", "RightLeg", (-2.43843, -6.69953, 0), None),
        ("RightToeBase", "RightFoot", (-0.20854, -0.57295, 2.02172), (0, 0, 1.05594)),
        ("LowerBack", "Hips", (0, 0, 0), None),
        ("Spine", "LowerBack", (-0.01560, 2.23971, -0.03712), None),
        ("Spine1", "Spine", (0.05490, 2.19225, -0.19086), None),
        ("Neck", "Spine1", (0, 0, 0), None),
        ("Neck1", "Neck", (-0.12403, 1.43168, 0.27585), None),
        ("Head", "Neck1", (0.17855, 1.46173, -0.32578), (0.07217, 1.51590, -0.14537)),
        ("LeftShoulder", "Spine1", (0, 0, 0), None),
        ("LeftArm", "LeftShoulder", (3.27650, 0.85634, 0.05396), None),
        ("LeftForeArm", "LeftArm", (4.96755, 0, 0), None),
        ("LeftHand", "LeftForeArm", (3.35751, 0, 0), None),
        ("LeftFingerBase", "LeftHand", (0, 0, 0), None),
        ("LeftHandIndex1", "LeftFingerBase", (0.79697, 0, 0), (0.64254, 0, 0)),
        ("LThumb", "LeftHand", (0, 0, 0), (0.65235, 0, 0.65235)),
        ("RightShoulder", "Spine1", (0, 0, 0), None),
        ("RightArm", "RightShoulder", (-3.24434, 1.02034, 0.34688), None),
        ("RightForeArm", "RightArm", (-5.21859, 0, 0), None),
        ("RightHand", "RightForeArm", (-3.36504, 0, 0), None),
        ("RightFingerBase", "RightHand", (0, 0, 0), None),
        ("RightHandIndex1", "RightFingerBase", (-0.62044, 0, 0), (-0.50022, 0, 0)),
        ("RThumb", "RightHand", (0, 0, 0), (-0.50786, 0, 0.50786)),
    ]
    names = [s[0] for s in spec]
    parents = [-1 if s[1] is None else names.index(s[1]) for s in spec]
    channels = [(("Xposition", "Yposition", "Zposition") + zyx) if s[1] is None else zyx for s in spec]
    ends = {i: np.array(s[3], dtype=np.float64) for i, s in enumerate(spec) if s[3] is not None}
    return BVHSkeleton(names, parents, np.array([s[2] for s in spec], dtype=np.float64), channels, ends)


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
                f"(joints: {', '.join(skeleton.names)}); pass a joint_map for this skeleton"
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
    if drop_first_frame:
        if data.num_frames < 2:
            raise ValueError(f"{where}: {data.num_frames} frame(s); nothing left after dropping frame 0 "
                             "(pass drop_first_frame=False for files without an added T-pose frame)")
        data = BVHData(data.skeleton, data.frame_time, values[1:])
    elif data.num_frames < 1:
        raise ValueError(f"{where}: no frames")
    retarget = retarget_to_smpl(data.skeleton, joint_map, rest_twist_deg, where)
    if check_axes:
        _check_axes(retarget.rest_joints, where)

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
    if fps is not None:
        motion = motion.resample_fps(float(fps))
    return motion
