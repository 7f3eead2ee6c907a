"""One motion sequence on the SMPL 22-joint skeleton, and the harness's own ``.npz`` format.

A :class:`Motion` holds local joint rotations (axis-angle, SMPL convention: relative to a T-pose
whose joint frames are aligned with the world axes), the root translation in metres (world y up,
body facing +z) and one timestamp per frame in seconds. The translation follows the SMPL
meaning: it is added to every posed joint, so the pelvis lies at ``rest_pelvis + trans``.

File format (``Motion.save`` / ``Motion.load``), all arrays plain (no pickle):

    poses       (T, 22, 3) float32   axis-angle, radians
    trans       (T, 3)     float32   metres, y up
    timestamps  (T,)       float64   seconds, strictly increasing
    fps         ()         float64   nominal rate 1 / median(dt) (NaN for one frame)
    shape       (S,)       float32   optional body-shape vector
    body        ()         unicode   optional: which body model ``shape`` belongs to
    source      ()         unicode   where the motion came from
    meta        ()         unicode   optional JSON object (provenance: corrections, units, ...)

A hand-written file may omit ``timestamps`` if it gives ``fps`` (frames at k / fps).

``Motion.load`` also refuses implausible content (:mod:`benchmark.core.plausibility`): fewer than 2
frames, timestamps whose rate is outside 1-1,000 fps or whose span exceeds an hour (milliseconds),
a translation beyond 1 km (millimetres, a scale error); it warns on unusual but usable content.
"""

from __future__ import annotations

import json
import logging
import math
import os
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from benchmark.body.lbs import forward_kinematics
from benchmark.core.plausibility import SMPL_FAMILY, check_motion, check_shape, shape_family
from benchmark.core.rotations import axis_angle_to_matrix, matrix_to_axis_angle, slerp_matrices
from benchmark.core.skeleton import NUM_JOINTS

log = logging.getLogger(__name__)

_TIME_EPS = 1e-9  # seconds; tolerance for timestamp comparisons at window edges


def _validate(poses, trans, timestamps, shape, where: str) -> None:
    """Check shapes, finiteness and time order; errors name `where` and the field."""
    if poses.dim() != 3 or poses.shape[1:] != (NUM_JOINTS, 3):
        hint = ""
        if poses.dim() == 2 and poses.shape[1] == NUM_JOINTS * 3:
            hint = f"; reshape the flat (T, {NUM_JOINTS * 3}) array to (T, {NUM_JOINTS}, 3)"
        raise ValueError(
            f"{where}: field 'poses' has shape {tuple(poses.shape)}, expected (T, {NUM_JOINTS}, 3){hint}"
        )
    T = poses.shape[0]
    if T < 1:
        raise ValueError(f"{where}: field 'poses' has no frames")
    if trans.shape != (T, 3):
        raise ValueError(f"{where}: field 'trans' has shape {tuple(trans.shape)}, expected (T, 3) = ({T}, 3)")
    if timestamps.shape != (T,):
        raise ValueError(
            f"{where}: field 'timestamps' has shape {tuple(timestamps.shape)}, expected (T,) = ({T},)"
        )
    named = [("poses", poses), ("trans", trans), ("timestamps", timestamps)]
    if shape is not None:
        if shape.dim() != 1:
            raise ValueError(f"{where}: field 'shape' has shape {tuple(shape.shape)}, expected (S,)")
        named.append(("shape", shape))
    for name, x in named:
        bad = ~torch.isfinite(x)
        if bad.any():
            rows = torch.nonzero(bad.reshape(x.shape[0], -1).any(-1)).flatten()
            if name == "shape":
                unit, fix = "index", "; give finite shape coefficients"
            else:
                unit, fix = "frame", ("; drop or repair those frames (a capture's gaps are often NaN: trim the sequence "
                                      "to the frames that hold values, or fill them) and save the file again")
            raise ValueError(
                f"{where}: field {name!r} has {int(bad.sum())} non-finite values (NaN/inf) in {rows.numel()} "
                f"{unit}{'s' if rows.numel() != 1 else ''} (the first: {rows[:5].tolist()}){fix}"
            )
    if T > 1:
        dt = timestamps[1:] - timestamps[:-1]
        if (dt <= 0).any():
            i = int(torch.nonzero(dt <= 0)[0])
            raise ValueError(
                f"{where}: field 'timestamps' is not strictly increasing at index {i} "
                f"(t[{i}] = {float(timestamps[i])!r}, t[{i + 1}] = {float(timestamps[i + 1])!r})"
            )


