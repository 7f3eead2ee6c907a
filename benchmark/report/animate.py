"""From a unit's stored arrays (:mod:`benchmark.data.unit_arrays`) to meshes, errors and animations."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from benchmark.core.fit_diagnostics import root_errors
from benchmark.report.render import render_frames, save_animation


@dataclass
class SequenceMotion:
    """One sequence of a unit, skinned: fitted and ground-truth vertices and joints (T, ., 3)."""

    sequence_id: str
    t: np.ndarray
    fit_vertices: np.ndarray
    fit_joints: np.ndarray
    gt_vertices: np.ndarray
    gt_joints: np.ndarray
    root_err_deg: np.ndarray  # (T,) geodesic angle between fitted and ground-truth root orientations
    facing_err_deg: np.ndarray  # (T,) angle between their horizontal facing directions
    obs_t: np.ndarray
    obs_points: np.ndarray | None
    obs_lengths: np.ndarray | None

    @property
    def backwards(self) -> np.ndarray:
        """(T,) bool: the fit faces more than 90 degrees away from the ground truth."""
        return self.facing_err_deg > 90.0

    @property
    def v2v_mm(self) -> np.ndarray:
        """(T,) mean per-vertex distance between fitted and ground-truth meshes, mm."""
        return np.linalg.norm(self.fit_vertices - self.gt_vertices, axis=-1).mean(-1) * 1000.0


def check_arrays(arrays: dict, unit: dict, source: str) -> str | None:
    """Why ``arrays`` cannot be used for ``unit`` (its JSON), or None."""
    need = ("spec_hash", "sequence_ids", "t", "fit_quat", "fit_trans", "fit_shape", "gt_quat", "gt_trans", "gt_shape")
    missing = [k for k in need if k not in arrays]
    if missing:
        return f"{source}: missing arrays {missing}"
    if str(arrays["spec_hash"]) != unit.get("spec_hash"):
        return f"{source}: its spec_hash differs from the unit JSON's (left by another run of this unit)"
    return None


def quat_to_rotmat(quat: np.ndarray) -> np.ndarray:
    """(..., 3, 3) float64 rotation matrices of (..., 4) unit quaternions (x, y, z, w)."""
    q = np.asarray(quat, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def root_diagnostics(arrays: dict, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Per output frame of sequence ``b``: root-orientation and facing errors (degrees), from the
    stored root rotations alone (no skinning)."""
    return root_errors(quat_to_rotmat(arrays["fit_quat"][b, :, 0]), quat_to_rotmat(arrays["gt_quat"][b, :, 0]))


def _skin(body, quat, trans, shape):
    import roma
    import torch

    with torch.no_grad():
        rot = roma.unitquat_to_rotmat(torch.as_tensor(quat, dtype=torch.float32))
        rest = body.prepare(torch.as_tensor(shape, dtype=torch.float32)[None])
        out = body.skin(rest, rot[None], torch.as_tensor(trans, dtype=torch.float32)[None])
    return out.vertices[0].numpy().astype(np.float64), out.joints[0].numpy().astype(np.float64), rot.numpy().astype(np.float64)


def sequence_motion(arrays: dict, b: int, body, gt_cache: dict | None = None) -> SequenceMotion:
    """Skin sequence ``b`` of a unit's arrays (fit and ground truth) on ``body``.

    ``gt_cache``: a dict shared across units; the ground truth of a sequence at the same
    timestamps is skinned once.
    """
    sid = str(arrays["sequence_ids"][b])
    fit_v, fit_j, fit_r = _skin(body, arrays["fit_quat"][b], arrays["fit_trans"][b], arrays["fit_shape"][b])
    key = (sid, arrays["t"][b].tobytes(), arrays["gt_quat"][b].tobytes(), arrays["gt_trans"][b].tobytes())
    if gt_cache is not None and key in gt_cache:
        gt = gt_cache[key]
    else:
        gt = _skin(body, arrays["gt_quat"][b], arrays["gt_trans"][b], arrays["gt_shape"][b])
        if gt_cache is not None:
            gt_cache.clear() if len(gt_cache) > 16 else None
            gt_cache[key] = gt
    gt_v, gt_j, gt_r = gt
    root_err, facing_err = root_errors(fit_r[:, 0], gt_r[:, 0])
    has_obs = "obs_points" in arrays
    return SequenceMotion(
        sequence_id=sid, t=arrays["t"][b].astype(np.float64), fit_vertices=fit_v, fit_joints=fit_j, gt_vertices=gt_v,
        gt_joints=gt_j, root_err_deg=root_err, facing_err_deg=facing_err,
        obs_t=arrays["obs_t"][b].astype(np.float64) if "obs_t" in arrays else np.zeros(0),
        obs_points=arrays["obs_points"][b] if has_obs else None,
        obs_lengths=arrays["obs_lengths"][b] if has_obs else None,
    )


def animate(motion: SequenceMotion, body, path, title: str = "", size=(150, 200), fps: float | None = None) -> str:
    """Render ``motion`` (front and side) to ``path`` (.webp or .gif), in real time.

    ``fps``: the animation's frame rate: every k-th frame of the motion's own rate (k rounded),
    None: every frame. Each observed frame is drawn on the rendered frame nearest to it.
    """
    from benchmark.core.skeleton import PARENTS

    rate = 1.0 / float(np.median(np.diff(motion.t))) if len(motion.t) > 1 else 30.0
    step = max(1, int(round(rate / fps))) if fps else 1
    i = np.arange(0, len(motion.t), step)
    frames = render_frames(motion.fit_vertices[i], motion.gt_vertices[i], body.faces.cpu().numpy(), motion.gt_joints[i],
                           PARENTS, motion.root_err_deg[i], motion.facing_err_deg[i], motion.t[i], motion.obs_t,
                           motion.obs_points, motion.obs_lengths, size=size, title=title)
    return save_animation(frames, path, rate / step)
