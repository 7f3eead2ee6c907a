"""AMASS ``.npz`` sequences (SMPL-H ``*_poses.npz`` and SMPL-X ``*_stageii.npz``) -> :class:`Motion`.

What the loader does, in order:

1. Reads ``poses`` (T, 156) SMPL-H / (T, 165) SMPL-X / (T, 72) SMPL (or the split SMPL-X keys
   ``root_orient`` + ``pose_body``), ``trans`` (T, 3), the rate (``mocap_framerate`` in SMPL-H
   releases, ``mocap_frame_rate`` in SMPL-X ones), optional ``betas`` and ``gender`` (0-d str or
   bytes). Keeps root (columns 0:3) + body (3:66) = the 22 SMPL joints; hands, jaw, eyes dropped.
2. Corrects known wrong stored rates from ``frame_rates.yaml`` (versioned data table).
3. Turns AMASS's z-up world into the harness's y-up world with the fixed rotation
   ``R = Rx(-90 deg)``, (x, y, z) -> (x, z, -y): the root orientation becomes ``R @ R_root``.
   Rotating the whole body about the world origin moves the pelvis ``J0 + trans`` to
   ``R (J0 + trans)``, so the new translation is ``R (trans + J0) - J0``. ``J0`` (the rest pelvis
   of the subject's body model) is not in the file: pass ``rest_pelvis`` to make this exact;
   without it the loader uses ``R @ trans`` (error: ``(R - I) J0``, a constant offset of a few
   centimetres for SMPL-H, J0 ~ (0, -0.2, 0) m in z-up) and records that in ``meta``.
4. Optionally resamples to ``fps`` by the exact rate ratio (SLERP; never integer frame skipping).

``shape`` is the file's ``betas`` with ``body`` = "smplh" / "smplx" / "smpl": it belongs to that
body model, not to the harness's default body.
"""

from __future__ import annotations

import fnmatch
import math
import zipfile
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from benchmark.core.frames import Z_UP_TO_Y_UP
from benchmark.core.motion import Motion
from benchmark.core.plausibility import check_motion
from benchmark.core.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from benchmark.core.safe_loading import npz_read_error
from benchmark.core.yaml_io import load_yaml

FRAME_RATE_TABLE = Path(__file__).with_name("frame_rates.yaml")

_RATE_KEYS = ("mocap_framerate", "mocap_frame_rate")
_BODY_BY_WIDTH = {156: "smplh", 165: "smplx", 72: "smpl", 66: None}


@lru_cache(maxsize=8)
def _read_table(path: str) -> tuple[int, tuple[dict, ...]]:
    with open(path) as f:
        doc = load_yaml(f.read(), path)
    if not isinstance(doc, dict) or "version" not in doc or "corrections" not in doc:
        raise ValueError(f"{path}: a frame-rate table needs 'version' and 'corrections' keys")
    entries = []
    for i, e in enumerate(doc["corrections"] or []):
        if not isinstance(e, dict) or "match" not in e or "fps" not in e:
            raise ValueError(f"{path}: correction {i} needs 'match' (glob) and 'fps' keys, got {e!r}")
        if not float(e["fps"]) > 0:
            raise ValueError(f"{path}: correction {i} ({e['match']!r}) has non-positive fps {e['fps']!r}")
        entries.append({"match": str(e["match"]), "fps": float(e["fps"]), "reason": str(e.get("reason", ""))})
    return int(doc["version"]), tuple(entries)


def frame_rate_correction(path, table=FRAME_RATE_TABLE) -> dict | None:
    """The table entry (first match, plus 'table_version') that applies to ``path``, or None."""
    version, entries = _read_table(str(table))
    p = Path(path).as_posix()
    for e in entries:
        if fnmatch.fnmatchcase(p, e["match"]):
            return {**e, "table_version": version, "table": Path(table).name}
    return None


def _text(a) -> str:
    v = np.asarray(a).reshape(-1)[0] if np.asarray(a).size else ""
    return v.decode("utf-8") if isinstance(v, bytes) else str(v)