@dataclass
class Motion:
    """One sequence. Arrays are coerced to torch (poses/trans/shape float32, timestamps float64).

    poses: (T, 22, 3) local axis-angle rotations, radians, SMPL joint order and convention.
    trans: (T, 3) root translation, metres, y up (added to all joints, SMPL meaning).
    timestamps: (T,) seconds, strictly increasing (need not start at 0).
    shape: optional (S,) body-shape vector of the body model named by ``body``.
    body: optional name of the body model ``shape`` belongs to (e.g. "anny", "smplh").
    source: where the sequence came from (free text, e.g. "amass:path/to/file.npz").
    meta: provenance (JSON-serialisable values preferred; they are saved as JSON).
    """

    poses: torch.Tensor
    trans: torch.Tensor
    timestamps: torch.Tensor
    shape: torch.Tensor | None = None
    body: str | None = None
    source: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.poses = torch.as_tensor(self.poses, dtype=torch.float32)
        self.trans = torch.as_tensor(self.trans, dtype=torch.float32)
        self.timestamps = torch.as_tensor(self.timestamps, dtype=torch.float64)
        if self.shape is not None:
            self.shape = torch.as_tensor(self.shape, dtype=torch.float32)
        if self.body is not None and not isinstance(self.body, str):
            raise TypeError(f"Motion: field 'body' must be a str or None, got {type(self.body).__name__}")
        if not isinstance(self.source, str):
            raise TypeError(f"Motion: field 'source' must be a str, got {type(self.source).__name__}")
        if not isinstance(self.meta, dict):
            raise TypeError(f"Motion: field 'meta' must be a dict, got {type(self.meta).__name__}")
        _validate(self.poses, self.trans, self.timestamps, self.shape, f"Motion ({self.source})" if self.source else "Motion")

    # ------------------------------------------------------------------ properties
    @property
    def num_frames(self) -> int:
        return int(self.poses.shape[0])

    @property
    def fps(self) -> float:
        """Nominal frame rate 1 / median(dt) in Hz; NaN for a single frame."""
        if self.num_frames < 2:
            return math.nan
        return float(1.0 / torch.median(self.timestamps.diff()))

    @property
    def span(self) -> float:
        """Seconds from the first to the last timestamp (a 120-frame 30 fps motion spans 119/30 s)."""
        return float(self.timestamps[-1] - self.timestamps[0])

    @property
    def duration(self) -> float:
        """Seconds the frames cover: span + one median frame period (a 120-frame 30 fps motion
        lasts 4.0 s); 0 for a single frame. A window of this length fits (see :meth:`window`)."""
        if self.num_frames < 2:
            return 0.0
        return self.span + float(torch.median(self.timestamps.diff()))

    def rotmats(self) -> torch.Tensor:
        """(T, 22, 3, 3) local rotation matrices."""
        return axis_angle_to_matrix(self.poses)

    # ------------------------------------------------------------------ time
    def resample(self, timestamps) -> Motion:
        """The motion at new timestamps (N,) seconds, strictly increasing.

        Every joint rotation is SLERPed between the two bracketing frames (shortest arc) and the
        translation is interpolated linearly. Timestamps before the first frame or after the last
        one are clamped: they get the first / last frame unchanged (no extrapolation). Vectorised:
        one searchsorted and one batched SLERP, no per-frame loop.
        """
        new_t = torch.as_tensor(timestamps, dtype=torch.float64).flatten()
        if new_t.numel() == 0:
            raise ValueError("resample: no timestamps given")
        t = self.timestamps
        T = self.num_frames
        if T == 1:
            idx = torch.zeros(len(new_t), dtype=torch.long)
            return replace(
                self, poses=self.poses[idx], trans=self.trans[idx], timestamps=new_t, meta=dict(self.meta)
            )
        i0 = (torch.searchsorted(t, new_t, right=True) - 1).clamp(0, T - 2)
        i1 = i0 + 1
        w = ((new_t - t[i0]) / (t[i1] - t[i0])).clamp(0.0, 1.0)
        R = axis_angle_to_matrix(self.poses.double())
        R_new = slerp_matrices(R[i0], R[i1], w[:, None])
        poses = matrix_to_axis_angle(R_new).float()
        tr = self.trans.double()
        trans = (tr[i0] + w[:, None] * (tr[i1] - tr[i0])).float()
        return replace(self, poses=poses, trans=trans, timestamps=new_t, meta=dict(self.meta))

    def resample_fps(self, fps: float) -> Motion:
        """Resample to a uniform rate: timestamps t0 + k / fps covering [t0, t_last] (exact rate
        ratio, SLERP between frames, never integer frame skipping)."""
        if not (fps > 0 and math.isfinite(fps)):
            raise ValueError(f"resample_fps: fps must be a positive number, got {fps!r}")
        n = int(math.floor(self.span * fps + 1e-6)) + 1
        t0 = float(self.timestamps[0])
        new_t = t0 + torch.arange(n, dtype=torch.float64) / fps
        out = self.resample(new_t)
        out.meta["resampled"] = {"from_fps": self.fps, "to_fps": float(fps)}
        return out

    def window(self, t0: float, duration: float) -> Motion:
        """Frames with t0 <= t < t0 + duration (timestamps kept absolute).

        Raises if the window starts before the first frame or ends after ``t_first + duration``
        (the last frame's period), so a too-short window is never returned silently.
        """
        t = self.timestamps
        end = float(t[0]) + self.duration
        if t0 < float(t[0]) - _TIME_EPS or t0 + duration > end + 1e-6:
            raise ValueError(
                f"window [{t0}, {t0 + duration}) s lies outside the motion "
                f"[{float(t[0])}, {end}) s ({self.source or 'motion'})"
            )
        keep = (t >= t0 - _TIME_EPS) & (t < t0 + duration - _TIME_EPS)
        if not keep.any():
            raise ValueError(f"window [{t0}, {t0 + duration}) s contains no frames")
        return replace(
            self, poses=self.poses[keep], trans=self.trans[keep], timestamps=t[keep], meta=dict(self.meta)
        )

    # ------------------------------------------------------------------ IO
    def save(self, path) -> Path:
        """Write the harness ``.npz`` (see module docstring), atomically (temp file + rename)."""
        path = Path(path)
        if path.suffix.lower() != ".npz":
            raise ValueError(f"{path}: the harness motion format is .npz; give a path ending in .npz")
        arrays = {
            "poses": self.poses.detach().cpu().numpy().astype(np.float32),
            "trans": self.trans.detach().cpu().numpy().astype(np.float32),
            "timestamps": self.timestamps.detach().cpu().numpy().astype(np.float64),
            "fps": np.array(self.fps, dtype=np.float64),
            "source": np.array(self.source, dtype=np.str_),
        }
        if self.shape is not None:
            arrays["shape"] = self.shape.detach().cpu().numpy().astype(np.float32)
        if self.body is not None:
            arrays["body"] = np.array(self.body, dtype=np.str_)
        if self.meta:
            arrays["meta"] = np.array(json.dumps(self.meta, default=_json_default), dtype=np.str_)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                _write_npz_deterministic(f, arrays)
            os.chmod(tmp, 0o644)
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        return path

    @classmethod
    def load(cls, path) -> Motion:
        """Read a harness ``.npz``; errors name the file and the field."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such motion file")
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except ValueError as e:  # object arrays need pickle: refuse, say why
            raise ValueError(f"{path}: cannot read without pickle ({e}); re-save it with Motion.save") from e
        except Exception as e:
            raise ValueError(f"{path}: not a readable .npz file ({e})") from e
        where = str(path)
        if "poses" not in data:
            raise KeyError(f"{where}: missing field 'poses' (fields present: {sorted(data)})")
        if "trans" not in data:
            raise KeyError(f"{where}: missing field 'trans' (fields present: {sorted(data)})")
        T = data["poses"].shape[0] if data["poses"].ndim else 0
        file_fps = None
        if "fps" in data:
            if data["fps"].shape != () or not np.issubdtype(data["fps"].dtype, np.number):
                raise ValueError(f"{where}: field 'fps' must be a scalar number, got {data['fps']!r}")
            file_fps = float(data["fps"])
        if "timestamps" in data:
            timestamps = data["timestamps"]
        elif file_fps is not None and file_fps > 0:
            timestamps = np.arange(T, dtype=np.float64) / file_fps
        else:
            raise KeyError(f"{where}: missing field 'timestamps' (or a positive 'fps' to derive them)")

        def text(name):
            if name not in data:
                return None
            a = data[name]
            if a.shape != () or a.dtype.kind not in "US":
                raise ValueError(f"{where}: field {name!r} must be a 0-d string array, got {a.dtype} {a.shape}")
            v = a.item()
            return v.decode() if isinstance(v, bytes) else str(v)

        tensors = {}
        for name, arr in (("poses", data["poses"]), ("trans", data["trans"]), ("timestamps", timestamps)):
            if not np.issubdtype(arr.dtype, np.number):
                raise ValueError(f"{where}: field {name!r} has non-numeric dtype {arr.dtype}")
            tensors[name] = torch.as_tensor(arr, dtype=torch.float64 if name == "timestamps" else torch.float32)
        if "shape" in data and not np.issubdtype(data["shape"].dtype, np.number):
            raise ValueError(f"{where}: field 'shape' has non-numeric dtype {data['shape'].dtype} (the body's shape "
                             "parameters are numbers); remove the field or write the numbers")
        shape = torch.as_tensor(data["shape"], dtype=torch.float32) if "shape" in data else None
        _validate(tensors["poses"], tensors["trans"], tensors["timestamps"], shape, where)
        meta_text = text("meta")
        try:
            meta = json.loads(meta_text) if meta_text else {}
        except json.JSONDecodeError as e:
            raise ValueError(f"{where}: field 'meta' is not valid JSON ({e})") from e
        motion = cls(
            tensors["poses"], tensors["trans"], tensors["timestamps"], shape=shape,
            body=text("body"), source=text("source") or "", meta=meta,
        )
        if file_fps is not None and motion.num_frames > 1 and math.isfinite(file_fps):
            if abs(file_fps - motion.fps) > 1e-3 * max(1.0, motion.fps):
                raise ValueError(
                    f"{where}: field 'fps' = {file_fps} disagrees with the timestamps "
                    f"(1 / median dt = {motion.fps:.6g}); fix or drop one of them"
                )
        check_motion(motion, where, time_field="timestamps" if "timestamps" in data else "fps")
        return motion


def _write_npz_deterministic(fileobj, arrays: dict) -> None:
    """Like ``np.savez`` (readable by ``np.load``), but with fixed zip timestamps and member order,
    so the same content always gives the same bytes."""
    import io
    import zipfile

    with zipfile.ZipFile(fileobj, mode="w", compression=zipfile.ZIP_STORED) as zf:
        for name in sorted(arrays):
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue())


def _json_default(x):
    if isinstance(x, (np.ndarray, torch.Tensor)):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"Motion.meta value of type {type(x).__name__} is not JSON-serialisable")


def stack_motions(motions: Sequence[Motion]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Batch equal-length motions: (rotmats (B, T, 22, 3, 3), trans (B, T, 3), timestamps (B, T))."""
    motions = list(motions)
    if not motions:
        raise ValueError("stack_motions: no motions given")
    T = motions[0].num_frames
    for i, m in enumerate(motions):
        if m.num_frames != T:
            raise ValueError(
                f"stack_motions: motion {i} ({m.source or 'unnamed'}) has {m.num_frames} frames, "
                f"motion 0 has {T}; cut them to equal length with Motion.window or Motion.resample"
            )
    rot = torch.stack([m.rotmats() for m in motions])
    trans = torch.stack([m.trans for m in motions])
    ts = torch.stack([m.timestamps for m in motions])
    return rot, trans, ts


