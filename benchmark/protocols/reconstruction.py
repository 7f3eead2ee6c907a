"""The reconstruction table (docs/protocol.md, "reconstruction"; HM-VAE, Li et al. 2021, Table 3).

Data: clean windows (the grid's ``window``, seconds; 2 s) at 30 fps of the test motions
(:class:`benchmark.protocols.motion_fit.MotionSource`), ground truth posed on the body with each
motion's own shape, fixed (never optimised).

Each prior with an encoder (``has_encoder`` and ``encode_motion``) encodes the clean motion (local
rotations, root included, translation, timestamps from the window start: the posterior mean) and
its latents are decoded at the same 30 fps frames (:func:`benchmark.protocols.fit_state.body_parameters`:
per-frame, fixed-window and continuous priors alike). What the prior does not encode comes from the
ground truth: root orientation (per frame: the ground-truth root), translation (per frame: the
ground-truth translation); a heading-normalised decoder gets the mean yaw between the ground-truth
and the decoded root, a decoder of translation the mean offset between the ground-truth and the
decoded translation (:func:`benchmark.protocols.motion_fit.set_rigid_from_observation`). No
optimisation. Priors without an encoder are n/a ("no encoder").

Metrics (sums over the window's frames; the table divides by frames): ``mpjpe_local_m`` (version 3's
headline: the joints relative to the pelvis, the local pose of VIBE's metrics that the paper's
Table 3 uses), ``mpjpe_m`` (world coordinates), ``pa_mpjpe_m``, ``v2v_m``, ``accel_mps2`` /
``gt_accel_mps2`` (mean joint acceleration magnitude of the pelvis-centred joints of the output /
the ground truth, m/s^2, as VIBE's; ``accel`` is judged by its distance to ``gt_accel``), ``accer_mps2``
(acceleration error, m/s^2); the acceleration metrics are the sequence means times its frame count
(version 3; versions 1-2 named them ``accel``, ``gt_accel``, ``accer``). ``root_m`` (only for priors
that encode translation; n/a for the others, whose root is the ground truth's): the distance between the
ground-truth root joint (pelvis) per frame (after the table's rigid alignment: the decoded root
path's shape, not its mean offset); ``gt_travel_m``: the ground-truth root's path length over the
window, times the frame count (so that the table shows the travel itself). The per-sequence ratio
``root_m / gt_travel_m`` is what "the decoded root path follows the ground truth's within x % of the
distance travelled" means (:func:`root_path_errors`).
"""

from __future__ import annotations

import time

import torch

from benchmark.metrics.pose import acceleration_error, mean_acceleration, mpjpe, pa_mpjpe
from benchmark.protocols.motion_fit import (
    MotionSource, MotionTargets, Timer, decode_parameters, init_motion_state, is_interpolation_baseline,
    joints_of, load_table_motions, pelvis_centred, tensor_fingerprint, unit_result, v2v_sums,
)
from priors.base import has_motion_encoder

ROOT_FROM_GROUND_TRUTH = "the prior encodes no translation: its root path is the ground truth's, given to it"

NO_ENCODER = "no encoder: the prior cannot encode a motion (has_encoder is False or encode_motion is missing)"


def root_path_errors(joints: torch.Tensor, gt_joints: torch.Tensor) -> tuple[list[float], list[float]]:
    """joints, gt_joints (B, T, J, 3), root first -> (mean root distance per sequence (B,), m;
    the ground-truth root's path length per sequence (B,), m)."""
    root, gt = joints[..., 0, :].double(), gt_joints[..., 0, :].double()
    err = (root - gt).norm(dim=-1).mean(-1)
    travel = (gt[:, 1:] - gt[:, :-1]).norm(dim=-1).sum(-1)
    return err.tolist(), travel.tolist()


# -- the protocol interface (benchmark.protocols.base.Protocol; wrapped by benchmark.protocols.builtin) --
def load_motions(spec: dict, data, body) -> dict:
    windows = [float(w) for w in (spec.get("grid") or {}).get("window", [])]
    return load_table_motions(spec, data, body, longest_window_s=max(windows) if windows else None)


def make_source(spec: dict, body, motions_by_id: dict, seed: int) -> MotionSource:
    return MotionSource(spec, body, motions_by_id, seed)


def na_reason(spec: dict, adapter) -> str | None:
    if is_interpolation_baseline(adapter):
        return "the SLERP baseline belongs to the in-betweening table (its encode/decode is the identity)"
    if not has_motion_encoder(adapter):
        return NO_ENCODER
    return None


def run_unit(unit, spec: dict, profile: dict, adapter, body, source: MotionSource, device) -> dict:
    window = float(unit.cell.get("window", source.window_s))
    ids = list(unit.sequence_ids)
    clean = source.clean(ids, window)
    B, T = clean.rotations.shape[:2]
    targets = MotionTargets(timestamps=clean.timestamps, shapes=clean.shapes, window_s=window, joints=clean.joints,
                            init_rotations=clean.rotations, init_trans=clean.trans)
    fp = tensor_fingerprint(timestamps=clean.timestamps, rotations=clean.rotations, trans=clean.trans,
                            shapes=clean.shapes)
    g = torch.Generator().manual_seed(unit.seed)
    timer = Timer(device)
    with timer:
        with torch.no_grad():
            latents = adapter.encode_motion(clean.rotations, clean.trans, clean.timestamps)
    state = init_motion_state(adapter, body, targets, g, device, latents=latents)  # rigid: ground truth
    with timer:
        rot, trans = decode_parameters(state, clean.timestamps)
    t_eval = time.perf_counter()
    joints = joints_of(body, clean.shapes, rot, trans)
    fps = clean.fps
    local, gt_local = pelvis_centred(joints), pelvis_centred(clean.joints)  # the paper's (VIBE's) local pose
    err_local = mpjpe(local, gt_local, reduction="sum")
    err = mpjpe(joints, clean.joints, reduction="sum")
    pa = pa_mpjpe(joints, clean.joints, reduction="sum")
    v2v = v2v_sums(body, clean.shapes, rot, trans, clean.rotations, clean.trans)
    accel = mean_acceleration(local, fps)
    gt_accel = mean_acceleration(gt_local, fps)
    accer = acceleration_error(local, gt_local, fps)
    root, travel = root_path_errors(joints, clean.joints)
    per_seq = [
        {"frames": T, "sums": {"mpjpe_local_m": err_local[b], "mpjpe_m": err[b], "pa_mpjpe_m": pa[b], "v2v_m": v2v[b], "accel_mps2": accel[b] * T,
                               "gt_accel_mps2": gt_accel[b] * T, "accer_mps2": accer[b] * T,
                               "gt_travel_m": travel[b] * T}}
        for b in range(B)
    ]
    for b, row in enumerate(per_seq):
        if getattr(adapter, "encodes_translation", False):
            row["sums"]["root_m"] = root[b] * T
        else:  # its root is the ground truth's by construction (version 3; versions 1-2 showed 0.0 mm)
            row["na"] = {"root_m": ROOT_FROM_GROUND_TRUTH}
    eval_s = time.perf_counter() - t_eval
    return unit_result(unit, fp, per_seq, fit_s=timer.seconds, eval_s=eval_s, device=device,
                       method="encode_motion -> decode")
