"""Physical sanity of motions: foot sliding during stance and floor penetration.

:func:`foot_metrics` measures, over a set of motions:

- stance-foot speed: per foot and frame, the foot's lowest point; the foot is in stance when that
  point is within ``contact_height`` of the floor; its speed is the horizontal speed of that same
  point (the same vertex / contact point, central differences over the neighbouring frames), so a
  foot rolling from heel to toe does not count as sliding, a sliding one does. Reported as the
  median (and 90th percentile) over all stance (foot, frame) pairs of all motions, m/s.
- worst floor penetration: the largest depth (m, >= 0) of any point below y = 0 over all frames.

The points are the body's mesh vertices when a body model is given (feet: the vertices skinned
mostly to the ankle and toe joints); otherwise the contact points of the motion's rest skeleton
("joints minus sole heights": the skeleton recorded in a synthetic motion's meta, or the one a
skeleton source gives for the motion's shape).
"""

from __future__ import annotations

from typing import Sequence

import torch

from benchmark.body.lbs import forward_kinematics
from benchmark.core.motion import Motion
from benchmark.core.skeleton import JOINT_INDEX
from benchmark.synthetic.rest import skeleton_from_meta

_DTYPE = torch.float64


def _foot_speeds(points: torch.Tensor, foot_masks: list[torch.Tensor], t: torch.Tensor, contact_height: float):
    """points (T, P, 3); per foot mask (P,) -> stance speeds (n,) over all feet."""
    T = points.shape[0]
    speeds = []
    if T < 2:
        return torch.zeros(0, dtype=_DTYPE)
    nxt = torch.arange(T).add(1).clamp(max=T - 1)
    prv = torch.arange(T).sub(1).clamp(min=0)
    span = (t[nxt] - t[prv])
    for mask in foot_masks:
        foot = points[:, mask]  # (T, Pf, 3)
        low = foot[..., 1].argmin(dim=-1)  # (T,)
        y = foot[torch.arange(T), low, 1]
        stance = y < contact_height
        p_next = foot[nxt, low][:, [0, 2]]
        p_prev = foot[prv, low][:, [0, 2]]
        v = (p_next - p_prev).norm(dim=-1) / span
        speeds.append(v[stance])
    return torch.cat(speeds)


def foot_metrics(motions: Sequence[Motion], body=None, contact_height: float = 0.01, chunk: int = 256) -> dict:
    """Median stance-foot speed (m/s) and worst floor penetration (m) over a set of motions.

    body: a body model (vertices; each motion's ``shape`` is its shape vector), a skeleton source
    (``rest_skeleton(shape)``, e.g. :class:`~benchmark.synthetic.rest.CanonicalSkeletons`), or
    None (each motion's generation skeleton from its meta). See the module docstring.
    """
    motions = list(motions)
    if not motions:
        raise ValueError("foot_metrics: no motions given")
    use_mesh = body is not None and isinstance(body, torch.nn.Module)
    if use_mesh and not hasattr(body, "weights"):
        raise TypeError(
            f"foot_metrics: body {type(body).__name__} has no 'weights' (V, 22) skinning weights to find its "
            "feet; pass a skeleton source (rest_skeleton(shape)) or None (the motions' recorded skeletons)"
        )
    all_speeds, worst, frames = [], 0.0, 0
    for m in motions:
        t = m.timestamps.to(_DTYPE)
        rot = m.rotmats().to(_DTYPE)
        trans = m.trans.to(_DTYPE)
        if use_mesh:
            if m.shape is None:
                raise ValueError(f"foot_metrics: motion {m.source or '?'} has no 'shape'; the body needs one")
            W = body.weights
            masks = [(W[:, JOINT_INDEX[f"{s}_ankle"]] + W[:, JOINT_INDEX[f"{s}_foot"]]) > 0.5 for s in ("left", "right")]
            dtype = W.dtype
            shape = m.shape.to(dtype)[None]
            with torch.no_grad():
                rest = body.prepare(shape)
                pts = []
                for i in range(0, m.num_frames, chunk):
                    out = body(rot[None, i:i + chunk].to(dtype), trans[None, i:i + chunk].to(dtype), rest=rest)
                    pts.append(out.vertices[0].to(_DTYPE))
            points = torch.cat(pts)
        else:
            skeleton = body.rest_skeleton(m.shape.tolist()) if body is not None else skeleton_from_meta(m.meta)
            g_rot, joints = forward_kinematics(rot, skeleton.joints)
            points = skeleton.posed_points(g_rot, joints) + trans[:, None]
            masks = [skeleton.groups == 0, skeleton.groups == 1]
        worst = max(worst, float(-points[..., 1].min()))
        all_speeds.append(_foot_speeds(points, masks, t, contact_height))
        frames += m.num_frames
    speeds = torch.cat(all_speeds)
    q = (lambda p: float(torch.quantile(speeds, p))) if len(speeds) else (lambda p: float("nan"))
    return {
        "median_stance_foot_speed": q(0.5),
        "p90_stance_foot_speed": q(0.9),
        "worst_floor_penetration": max(0.0, worst),
        "stance_samples": int(len(speeds)),
        "frames": int(frames),
        "motions": len(motions),
        "contact_height": contact_height,
        "points": "mesh vertices" if use_mesh else "skeleton contact points",
    }