def joint_positions(motion_or_batch, rest_joints: torch.Tensor) -> torch.Tensor:
    """World joint positions by forward kinematics: FK(rotations, rest_joints) + trans.

    motion_or_batch: a Motion -> returns (T, 22, 3); a list of equal-length Motions or a
    (rotmats (B, T, 22, 3, 3), trans (B, T, 3), ...) tuple -> returns (B, T, 22, 3).
    rest_joints: (22, 3) or, for a batch, (B, 22, 3) T-pose joints at zero translation (metres).
    """
    if isinstance(motion_or_batch, Motion):
        rot, trans = motion_or_batch.rotmats(), motion_or_batch.trans
        rest = rest_joints
    else:
        if isinstance(motion_or_batch, (list, tuple)) and motion_or_batch and isinstance(motion_or_batch[0], Motion):
            rot, trans, _ = stack_motions(motion_or_batch)
        else:
            rot, trans = motion_or_batch[0], motion_or_batch[1]
        rest = rest_joints if rest_joints.dim() == 2 else rest_joints[:, None]
    rest = rest.to(rot)
    if rest.shape[-2:] != (NUM_JOINTS, 3):
        raise ValueError(f"rest_joints must end in ({NUM_JOINTS}, 3), got {tuple(rest_joints.shape)}")
    _, joints = forward_kinematics(rot, rest)
    return joints + trans.to(rot)[..., None, :]


