"""The in-betweening table (docs/protocol.md, "inbetween"; HM-VAE, Li et al. 2021, Table 2; Harvey et al. 2020).

Data: clean 2 s windows at 30 fps of the test motions (:class:`benchmark.protocols.motion_fit.MotionSource`),
ground truth posed on the body with each motion's own shape, fixed (never optimised).

Observation of a cell ``gap``: the first ``data.context_frames`` (10) frames and one key frame after
``gap`` missing frames, i.e. frames 0..9 and 10 + gap (their local rotations, root translation and
joint positions, exact). The prior fills frames 10 .. 10 + gap - 1. No randomness: every prior sees
the same observation (the unit's ``fingerprint``).

Every prior is fitted (:func:`benchmark.protocols.motion_fit.fit_motion`) to the observed frames::

    mean |joint - joint_obs|^2 (mm^2) + w_rot * mean |R - R_obs|_F^2 + lambda_prior * prior term

(joint positions and local rotations of all 22 joints; HM-VAE's in-betweening objective also matches
rotations and joint positions). ``objective.init: encoder``: priors with an encoder start from its
latents (:func:`initial_latents`: per-frame priors encode the observed frames, the others the window
filled by the SLERP baseline), a prior whose ``encode_motion`` is an exact change of representation
(``no-prior``, version 2) from the observed frames themselves, the others from a prior sample;
``sample``: every prior starts from a prior sample (as HM-VAE: "randomly sampled latent vectors").
Root orientation and translation (where the prior does not encode them) one per observed frame,
started at the observed values and SLERPed / LERPed by the protocol in between. Adam; version 2: the
plateau rule (each sequence to its plateau under the profile's cap, its fit diagnostics stored);
version 1: a cosine schedule over the profile's steps.

The SLERP baseline (adapter ``slerp``, priors/slerp.py, ``interpolation_baseline = True``) is not
fitted: its latents are the observed rotations, its rigid parameters the observed root and
translation, and the protocol SLERPs the local rotations / LERPs the translation between frame 9 and
the key frame: exact on the observed frames.

Metrics on the ``gap`` missing frames (sums over them; the table divides by frames):
``mpjpe_local_m`` (version 2's headline: the joints relative to the pelvis, the local pose the paper's
Table 2 scores with VIBE's metrics), ``mpjpe_m`` (world coordinates: the root's path enters),
``pa_mpjpe_m``, ``accel_mps2`` (mean joint acceleration magnitude of the output's pelvis-centred
joints, as VIBE's, m/s^2, the second difference centred on each missing frame, so the last context
frame and the key frame of the output enter; judged by its distance to ``gt_accel_mps2``, the ground
truth's own), ``accer_mps2`` (the same of the difference to the ground truth's acceleration),
``quat_loss`` (the
global quaternion loss of Harvey et al.: per frame, the Euclidean norm of the difference of the 22
world-rotation quaternions concatenated, each sign-aligned to the ground truth;
:func:`benchmark.protocols.motion_fit.quaternion_loss`).
"""

from __future__ import annotations

import time

import torch

from benchmark.core.interpolate import lerp_frames, slerp_frames
from benchmark.metrics.pose import acceleration_error, mean_acceleration, mpjpe, pa_mpjpe
from benchmark.protocols.motion_fit import (
    MotionSource, MotionTargets, Timer, decode_parameters, fit_motion, init_motion_state,
    is_interpolation_baseline, joints_of, load_table_motions, objective_value, pelvis_centred, quaternion_loss,
    tensor_fingerprint,
    unit_result,
)
from benchmark.protocols.step_rules import plateau_rule
from priors.base import MotionEncoder, has_motion_encoder


def context_frames(spec: dict) -> int:
    return int((spec.get("data") or {}).get("context_frames", 10))


def observed_frames(context: int, gap: int, total: int) -> tuple[list[int], int]:
    """(observed frame indices, key frame index): frames 0..context-1 and context + gap."""
    key = context + int(gap)
    if context < 1 or gap < 1:
        raise ValueError(f"inbetween: context_frames ({context}) and gap ({gap}) must be >= 1")
    if key >= total:
        raise ValueError(f"inbetween: the key frame {key} (context {context} + gap {gap}) lies outside the "
                         f"{total}-frame window; lengthen data.window_s or shorten the gap")
    return list(range(context)) + [key], key


# -- the protocol interface (benchmark.protocols.base.Protocol; wrapped by benchmark.protocols.builtin) --
def load_motions(spec: dict, data, body) -> dict:
    return load_table_motions(spec, data, body)


def make_source(spec: dict, body, motions_by_id: dict, seed: int) -> MotionSource:
    return MotionSource(spec, body, motions_by_id, seed)


def na_reason(spec: dict, adapter) -> str | None:
    return None  # every prior can fill a gap


