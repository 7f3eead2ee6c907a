"""The BVH file format: skeleton and motion data (:class:`BVHSkeleton`, :class:`BVHData`), a
parser (:func:`parse_bvh`), a small writer (:func:`write_bvh`) and a CMU-like 31-joint skeleton
(:func:`cmu_skeleton`). Conversion to the SMPL 22-joint skeleton lives in
:mod:`benchmark.loaders.bvh`.

Channels ``Zrotation Yrotation Xrotation`` in degrees mean R = Rz @ Ry @ Rx (any order string is
read the same way).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from benchmark.core.rotations import euler_to_matrix, matrix_to_euler

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
        raw = path.read_bytes()
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such BVH file") from None
    except IsADirectoryError:
        raise ValueError(f"{path}: is a folder, not a BVH file") from None
    if not raw.strip():
        raise ValueError(f"{path}: the file is empty; a BVH file is text: HIERARCHY ... then MOTION ... "
                         "(export the take again)")
    if b"\0" in raw[:65536]:
        raise ValueError(f"{path}: a binary file, not a BVH (text: HIERARCHY ... then MOTION ...); export the take as "
                         "BVH again, or check that this is the file you meant")
    try:
        text = raw.decode("utf-8-sig")  # a byte-order mark (some Windows exporters) is not part of the text
    except UnicodeDecodeError:
        text = raw.decode("latin-1")  # older exporters: joint names in a legacy 8-bit encoding
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
    if not (frame_time > 0 and math.isfinite(frame_time)):
        raise ValueError(f"{path}: 'Frame Time' must be a positive number of seconds per frame, got {frame_time}")
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
                count, count_line = take()
                if not count.isdigit():
                    raise ValueError(f"{path}:{count_line}: CHANNELS count: expected a whole number, got {count!r}")
                n = int(count)
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
