"""The subject's rest skeleton and ground-contact points, the generator's only body input.

A :class:`RestSkeleton` holds the T-pose joints (22, 3) at zero translation (feet on y = 0) and a
set of contact points on the feet and hands (the points that may touch the floor), each skinned
to the joints like a mesh vertex. Two ways to make one:

- :meth:`RestSkeleton.from_joints`: from rest joints plus the heights of the sole below the ankle
  and the toe joints (a box-shaped foot and a flat hand are laid out from the bone lengths);
  this is what the generator uses without a mesh, and what ``foot_metrics`` uses for
  "joints minus sole heights".
- :meth:`RestSkeleton.from_body`: from a body model's T-pose mesh: the convex-hull and sole
  vertices of the feet and hands, with the body's own skinning weights, so the generator's floor
  contact is the mesh's.

Units: metres. World frame y up, facing +z, left at +x.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import torch

from benchmark.core.skeleton import JOINT_INDEX, NUM_JOINTS

_DTYPE = torch.float64

# Contact groups (index into RestSkeleton.groups).
GROUPS = ("left_foot", "right_foot", "left_hand", "right_hand")
FOOT_GROUPS = (0, 1)

# SMPL-like T-pose (metres, y up, facing +z, left at +x), stature about 1.72 m: pelvis 0.93 m
# high, hips at +-0.09 m, legs straight down, arms along +-x. Used for tests and when no body
# model is at hand; scaled uniformly by CanonicalSkeletons for other statures.
CANONICAL_STATURE = 1.72
CANONICAL_JOINTS = (
    (0.0, 0.930, 0.000),    # pelvis
    (0.090, 0.860, 0.000),  # left_hip
    (-0.090, 0.860, 0.000),  # right_hip
    (0.0, 1.040, -0.020),   # spine1
    (0.090, 0.480, 0.000),  # left_knee
    (-0.090, 0.480, 0.000),  # right_knee
    (0.0, 1.180, -0.010),   # spine2
    (0.090, 0.080, 0.000),  # left_ankle
    (-0.090, 0.080, 0.000),  # right_ankle
    (0.0, 1.240, 0.000),    # spine3
    (0.090, 0.030, 0.130),  # left_foot
    (-0.090, 0.030, 0.130),  # right_foot
    (0.0, 1.460, -0.010),   # neck
    (0.080, 1.380, -0.005),  # left_collar
    (-0.080, 1.380, -0.005),  # right_collar
    (0.0, 1.560, 0.030),    # head
    (0.180, 1.410, -0.010),  # left_shoulder
    (-0.180, 1.410, -0.010),  # right_shoulder
    (0.440, 1.410, -0.010),  # left_elbow
    (-0.440, 1.410, -0.010),  # right_elbow
    (0.690, 1.410, -0.010),  # left_wrist
    (-0.690, 1.410, -0.010),  # right_wrist
)
CANONICAL_ANKLE_SOLE = 0.080  # sole below the ankle joint, metres
CANONICAL_TOE_SOLE = 0.030  # sole below the toe (SMPL "foot") joint, metres


@dataclass
class RestSkeleton:
    """Rest joints and skinned contact points of one subject.

    joints: (22, 3) T-pose joint positions at zero translation, metres (feet on y = 0).
    points: (K, M, 3) contact point k as seen by its m-th influencing joint in the T-pose (for a
        mesh with per-joint pre-transforms these differ; otherwise all M rows are the point).
    joint_index: (K, M) long, the influencing joints; weights: (K, M) their weights (rows sum to 1).
    groups: (K,) long, index into GROUPS.
    ankle_sole, toe_sole: heights (m) of the sole below the ankle / toe joints in the T-pose.
    source: where it came from ("canonical", "anny", ...).
    """

    joints: torch.Tensor
    points: torch.Tensor
    joint_index: torch.Tensor
    weights: torch.Tensor
    groups: torch.Tensor
    ankle_sole: float
    toe_sole: float
    source: str

    def __post_init__(self):
        self.joints = torch.as_tensor(self.joints, dtype=_DTYPE)
        if self.joints.shape != (NUM_JOINTS, 3):
            raise ValueError(f"RestSkeleton: field 'joints' must be (22, 3), got {tuple(self.joints.shape)}")
        K = self.points.shape[0]
        if self.points.dim() != 3 or self.joint_index.shape != self.points.shape[:2] or self.weights.shape != self.points.shape[:2]:
            raise ValueError(
                "RestSkeleton: 'points' (K, M, 3), 'joint_index' (K, M) and 'weights' (K, M) disagree: "
                f"{tuple(self.points.shape)}, {tuple(self.joint_index.shape)}, {tuple(self.weights.shape)}"
            )
        if self.groups.shape != (K,):
            raise ValueError(f"RestSkeleton: field 'groups' must be (K,) = ({K},), got {tuple(self.groups.shape)}")

    # ------------------------------------------------------------------ posing
    def posed_points(self, global_rot: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
        """Contact points (..., K, 3) for FK output global_rot (..., 22, 3, 3), joints (..., 22, 3).

        Linear blend skinning of each point over its influencing joints:
        p_k = sum_m w_km (G_j (q_km - J_j) + P_j) with j = joint_index[k, m], evaluated joint by
        joint (one matrix product per influencing joint, batched over all time samples).
        """
        if self.joint_index.numel() <= 64:  # few points: gather the joints' transforms per point
            G = global_rot[..., self.joint_index, :, :]  # (..., K, M, 3, 3)
            local = (self.points - self.joints[self.joint_index]).to(global_rot)  # (K, M, 3)
            p = (G @ local[..., None])[..., 0] + joints[..., self.joint_index, :]
            return (p * self.weights.to(p)[..., None]).sum(-2)
        batch = global_rot.shape[:-3]
        out = global_rot.new_zeros(*batch, self.points.shape[0], 3)
        flat_out = out.reshape(-1, *out.shape[-2:])
        G = global_rot.reshape(-1, *global_rot.shape[-3:])
        P = joints.reshape(-1, *joints.shape[-2:])
        for j, k_idx, local, w in self._by_joint():
            contrib = (G[:, j] @ local.to(G).T).transpose(-1, -2) + P[:, j, None, :]  # (B, n, 3)
            flat_out.index_add_(1, k_idx, contrib * w.to(G)[:, None])
        return flat_out.reshape(*batch, *out.shape[-2:])

    def _by_joint(self):
        """Per influencing joint: (joint, point indices (n,), local offsets (n, 3), weights (n,))."""
        if getattr(self, "_groups_cache", None) is None:
            groups = []
            for j in torch.unique(self.joint_index).tolist():
                k, m = torch.nonzero((self.joint_index == j) & (self.weights > 0), as_tuple=True)
                if len(k):
                    groups.append((j, k, self.points[k, m] - self.joints[j], self.weights[k, m]))
            self._groups_cache = groups
        return self._groups_cache

    # ------------------------------------------------------------------ provenance
    def rest_points(self) -> torch.Tensor:
        """(K, 3) the contact points in the T-pose (the skinned blend of their per-joint copies)."""
        return (self.points * self.weights[..., None]).sum(1)

    def to_meta(self, max_points_per_group: int = 24) -> dict:
        """JSON-friendly record of the skeleton: rest joints, sole heights and a subset of the
        contact points (at most ``max_points_per_group`` per foot / hand, spread by farthest-point
        sampling over the points below the ankle for the feet), each rigid with its main joint;
        :func:`skeleton_from_meta` rebuilds a skeleton from it (foot_metrics does)."""
        rest = self.rest_points()
        main = self.joint_index.gather(1, self.weights.argmax(1, keepdim=True))[:, 0]
        keep = []
        for g in range(len(GROUPS)):
            ids = torch.nonzero(self.groups == g).flatten()
            if g in FOOT_GROUPS:
                ankle_y = float(self.joints[JOINT_INDEX[("left", "right")[g] + "_ankle"], 1])
                low = ids[rest[ids, 1] < ankle_y]
                ids = low if len(low) else ids
            keep += _farthest_points(rest[ids], max_points_per_group, ids)
        keep = sorted(keep)
        return {
            "source": self.source,
            "rest_joints": [[round(float(x), 6) for x in row] for row in self.joints.tolist()],
            "ankle_sole_height": round(float(self.ankle_sole), 6),
            "toe_sole_height": round(float(self.toe_sole), 6),
            "num_contact_points": int(self.points.shape[0]),
            "contact_points": [[round(float(x), 5) for x in rest[k].tolist()] + [int(main[k]), int(self.groups[k])]
                               for k in keep],
        }

    def digest(self) -> str:
        """sha256 of the joints and contact points (float64 bytes): changes iff the skeleton does."""
        h = hashlib.sha256()
        for t in (self.joints, self.points, self.weights):
            h.update(np.ascontiguousarray(t.detach().cpu().numpy().astype(np.float64)).tobytes())
        h.update(np.ascontiguousarray(self.joint_index.cpu().numpy().astype(np.int64)).tobytes())
        return h.hexdigest()

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_joints(cls, joints, ankle_sole: float, toe_sole: float, source: str = "joints") -> RestSkeleton:
        """Contact points laid out from T-pose joints (22, 3) and the sole heights (m).

        Each foot: a sole of heel, mid-foot and ball points rigid with the ankle, and toe-tip
        points rigid with the toe joint, all on the sole plane (ankle height - ankle_sole at the
        heel, toe height - toe_sole at the ball); lengths and widths in proportion to the
        ankle-to-toe-joint distance d (heel 0.42 d behind the ankle, toe tip 0.42 d beyond the toe
        joint, as on the embedded body). Each hand: palm and fingertip points rigid with the
        wrist, continuing the forearm (the hand about 0.75 of the forearm's length).
        """
        J = torch.as_tensor(joints, dtype=_DTYPE)
        if J.shape != (NUM_JOINTS, 3):
            raise ValueError(f"RestSkeleton.from_joints: joints must be (22, 3), got {tuple(J.shape)}")
        if not (0.0 <= ankle_sole < 0.3 and 0.0 <= toe_sole < 0.3):
            raise ValueError(
                f"RestSkeleton.from_joints: sole heights must be in [0, 0.3) m, got ankle {ankle_sole}, toe {toe_sole}"
            )
        pts, idx, grp = [], [], []
        for g, side in enumerate(("left", "right")):
            a = J[JOINT_INDEX[f"{side}_ankle"]]
            f = J[JOINT_INDEX[f"{side}_foot"]]
            d = max(float((f[[0, 2]] - a[[0, 2]]).norm()), 0.05)  # ankle -> toe joint, horizontal
            ya, yf = float(a[1]) - ankle_sole, float(f[1]) - toe_sole
            ja, jf = JOINT_INDEX[f"{side}_ankle"], JOINT_INDEX[f"{side}_foot"]
            az, fz = float(a[2]), float(f[2])
            for dx, y, z, j in (
                (-0.28, ya, az - 0.42 * d, ja), (0.28, ya, az - 0.42 * d, ja),  # heel
                (-0.32, ya, az + 0.15 * d, ja), (0.32, ya, az + 0.15 * d, ja),  # mid-foot
                (-0.35, yf, fz, ja), (0.35, yf, fz, ja),  # ball
                (-0.27, yf, fz + 0.3 * d, jf), (0.27, yf, fz + 0.3 * d, jf),  # toes
                (0.0, yf, fz + 0.42 * d, jf),  # big-toe tip
            ):
                pts.append((float(a[0]) + dx * d, y, z))
                idx.append(j)
                grp.append(g)
        for g, side in ((2, "left"), (3, "right")):
            w = J[JOINT_INDEX[f"{side}_wrist"]]
            e = J[JOINT_INDEX[f"{side}_elbow"]]
            fl = max(float((w - e).norm()), 0.1)  # forearm length: the hand is ~0.75 of it
            u = (w - e) / (w - e).norm()
            side_axis = torch.tensor([0.0, 0.0, 1.0], dtype=_DTYPE)
            up = torch.linalg.cross(side_axis, u)
            up = up / up.norm() * torch.sign(up[1] + 1e-12)  # the world-up-ish palm normal
            jw = JOINT_INDEX[f"{side}_wrist"]
            for along, across, thick in (
                (0.28, -0.18, -0.06), (0.28, 0.18, -0.06), (0.28, -0.18, 0.08), (0.28, 0.18, 0.08),
                (0.48, -0.16, -0.05), (0.48, 0.16, -0.05), (0.48, 0.0, 0.07),
                (0.72, -0.1, 0.0), (0.72, 0.1, 0.0), (0.76, 0.0, 0.0),
            ):
                p = w + (u * along + side_axis * across + up * thick) * fl
                pts.append(tuple(p.tolist()))
                idx.append(jw)
                grp.append(g)
        K = len(pts)
        return cls(
            joints=J,
            points=torch.tensor(pts, dtype=_DTYPE)[:, None, :],
            joint_index=torch.tensor(idx, dtype=torch.long)[:, None],
            weights=torch.ones(K, 1, dtype=_DTYPE),
            groups=torch.tensor(grp, dtype=torch.long),
            ankle_sole=float(ankle_sole),
            toe_sole=float(toe_sole),
            source=source,
        )

    @classmethod
    def from_body(cls, body, shape: torch.Tensor, source: str | None = None) -> RestSkeleton:
        """Contact points from a body model's T-pose mesh for one shape (S,).

        The feet are the vertices skinned mostly to the ankle and toe joints, the hands those
        skinned mostly to the wrist; their convex-hull vertices (which hold the lowest point in
        any orientation) and their sole/palm vertices become the contact points, with the body's
        skinning weights (``body.weights`` (V, 22)) and per-joint pre-transforms when it has them.
        """
        if not hasattr(body, "weights"):
            raise TypeError(
                f"RestSkeleton.from_body: body {type(body).__name__} has no 'weights' (V, 22) skinning "
                "weights buffer; use RestSkeleton.from_joints with its rest joints and sole heights instead"
            )
        from scipy.spatial import ConvexHull

        shape = torch.as_tensor(shape).reshape(1, -1).to(body.weights.dtype)
        with torch.no_grad():
            rest = body.prepare(shape)
            eye = torch.eye(3, dtype=body.weights.dtype).expand(1, 1, NUM_JOINTS, 3, 3)
            tpose = body(eye, torch.zeros(1, 1, 3, dtype=body.weights.dtype), rest=rest).vertices[0, 0]
        joints = rest.joints[0].to(_DTYPE)
        V = tpose.to(_DTYPE)
        W = body.weights.to(_DTYPE)
        if rest.pre_transforms is not None:
            A = rest.pre_transforms[0].to(_DTYPE)  # (22, 3, 4): rest vertex -> T-pose, per joint
            base = rest.vertices[0].to(_DTYPE)
        else:
            A, base = None, None
        floor = float(V[:, 1].min())
        regions = []
        for g, side in enumerate(("left", "right")):
            ja, jf = JOINT_INDEX[f"{side}_ankle"], JOINT_INDEX[f"{side}_foot"]
            mask = (W[:, ja] + W[:, jf]) > 0.5
            sole = mask & (V[:, 1] < floor + 0.015)
            regions.append((g, mask, sole))
        for g, side in ((2, "left"), (3, "right")):
            jw = JOINT_INDEX[f"{side}_wrist"]
            mask = W[:, jw] > 0.5
            regions.append((g, mask, torch.zeros_like(mask)))
        vid, grp = [], []
        for g, mask, extra in regions:
            ids = torch.nonzero(mask).flatten()
            if len(ids) < 8:
                raise ValueError(
                    f"RestSkeleton.from_body: the {GROUPS[g]} region of body {getattr(body, 'name', '?')} has "
                    f"{len(ids)} vertices; its skinning weights do not single out the feet and hands"
                )
            hull = ConvexHull(V[ids].numpy()).vertices
            keep = set(ids[torch.as_tensor(hull)].tolist()) | set(torch.nonzero(extra).flatten().tolist())
            keep = sorted(keep)
            vid += keep
            grp += [g] * len(keep)
        vid_t = torch.tensor(vid, dtype=torch.long)
        w = W[vid_t]  # (K, 22)
        M = int((w > 1e-6).sum(-1).max())
        top_w, top_j = w.topk(M, dim=-1)
        top_w = top_w / top_w.sum(-1, keepdim=True)
        if A is not None:  # per-joint T-pose position of the vertex: A_j v_rest
            vb = base[vid_t]  # (K, 3)
            Aj = A[top_j]  # (K, M, 3, 4)
            pts = (Aj[..., :3] @ vb[:, None, :, None])[..., 0] + Aj[..., 3]
        else:
            pts = V[vid_t][:, None, :].expand(-1, M, -1).clone()
        ankle_sole = float(joints[JOINT_INDEX["left_ankle"], 1] - floor)
        toe_sole = float(joints[JOINT_INDEX["left_foot"], 1] - floor)
        return cls(
            joints=joints - torch.tensor([0.0, floor, 0.0], dtype=_DTYPE),
            points=pts - torch.tensor([0.0, floor, 0.0], dtype=_DTYPE),
            joint_index=top_j,
            weights=top_w,
            groups=torch.tensor(grp, dtype=torch.long),
            ankle_sole=ankle_sole,
            toe_sole=toe_sole,
            source=source or getattr(body, "name", type(body).__name__),
        )


def approximate_stature(phenotype) -> float:
    """Rough standing height (m) of an Anny phenotype [gender, age, muscle, weight, height,
    proportions], fitted to the embedded Anny body at adult ages (within about 2 cm for
    age 0.6-0.8); only used to scale the canonical skeleton when no body model is given."""
    g, age, _, _, h, _ = (float(x) for x in phenotype)
    stature = 1.86 - 0.14 * g + 1.08 * (h - 0.45)
    if age < 0.67:
        stature -= 1.2 * (0.67 - age)
    return stature


class CanonicalSkeletons:
    """Skeleton source without a body model: the canonical skeleton scaled to each subject's
    approximate stature (:func:`approximate_stature`). Fast; for tests and quick previews."""

    name = "canonical"

    def rest_skeleton(self, phenotype) -> RestSkeleton:
        s = approximate_stature(phenotype) / CANONICAL_STATURE
        joints = torch.tensor(CANONICAL_JOINTS, dtype=_DTYPE) * s
        return RestSkeleton.from_joints(joints, CANONICAL_ANKLE_SOLE * s, CANONICAL_TOE_SOLE * s, source="canonical")


class BodySkeletons:
    """Skeleton source from a body model's mesh (see :meth:`RestSkeleton.from_body`), cached per shape."""

    def __init__(self, body):
        self.body = body
        self.name = getattr(body, "name", type(body).__name__)
        self._cache: dict = {}

    def rest_skeleton(self, phenotype) -> RestSkeleton:
        """The skeleton of the body at ``phenotype``, computed on one torch thread whatever the
        caller's count: a CPU matrix product's bits depend on the thread count (up to 2e-7 m here),
        and the synthetic splits are keyed by these bits (``skeleton_digest``), so a process on two
        threads and a worker on one would otherwise rebuild each other's split and see motions
        that differ in their last bits."""
        key = tuple(round(float(x), 9) for x in phenotype)
        if key not in self._cache:
            threads = torch.get_num_threads()
            torch.set_num_threads(1)
            try:
                self._cache[key] = RestSkeleton.from_body(self.body, torch.tensor(key), source=self.name)
            finally:
                torch.set_num_threads(threads)
        return self._cache[key]


def skeleton_source(body):
    """A BodyModel, a skeleton source (anything with ``rest_skeleton(phenotype)``) or None (the
    embedded Anny body) -> a skeleton source."""
    if body is None:
        from benchmark.body.anny_body import load_anny_body

        body = load_anny_body("cpu")
    if hasattr(body, "rest_skeleton") and callable(getattr(body, "rest_skeleton")):
        return body
    if isinstance(body, torch.nn.Module):
        return BodySkeletons(body)
    raise TypeError(
        f"expected a body model (benchmark.body), a skeleton source with rest_skeleton(phenotype) "
        f"(e.g. benchmark.synthetic.rest.CanonicalSkeletons()) or None, got {type(body).__name__}"
    )


def skeleton_from_meta(meta: dict) -> RestSkeleton:
    """Rebuild the generation skeleton recorded in a synthetic Motion's meta["skeleton"]: its rest
    joints with the recorded contact points (rigid with their main joint), or, for a record
    without them, the points :meth:`RestSkeleton.from_joints` lays out from the sole heights."""
    sk = meta.get("skeleton") if isinstance(meta, dict) else None
    if not sk or "rest_joints" not in sk:
        raise KeyError(
            "motion meta has no 'skeleton' record with 'rest_joints'; it was not made by the synthetic "
            "generator: pass a body model (or a skeleton source) to foot_metrics instead"
        )
    joints = torch.tensor(sk["rest_joints"], dtype=_DTYPE)
    if not sk.get("contact_points"):
        return RestSkeleton.from_joints(joints, sk["ankle_sole_height"], sk["toe_sole_height"],
                                        source=sk.get("source", "meta"))
    cp = torch.tensor(sk["contact_points"], dtype=_DTYPE)
    return RestSkeleton(
        joints=joints, points=cp[:, None, :3], joint_index=cp[:, 3:4].long(), weights=torch.ones(len(cp), 1, dtype=_DTYPE),
        groups=cp[:, 4].long(), ankle_sole=sk["ankle_sole_height"], toe_sole=sk["toe_sole_height"],
        source=f"meta:{sk.get('source', '?')}",
    )


def _farthest_points(points: torch.Tensor, n: int, ids: torch.Tensor) -> list[int]:
    """Up to n of ``ids`` spread over ``points`` (m, 3) by farthest-point sampling, starting
    from the lowest point (deterministic)."""
    if len(ids) <= n:
        return ids.tolist()
    chosen = [int(points[:, 1].argmin())]
    dist = (points - points[chosen[0]]).norm(dim=-1)
    while len(chosen) < n:
        k = int(dist.argmax())
        chosen.append(k)
        dist = torch.minimum(dist, (points - points[k]).norm(dim=-1))
    return [int(ids[k]) for k in chosen]
