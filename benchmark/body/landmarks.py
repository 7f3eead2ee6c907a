"""Choose the 16 MoCap-style landmark vertices of any body mesh from its T-pose geometry.

Topology-agnostic: the landmarks are found from the T-pose (zero pose) mesh and its 22 SMPL joints
in the project frame (y up, facing +z, left at +x), so the same rule serves SMPL files and the
embedded body. Each landmark except the toes is where a ray from a joint (or a point between
joints) leaves the body surface: among the vertices inside a 45-degree cone around the ray, the
one with the smallest ``|v - o| / cos(angle)^4`` (near the joint and close to the ray's direction:
the surface point straight along the ray). The toes are the front-most vertices of each foot.

    landmark        origin                       direction   anatomical meaning in the T-pose
    head            head joint                   +y          top of the head
    sternum         midpoint spine3 - neck       +z          front of the chest on the midline
    *_shoulder      shoulder joint               +y          top of the shoulder (acromion)
    *_elbow         elbow joint                  +y          lateral epicondyle (palms face down)
    *_wrist         wrist joint                  +z          thumb side of the wrist (radial styloid)
    pelvis_front    pelvis joint                 +z          front of the pelvis on the midline
    pelvis_back     pelvis joint                 -z          back of the pelvis (sacrum)
    *_knee          knee joint                   lateral     lateral femoral epicondyle
    *_ankle         ankle joint                  lateral     lateral malleolus
    *_toe           -                            -           front-most vertex of the foot

Lateral is +x for the left side and -x for the right side.
"""

from __future__ import annotations

import math

import torch

from benchmark.core.skeleton import JOINT_INDEX, LANDMARK_NAMES, NUM_JOINTS

_X, _Y, _Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)


def _neg(d):
    return tuple(-c for c in d)


# landmark -> (origin joints averaged, ray direction); the toes are handled separately.
LANDMARK_RAYS: dict[str, tuple[tuple[str, ...], tuple[float, float, float]]] = {
    "head": (("head",), _Y),
    "sternum": (("spine3", "neck"), _Z),
    "left_shoulder": (("left_shoulder",), _Y),
    "right_shoulder": (("right_shoulder",), _Y),
    "left_elbow": (("left_elbow",), _Y),
    "right_elbow": (("right_elbow",), _Y),
    "left_wrist": (("left_wrist",), _Z),
    "right_wrist": (("right_wrist",), _Z),
    "pelvis_front": (("pelvis",), _Z),
    "pelvis_back": (("pelvis",), _neg(_Z)),
    "left_knee": (("left_knee",), _X),
    "right_knee": (("right_knee",), _neg(_X)),
    "left_ankle": (("left_ankle",), _X),
    "right_ankle": (("right_ankle",), _neg(_X)),
}
# Score exponent on the cosine: 1 would let the side of a head whose joint sits low in it win over
# the top (side at 45 degrees and 0.10 m against top at 0.15 m, Anny's head); 4 makes the angle count.
ANGLE_PENALTY = 4.0
TOES = {"left_toe": ("left_ankle", 1.0), "right_toe": ("right_ankle", -1.0)}  # ankle joint, side sign on x


def ray_exit_vertices(
    vertices: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor, cone_degrees: float = 45.0
) -> torch.Tensor:
    """For each ray, the vertex where it leaves the surface.

    vertices (V, 3); origins (R, 3); directions (R, 3) (normalised here).
    Among the vertices within ``cone_degrees`` of each ray, returns (R,) long the index minimising
    ``|v - o| / cos(angle)^ANGLE_PENALTY``. A ray whose cone holds no vertex (a sparse or odd mesh) is retried
    with the cone widened to 60, 75 and 85 degrees; if still empty, ValueError names the ray.
    """
    d = directions / directions.norm(dim=-1, keepdim=True)
    rel = vertices[None, :, :] - origins[:, None, :]  # (R, V, 3)
    dist = rel.norm(dim=-1)
    cos = (rel * d[:, None, :]).sum(-1) / dist.clamp_min(1e-12)  # (R, V) cosine of the angle to the ray
    raw_score = dist / cos.clamp_min(1e-6).pow(ANGLE_PENALTY)
    best = torch.full((len(origins),), -1, dtype=torch.long, device=vertices.device)
    for degrees in sorted({cone_degrees, max(cone_degrees, 60.0), max(cone_degrees, 75.0), max(cone_degrees, 85.0)}):
        inside = cos > math.cos(math.radians(degrees))
        score = torch.where(inside, raw_score, torch.full_like(dist, math.inf))
        todo = (best < 0) & inside.any(dim=-1)
        best = torch.where(todo, score.argmin(dim=-1), best)
    if (best < 0).any():
        bad = (best < 0).nonzero().flatten().tolist()
        raise ValueError(f"no mesh vertex within 85 degrees of ray(s) {bad}; is the mesh in the T-pose?")
    return best


def select_landmarks(vertices: torch.Tensor, joints: torch.Tensor, cone_degrees: float = 45.0) -> torch.Tensor:
    """The 16 landmark vertex indices, in ``LANDMARK_NAMES`` order, of a T-pose mesh.

    vertices: (V, 3) T-pose (zero pose) mesh in metres, y up, facing +z, left at +x.
    joints: (22, 3) its SMPL joints (``benchmark.core.skeleton.JOINT_NAMES`` order).
    Returns a (16,) long tensor on the vertices' device. See the module docstring for the rules.
    """
    vertices = torch.as_tensor(vertices)
    joints = torch.as_tensor(joints).to(vertices)
    if vertices.dim() != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {tuple(vertices.shape)}")
    if joints.shape != (NUM_JOINTS, 3):
        raise ValueError(f"joints must be ({NUM_JOINTS}, 3), got {tuple(joints.shape)}")
    ray_names = list(LANDMARK_RAYS)
    origins = torch.stack(
        [joints[[JOINT_INDEX[j] for j in LANDMARK_RAYS[n][0]]].mean(0) for n in ray_names]
    )
    directions = torch.tensor([LANDMARK_RAYS[n][1] for n in ray_names]).to(vertices)
    try:
        found = ray_exit_vertices(vertices, origins, directions, cone_degrees)
    except ValueError as exc:
        raise ValueError(f"select_landmarks: {exc} (rays: {ray_names})") from exc
    index = dict(zip(ray_names, found.tolist()))

    midline_x = joints[JOINT_INDEX["pelvis"], 0]
    for name, (ankle, side) in TOES.items():
        foot = (vertices[:, 1] < joints[JOINT_INDEX[ankle], 1]) & ((vertices[:, 0] - midline_x) * side > 0)
        if not foot.any():
            raise ValueError(f"select_landmarks: no vertex below the {ankle} joint on its side for {name!r}")
        z = torch.where(foot, vertices[:, 2], torch.full_like(vertices[:, 2], -math.inf))
        index[name] = int(z.argmax())
    return torch.tensor([index[n] for n in LANDMARK_NAMES], dtype=torch.long, device=vertices.device)
