"""What a work unit keeps besides its JSON: the fitted motion, for the report's animations.

A unit executor may return ``result["arrays"]``: a dict of numpy arrays. The runner pops it before
validating the JSON result and writes it, atomically, as ``<out_dir>/units/<unit_id>.npz``
(compressed, no pickles) *before* the JSON, so a unit whose JSON exists has its arrays too. The
arrays carry the unit's ``spec_hash``; a reader must check it against the JSON (an ``.npz`` left by
an earlier run of another spec is not this unit's).

Contents written by :func:`fit_arrays` (B sequences, T output frames, n observed frames):

- ``format`` (), ``spec_hash`` (), ``sequence_ids`` (B,) str;
- ``t`` (B, T) float32 seconds from the window start, the output (or anchor) timestamps;
- ``fit_quat`` (B, T, 22, 4) float32 local joint rotations, unit quaternions (x, y, z, w);
  ``fit_trans`` (B, T, 3) float32 metres; ``fit_shape`` (B, S) float32 body shape;
- ``gt_quat``, ``gt_trans``, ``gt_shape``: the ground truth at the same timestamps;
- ``obs_t`` (B, n) float32 observed timestamps; ``obs_points`` (B, n, P, 3) float16, at most
  :data:`MAX_OBS_POINTS` of each observed frame's points (the observations are i.i.d. surface
  samples, so the first P are a uniform subsample); ``obs_lengths`` (B, n) int32 valid points.

Compressed, 60-80 kB per table1 sequence (120 output frames); the report re-skins both bodies from these.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from benchmark.core.json_io import current_umask

FORMAT = 1
MAX_OBS_POINTS = 128
ARRAYS_KEY = "arrays"


def arrays_path(out_dir: str | os.PathLike, unit_id: str) -> Path:
    """``<out_dir>/units/<unit_id>.npz``, beside the unit's JSON."""
    return Path(out_dir) / "units" / f"{unit_id}.npz"


def write_arrays(path: str | os.PathLike, arrays: dict) -> Path:
    """Write ``arrays`` as a compressed ``.npz`` atomically (temp file in the same folder, rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    bad = [k for k, v in arrays.items() if not isinstance(v, np.ndarray) or v.dtype == object]
    if bad:
        raise TypeError(f"unit arrays for {path.name}: entries {bad} are not plain numpy arrays")
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        try:  # the mode a plain open() gives (as the unit's JSON: benchmark.core.json_io), not mkstemp's 0600
            os.fchmod(fd, 0o666 & ~current_umask())
        except (AttributeError, OSError):
            pass
        with os.fdopen(fd, "wb") as fh:
            np.savez_compressed(fh, **arrays)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def read_arrays(path: str | os.PathLike) -> dict:
    """The arrays of a unit's ``.npz`` (loaded into memory; no pickles)."""
    with np.load(path, allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}


def _quat(rotmats) -> np.ndarray:
    import roma
    import torch

    r = torch.as_tensor(rotmats).detach().to("cpu", torch.float64)
    return roma.rotmat_to_unitquat(r).to(torch.float32).numpy()


def ground_truth_pose(body, motions, timestamps):
    """Ground-truth local rotations (B, T, 22, 3, 3), translation (B, T, 3) and shapes (B, S) of
    ``motions`` at absolute ``timestamps`` (B, T): the same resampling that posed the ground truth."""
    import roma
    import torch

    from benchmark.core.motion_posing import resample_stack, stack_shapes

    ts = torch.as_tensor(timestamps, dtype=torch.float64).cpu()
    poses, trans = resample_stack(motions, ts, torch.ones(ts.shape, dtype=torch.bool))
    shapes = stack_shapes(body, motions, None, torch.float32, "cpu")
    return roma.rotvec_to_rotmat(torch.as_tensor(poses, dtype=torch.float64)), torch.as_tensor(trans), shapes


def fit_arrays(unit, t, fit_rot, fit_trans, fit_shape, gt_rot, gt_trans, gt_shape,
               obs_t, obs_points=None, obs_lengths=None) -> dict:
    """The arrays of one unit (see the module docstring). Tensors may live on any device."""
    import torch

    def f32(x):
        return torch.as_tensor(x).detach().to("cpu", torch.float32).numpy()

    B = len(unit.sequence_ids)
    t = torch.as_tensor(t).detach().cpu()
    if t.dim() == 1:
        t = t.expand(B, -1)
    obs_t = torch.as_tensor(obs_t).detach().cpu()
    if obs_t.dim() == 1:
        obs_t = obs_t.expand(B, -1)
    out = {
        "format": np.array(FORMAT), "spec_hash": np.array(unit.spec_hash), "sequence_ids": np.array(list(unit.sequence_ids)),
        "t": f32(t), "fit_quat": _quat(fit_rot), "fit_trans": f32(fit_trans), "fit_shape": f32(fit_shape),
        "gt_quat": _quat(gt_rot), "gt_trans": f32(gt_trans), "gt_shape": f32(gt_shape), "obs_t": f32(obs_t),
    }
    if obs_points is not None:
        pts = torch.as_tensor(obs_points).detach().cpu()[:, :, :MAX_OBS_POINTS]
        lengths = (torch.full(pts.shape[:2], pts.shape[2]) if obs_lengths is None
                   else torch.as_tensor(obs_lengths).cpu().clamp_max(pts.shape[2]))
        out["obs_points"] = pts.to(torch.float16).numpy()
        out["obs_lengths"] = lengths.to(torch.int32).numpy()
    return out