_WARNED_GENDERS: set = set()  # (gender, body name) pairs warned about once


def shape_for_body(motion, body, where: str | None = None):
    """``motion`` with its shape made fit for ``body``: kept when it belongs to this body kind (SMPL,
    SMPL-H and SMPL-X each have their own shape space: betas of one do not carry to another; SMPL
    betas truncated or zero-padded to the body's count); a shape of another body is replaced by the
    neutral shape, with a warning. Betas of a gendered model (``meta["gender"]``, AMASS) on a body of
    another gender are kept, with a warning (once per pair). The length is checked first
    (:func:`benchmark.core.plausibility.check_shape`: an implausible one is an error naming ``where``,
    the motion's file; default its source)."""
    if motion.shape is None:
        return motion
    src = shape_family(motion.body)
    kind = shape_family(str(getattr(body, "model_type", None) or body.name))  # "smplh-female" -> "smplh"
    if src == kind:
        check_shape(motion.shape, where or motion.source or "motion", body.name, kind, body.shape_dim)
        s = motion.shape.reshape(-1)[: body.shape_dim]
        s = torch.cat([s, s.new_zeros(body.shape_dim - s.numel())])
        gender = str((motion.meta or {}).get("gender") or "").lower()
        body_gender = str(body.name).lower().split("-")[-1] if "-" in str(body.name) else ""
        if kind in SMPL_FAMILY and gender in ("male", "female", "neutral") and body_gender and gender != body_gender:
            if (gender, body.name) not in _WARNED_GENDERS:
                _WARNED_GENDERS.add((gender, body.name))
                log.warning("motion %s: its betas are for the %s %s model, the body is %r: the shape is not the "
                            "subject's (give --body %s=PATH:%s for its own model)", where or motion.source, gender,
                            kind.upper(), body.name, kind, gender)
        return replace(motion, shape=s, body=body.name)
    if src in SMPL_FAMILY and kind in SMPL_FAMILY:
        log.warning("motion %s: its %s betas do not apply to body %r (another shape space); using the neutral shape",
                    where or motion.source, src.upper(), body.name)
    else:
        log.info("motion %s: its %s shape does not apply to body %r; using the neutral shape", motion.source, src,
                 body.name)
    return replace(motion, shape=None, body=None)