def observation(clean, spec: dict, gap: int) -> tuple[MotionTargets, list[int], int, str]:
    """The observed frames of a batch as fit targets, their indices, the key frame and a fingerprint."""
    ctx = context_frames(spec)
    idx, key = observed_frames(ctx, gap, clean.num_frames)
    use_rot = float(objective_value(spec, "rotation_weight_mm2", 0.0)) > 0
    rot = clean.rotations[:, idx]
    targets = MotionTargets(timestamps=clean.timestamps[:, idx], shapes=clean.shapes, window_s=clean.window_s,
                            joints=clean.joints[:, idx], rotations=rot if use_rot else None, init_rotations=rot,
                            init_trans=clean.trans[:, idx], output_timestamps=clean.timestamps)
    fp = tensor_fingerprint(timestamps=targets.timestamps, rotations=rot, trans=targets.init_trans,
                            joints=targets.joints, shapes=clean.shapes)
    return targets, idx, key, fp


@torch.no_grad()
def initial_latents(adapter, targets: MotionTargets, window_t: torch.Tensor) -> dict:
    """Encoder latents to start a fit from: per-frame priors encode the observed frames; the others
    encode the whole window filled by the SLERP baseline (local rotations SLERPed, translation
    LERPed between observed frames, held after the key frame) at the window's frames ``window_t``."""
    if adapter.window.kind == "per-frame":
        return adapter.encode_motion(targets.init_rotations, targets.init_trans, targets.timestamps)
    rot = slerp_frames(targets.init_rotations, targets.timestamps, window_t)
    trans = lerp_frames(targets.init_trans, targets.timestamps, window_t)
    return adapter.encode_motion(rot, trans, window_t)


def run_unit(unit, spec: dict, profile: dict, adapter, body, source: MotionSource, device) -> dict:
    gap = int(unit.cell["gap"])
    ids = list(unit.sequence_ids)
    clean = source.clean(ids)
    targets, _, key, fp = observation(clean, spec, gap)
    ctx = context_frames(spec)
    B = clean.rotations.shape[0]
    g = torch.Generator().manual_seed(unit.seed)
    timer = Timer(device)
    info: dict = {"history": []}
    if is_interpolation_baseline(adapter):
        method = "interpolation baseline: observed frames, SLERP/LERP between them"
        with timer:
            with torch.no_grad():
                latents = adapter.encode_motion(targets.init_rotations, targets.init_trans, targets.timestamps)
            state = init_motion_state(adapter, body, targets, g, device, latents=latents)
    else:
        rule = str(objective_value(spec, "init", "sample"))
        if rule not in ("encoder", "sample"):
            raise ValueError(f"{spec.get('_source', 'benchmark/tables/inbetween.yaml')}: objective.init is {rule!r}; "
                             "expected 'encoder' (the encoder where the prior has one, else a prior sample) or 'sample'")
        if rule == "encoder" and has_motion_encoder(adapter):
            init = "encoder"
        elif rule == "encoder" and isinstance(adapter, MotionEncoder):  # exact (no-prior): the observed frames
            init = "observation"
        else:
            init = "sample"
        steps = int(profile["steps"])
        step_rule = plateau_rule(spec)
        method = f"fit (init {init}, " + (f"plateau rule, cap {steps} steps)" if step_rule else f"{steps} steps)")
        with timer:
            latents = None
            if init == "encoder":
                latents = initial_latents(adapter, targets, clean.timestamps)
            elif init == "observation":
                with torch.no_grad():
                    latents = adapter.encode_motion(targets.init_rotations, targets.init_trans, targets.timestamps)
            state, info = fit_motion(adapter, body, targets, steps=steps, lr=float(objective_value(spec, "lr")),
                                     lambda_prior=float(objective_value(spec, "lambda_prior")), generator=g,
                                     device=device, init="sample", latents=latents,
                                     rotation_weight_mm2=float(objective_value(spec, "rotation_weight_mm2", 0.0)),
                                     rule=step_rule)
    t_eval = time.perf_counter()
    # the last context frame .. the key frame: the missing frames and one neighbour on each side
    span = slice(ctx - 1, key + 1)
    rot, trans = decode_parameters(state, clean.timestamps[:, span])
    joints = joints_of(body, clean.shapes, rot, trans)
    gt_joints, gt_rot = clean.joints[:, span], clean.rotations[:, span]
    fps = clean.fps
    local, gt_local = pelvis_centred(joints), pelvis_centred(gt_joints)  # the paper's (VIBE's) local pose
    sums = {
        "mpjpe_local_m": mpjpe(local[:, 1:-1], gt_local[:, 1:-1], reduction="sum"),
        "mpjpe_m": mpjpe(joints[:, 1:-1], gt_joints[:, 1:-1], reduction="sum"),
        "pa_mpjpe_m": pa_mpjpe(joints[:, 1:-1], gt_joints[:, 1:-1], reduction="sum"),
        "accel_mps2": mean_acceleration(local, fps, reduction="sum"),
        "gt_accel_mps2": mean_acceleration(gt_local, fps, reduction="sum"),
        "accer_mps2": acceleration_error(local, gt_local, fps, reduction="sum"),
        "quat_loss": quaternion_loss(rot[:, 1:-1], gt_rot[:, 1:-1]).sum(1),
    }
    diagnostics = info.get("diagnostics")
    per_seq = [{"frames": gap, "sums": {k: v[b] for k, v in sums.items()},
                **({"diagnostics": diagnostics[b]} if diagnostics else {})} for b in range(B)]
    eval_s = time.perf_counter() - t_eval
    return unit_result(unit, fp, per_seq, fit_s=timer.seconds, eval_s=eval_s, device=device, method=method,
                       fit_log=info.get("history", []))