def is_shape_file(path: str | Path, keys) -> bool:
    """An AMASS subject's shape file (``shape.npz``, ``*_shape.npz``: betas and gender, no poses),
    from its name and its keys (``keys``: the file's field names)."""
    name = Path(path).name
    has_pose = "poses" in keys or ("root_orient" in keys and "pose_body" in keys)
    return name.endswith("_shape.npz") or (not has_pose and (name == "shape.npz" or "betas" in keys))


def load_amass(
    path,
    fps: float | None = None,
    rest_pelvis=None,
    frame_rate_table=FRAME_RATE_TABLE,
) -> Motion:
    """Load one AMASS sequence as a y-up :class:`Motion` (see the module docstring).

    path: an AMASS ``.npz`` (not a ``*_shape.npz``).
    fps: resample to this rate (exact ratio, SLERP); None keeps the (corrected) stored rate.
    rest_pelvis: optional (3,) rest pelvis J0 of the subject's body model (metres, the body
        model's own coordinates, i.e. the pelvis at zero pose and zero trans); makes the
        translation exact (see module docstring).
    frame_rate_table: path of the rate-correction YAML; None disables corrections.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such AMASS file")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as e:
        if zipfile.is_zipfile(path) and isinstance(e, ValueError):
            raise ValueError(f"{path}: cannot read without pickle ({e}); AMASS files hold plain arrays") from e
        raise ValueError(f"{path}: not a readable .npz file ({npz_read_error(path, e)})") from e

    has_pose = "poses" in data or ("root_orient" in data and "pose_body" in data)
    if is_shape_file(path, data):
        raise ValueError(
            f"{path}: this is an AMASS shape file (betas/gender only, no poses); "
            "load the subject's *_poses.npz / *_stageii.npz sequences instead"
        )

    if not has_pose:
        hint = ""
        if "pose" in data or "transl" in data:
            hint = (" (keys 'pose' / 'transl' are not AMASS names: rename them to 'poses' (T, 156) and 'trans' (T, 3), "
                    "or convert the file with the tool that wrote it)")
        raise ValueError(
            f"{path}: no pose data: an AMASS file holds 'poses' (T, 156 / 165 / 72 / 66) or 'root_orient' (T, 3) + "
            f"'pose_body' (T, 63); keys present: {sorted(data)}{hint}"
        )

    def need(key):
        if key not in data:
            raise KeyError(f"{path}: missing key {key!r} (keys present: {sorted(data)})")
        return data[key]

    for key in ("poses", "root_orient", "pose_body", "trans"):
        if key in data and data[key].dtype.kind not in "iuf":  # strings, objects, complex numbers
            raise ValueError(f"{path}: key {key!r} holds {data[key].dtype} values, not real numbers (radians for poses, "
                             "metres for trans); write the numbers (e.g. np.asarray(values, dtype=np.float32))")

    if "poses" in data:
        poses = np.asarray(data["poses"], dtype=np.float64)
        if poses.ndim != 2 or poses.shape[1] not in _BODY_BY_WIDTH:
            raise ValueError(
                f"{path}: key 'poses' has shape {poses.shape}, expected (T, 156) SMPL-H, "
                "(T, 165) SMPL-X, (T, 72) SMPL or (T, 66)"
            )
        body = _BODY_BY_WIDTH[poses.shape[1]]
        pose22 = poses[:, :66]
    else:
        root, body_pose = np.asarray(data["root_orient"], np.float64), np.asarray(data["pose_body"], np.float64)
        if root.ndim != 2 or root.shape[1] != 3 or body_pose.shape != (root.shape[0], 63):
            raise ValueError(
                f"{path}: keys 'root_orient' {root.shape} / 'pose_body' {body_pose.shape} "
                "must be (T, 3) and (T, 63)"
            )
        pose22 = np.concatenate([root, body_pose], axis=1)
        body = "smplx"
    if "surface_model_type" in data:
        body = _text(data["surface_model_type"]).lower() or body
    trans = np.asarray(need("trans"), dtype=np.float64)
    T = pose22.shape[0]
    if trans.shape != (T, 3):
        raise ValueError(f"{path}: key 'trans' has shape {trans.shape}, expected (T, 3) = ({T}, 3)")
    rate_key = next((k for k in _RATE_KEYS if k in data), None)
    if rate_key is None:
        raise KeyError(
            f"{path}: missing key 'mocap_framerate' (SMPL-H) or 'mocap_frame_rate' (SMPL-X) "
            f"(keys present: {sorted(data)})"
        )
    rate_arr = np.asarray(data[rate_key])
    if rate_arr.size != 1 or not np.issubdtype(rate_arr.dtype, np.number):
        raise ValueError(f"{path}: key {rate_key!r} must hold one number (the capture's frames per second), got "
                         f"{rate_arr.dtype} {rate_arr.shape}")
    stored_fps = float(rate_arr.reshape(-1)[0])
    if not (stored_fps > 0 and math.isfinite(stored_fps)):
        raise ValueError(f"{path}: key {rate_key!r} = {stored_fps!r} is not a positive frame rate")

    meta = {
        "format": "amass",
        "file": str(path),
        "body_model": body,
        "stored_fps": stored_fps,
        "up_axis_conversion": "z-up -> y-up, R = Rx(-90 deg): (x, y, z) -> (x, z, -y)",
    }
    if "gender" in data:
        meta["gender"] = _text(data["gender"])
    rate = stored_fps
    if frame_rate_table is not None:
        fix = frame_rate_correction(path, frame_rate_table)
        if fix is not None and abs(fix["fps"] - stored_fps) > 1e-9:
            rate = fix["fps"]
            meta["frame_rate_correction"] = {
                "stored": stored_fps, "corrected": rate, "rule": fix["match"],
                "reason": fix["reason"], "table": fix["table"], "table_version": fix["table_version"],
            }

    R = Z_UP_TO_Y_UP
    aa = torch.from_numpy(pose22).reshape(T, 22, 3)
    root = R @ axis_angle_to_matrix(aa[:, 0])
    aa = torch.cat([matrix_to_axis_angle(root)[:, None], aa[:, 1:]], dim=1)
    tr = torch.from_numpy(trans)
    if rest_pelvis is not None:
        J0 = torch.as_tensor(np.asarray(rest_pelvis, dtype=np.float64)).reshape(-1)
        if J0.shape != (3,):
            raise ValueError(f"rest_pelvis must be a 3-vector (metres), got shape {tuple(J0.shape)}")
        new_trans = (tr + J0) @ R.T - J0
        meta["pelvis_offset_compensated"] = True
    else:
        new_trans = tr @ R.T
        meta["pelvis_offset_compensated"] = False
        meta["pelvis_offset_note"] = (
            "trans rotated as R @ trans; the rest pelvis J0 was unknown, so the body is off by "
            "(R - I) J0 (constant); pass rest_pelvis to make it exact"
        )

    shape = None
    if "betas" in data:
        if not np.issubdtype(np.asarray(data["betas"]).dtype, np.number):
            raise ValueError(f"{path}: key 'betas' must hold the body's shape coefficients (numbers), got "
                             f"{np.asarray(data['betas']).dtype}; remove the key or write the numbers")
        betas = np.asarray(data["betas"], dtype=np.float64).reshape(-1)
        shape = torch.from_numpy(betas).float()
        meta["num_betas"] = int(betas.shape[0])
    timestamps = torch.arange(T, dtype=torch.float64) / rate
    motion = Motion(
        poses=aa.float(), trans=new_trans.float(), timestamps=timestamps,
        shape=shape, body=body if shape is not None else None, source=f"amass:{path}", meta=meta,
    )
    rate_note = f" (corrected by {FRAME_RATE_TABLE.name})" if "frame_rate_correction" in meta else ""
    check_motion(motion, str(path), time_field=rate_key + rate_note,
                 time_fix=f"{rate_key!r} must be the capture rate in frames per second (AMASS: 60-250)",
                 trans_field="trans")
    if fps is not None:
        motion = motion.resample_fps(float(fps))
    return motion
