"""The denoise table (docs/protocol.md, "denoise"; Motion-DVAE, Fiche et al. 2023, section 5.1, Table 1).

Data: clean 2 s windows at 30 fps of the test motions (:class:`benchmark.protocols.motion_fit.MotionSource`),
ground truth posed on the body with each motion's own shape, which is fixed (never optimised).

Observation of a cell ``sigma`` (:func:`benchmark.data.observations.make_noisy_joints`): Gaussian noise of
standard deviation sigma (rad) on each of the 22 x 3 axis-angle components of every frame (root
included; translation and shape stay clean). The observed data are the noisy joints (joint positions
of the noisy pose) and ``data.num_markers`` virtual markers (a fixed farthest-point subset of the
mesh vertices, :func:`benchmark.data.observations.virtual_marker_indices`) of the noisy pose; the noisy
rotations and the translation are given too (the paper initialises from the noisy SMPL parameters).
The noise of a sequence is drawn from ``stable_seed("denoise-noise", table seed, sigma, sequence id)``:
it depends on nothing else (not the prior, the mode, the batch), so every prior sees the same
observation (the unit's ``fingerprint``).

Modes (the grid's ``mode`` axis):

- ``regression``: one forward pass. An adapter with ``denoise_motion(rotations, trans, timestamps,
  mode, iterations)`` is called with ``mode="regression", iterations=0``; else an adapter with an
  encoder is given ``encode_motion(noisy rotations, translation)`` and its latents are decoded at the
  30 fps frames, with the rigid parameters it does not encode taken from the observation (root
  orientation: the noisy root; translation: the observed one); else the cell is n/a.
- ``optimisation``: ``denoise_motion(..., mode="optimisation", iterations=objective.denoiser_iterations)``
  where the adapter has it (its paper's count; version 1: the profile's steps); else the prior's
  latents and its free rigid parameters are fitted to the noisy joints and markers
  (:func:`benchmark.protocols.motion_fit.fit_motion`: mean squared position error over joints and
  markers in mm^2 + lambda_prior * prior term, Adam; version 2: the plateau rule, each sequence to its
  plateau under the profile's cap, its fit diagnostics stored; version 1: a cosine schedule over the
  profile's steps), starting from the encoder's output where the prior has a learned one, from the
  noisy motion itself where its ``encode_motion`` is an exact change of representation
  (``no-prior``, version 2: the paper initialises from the noisy SMPL parameters; version 1 started
  it from a prior sample), else from a prior sample.

Metrics per sequence (sums over its frames; the table divides by frames): ``v2v_m`` (every vertex
vs the clean ground truth), ``obs_v2v_m`` (the noisy observation's own V2V, a reference),
``mpjpe_m``, ``accel_mps2`` / ``gt_accel_mps2`` / ``obs_accel_mps2`` (mean joint acceleration
magnitude of the output / the ground truth / the noisy observation, m/s^2, stored as the sequence
mean times its frame count; ``accel`` is judged by its distance to ``gt_accel``), ``time_per_frame_s``
(the prior's measured seconds for the unit / (B * frames), stored as the unit seconds / B; the unit
result names the device in ``device`` and ``device_name``). Version 1 named them ``accel``,
``gt_accel``, ``obs_accel`` and ``s_per_frame``.
"""

from __future__ import annotations

import time

import torch

from benchmark.data.degrade import fingerprint
from benchmark.metrics.pose import mean_acceleration, mpjpe
from benchmark.data.observations import NoisyJoints, make_noisy_joints, virtual_marker_indices
from benchmark.protocols.motion_fit import (
    MotionSource, MotionTargets, Timer, decode_parameters, fit_motion, init_motion_state,
    is_interpolation_baseline, joints_of, load_table_motions, objective_value, unit_result, v2v_sums,
)
from benchmark.core.work_units import na_result, stable_seed
from benchmark.protocols.step_rules import plateau_rule
from priors.base import MotionDenoiser, MotionEncoder, has_motion_encoder

MODES = ("regression", "optimisation")
NO_REGRESSION = ("regression needs one forward pass: the prior has neither denoise_motion nor a learned encoder "
                 "(encode_motion with has_encoder)")


class DenoiseSource(MotionSource):
    """Clean windows (MotionSource) plus the noisy observation of each (sequences, sigma)."""

    def marker_indices(self) -> torch.Tensor:
        def build():
            count = int((self.spec.get("data") or {}).get("num_markers", 43))
            return virtual_marker_indices(self.body.on_cpu(), count).to(self.body.faces.device)

        return self.cached(("markers",), build)

    def noise_seed(self, sigma: float, sequence_id: str) -> int:
        return stable_seed("denoise-noise", self.seed, f"{float(sigma):.6g}", sequence_id)

    def noisy(self, sequence_ids, sigma: float) -> tuple[NoisyJoints, str]:
        """(NoisyJoints (B, T), fingerprint) of the batch; each sequence with its own noise seed."""
        ids = list(sequence_ids)
        return self.cached(("noisy", tuple(ids), float(sigma)), lambda: self._build_noisy(ids, float(sigma)))

    def _build_noisy(self, ids: list, sigma: float):
        clean = self.clean(ids)
        markers = self.marker_indices()
        parts = []
        for b, (sid, motion) in enumerate(zip(ids, clean.motions)):  # on the CPU whatever the device (BodyModel.on_cpu)
            obs, _ = make_noisy_joints([motion], sigma, self.noise_seed(sigma, sid), body=self.body.on_cpu(),
                                       marker_indices=markers.cpu(), shapes=clean.shapes[b:b + 1].cpu())
            parts.append(obs)
        cat = lambda name: torch.cat([getattr(p, name) for p in parts])  # noqa: E731
        obs = NoisyJoints(rotations=cat("rotations"), joints=cat("joints"), markers=cat("markers"),
                          marker_indices=markers, trans=cat("trans"), shapes=cat("shapes"),
                          timestamps=cat("timestamps"), frame_mask=cat("frame_mask"), sigma=sigma)
        if not bool(obs.frame_mask.all()):
            raise ValueError("denoise: every sequence of a unit must have all its frames")
        return obs, fingerprint(obs)

    def observation_v2v(self, sequence_ids, sigma: float) -> torch.Tensor:
        """(B,) per-sequence sums over frames of the noisy observation's V2V (metres)."""
        ids = list(sequence_ids)

        def build():
            clean = self.clean(ids)
            obs, _ = self.noisy(ids, sigma)
            return v2v_sums(self.body, clean.shapes, obs.rotmats().to(clean.rotations), obs.trans.to(clean.trans),
                            clean.rotations, clean.trans)

        return self.cached(("obs_v2v", tuple(ids), float(sigma)), build)


# -- the protocol interface (benchmark.protocols.base.Protocol; wrapped by benchmark.protocols.builtin) --
def load_motions(spec: dict, data, body) -> dict:
    return load_table_motions(spec, data, body)


def make_source(spec: dict, body, motions_by_id: dict, seed: int) -> DenoiseSource:
    return DenoiseSource(spec, body, motions_by_id, seed)


def na_reason(spec: dict, adapter) -> str | None:
    if is_interpolation_baseline(adapter):
        return ("the SLERP baseline belongs to the in-betweening table; the noisy observation's own error is "
                "the obs_v2v_mm column of the other priors' rows")
    return None


def denoiser_iterations(spec: dict, steps: int) -> int:
    """Iterations of a prior's own ``denoise_motion`` optimisation: ``objective.denoiser_iterations``
    (its paper's count, version 2), at most the profile's steps (the smoke profile's few); version 1:
    the profile's steps."""
    value = (spec.get("objective") or {}).get("denoiser_iterations")
    return int(steps) if value is None else min(int(value), int(steps))


def mode_na_reason(adapter, mode: str) -> str | None:
    """Why a prior cannot serve a mode (None when it can)."""
    if mode == "regression" and not isinstance(adapter, MotionDenoiser) and not has_motion_encoder(adapter):
        return NO_REGRESSION
    return None


def _as_motion(result, trans_obs: torch.Tensor, name: str, B: int, T: int):
    """(rotations, trans) from what denoise_motion returned: a Decoded, a (rot, trans) pair or a dict."""
    if isinstance(result, dict):
        rot, trans = result.get("rotations"), result.get("trans")
    elif isinstance(result, (tuple, list)):
        rot, trans = (result[0], result[1] if len(result) > 1 else None)
    else:
        rot, trans = getattr(result, "rotations", None), getattr(result, "trans", None)
    if not isinstance(rot, torch.Tensor) or tuple(rot.shape) != (B, T, 22, 3, 3):
        got = tuple(rot.shape) if isinstance(rot, torch.Tensor) else type(rot).__name__
        raise ValueError(f"prior {name!r}: denoise_motion must return rotations (B, T, 22, 3, 3) = {(B, T, 22, 3, 3)} "
                         f"(a Decoded, a (rotations, trans) pair or a dict), got {got}")
    if trans is None:
        trans = trans_obs
    if tuple(trans.shape) != (B, T, 3):
        raise ValueError(f"prior {name!r}: denoise_motion returned trans {tuple(trans.shape)}, expected {(B, T, 3)}")
    return rot.detach().to(trans_obs), trans.detach().to(trans_obs)


def run_unit(unit, spec: dict, profile: dict, adapter, body, source: DenoiseSource, device) -> dict:
    cell = unit.cell
    sigma, mode = float(cell["sigma"]), str(cell["mode"])
    if mode not in MODES:
        raise ValueError(f"{spec.get('_source', 'benchmark/tables/denoise.yaml')}: grid mode {mode!r}; known: {MODES}")
    reason = mode_na_reason(adapter, mode)
    if reason:
        return na_result(unit, reason)
    ids = list(unit.sequence_ids)
    clean = source.clean(ids)
    obs, fp = source.noisy(ids, sigma)
    B, T = clean.rotations.shape[:2]
    noisy_rot = obs.rotmats().to(clean.rotations)
    obs_trans = obs.trans.to(clean.trans)
    steps = int(profile["steps"])
    targets = MotionTargets(timestamps=clean.timestamps, shapes=clean.shapes, window_s=clean.window_s,
                            joints=obs.joints.to(clean.joints), markers=obs.markers.to(clean.joints),
                            marker_indices=obs.marker_indices, init_rotations=noisy_rot, init_trans=obs_trans)
    g = torch.Generator().manual_seed(unit.seed)
    timer = Timer(device)
    info: dict = {"history": []}
    if isinstance(adapter, MotionDenoiser):
        iterations = 0 if mode == "regression" else denoiser_iterations(spec, steps)
        method = f"denoise_motion(mode={mode!r}" + (f", {iterations} iterations)" if iterations else ")")
        with timer:
            res = adapter.denoise_motion(rotations=noisy_rot, trans=obs_trans, timestamps=clean.timestamps, mode=mode,
                                         iterations=iterations)
        rot, trans = _as_motion(res, obs_trans, adapter.name, B, T)
    elif mode == "regression":
        method = "encode_motion -> decode"
        with timer:
            with torch.no_grad():
                latents = adapter.encode_motion(noisy_rot, obs_trans, clean.timestamps)
        state = init_motion_state(adapter, body, targets, g, device, latents=latents)  # rigid: observed
        with timer:
            rot, trans = decode_parameters(state, clean.timestamps)
    else:
        rule = plateau_rule(spec)
        latents = None
        if has_motion_encoder(adapter):
            init = "encoder"
        elif isinstance(adapter, MotionEncoder):  # an exact change of representation (no-prior): the noisy motion
            init = "observation"
            with torch.no_grad():
                latents = adapter.encode_motion(noisy_rot, obs_trans, clean.timestamps)
        else:
            init = "sample"
        method = f"fit (init {init}, " + (f"plateau rule, cap {steps} steps)" if rule else f"{steps} steps)")
        with timer:
            state, info = fit_motion(adapter, body, targets, steps=steps, lr=float(objective_value(spec, "lr")),
                                     lambda_prior=float(objective_value(spec, "lambda_prior")), generator=g,
                                     device=device, init="encoder" if init == "encoder" else "sample", latents=latents,
                                     rule=rule)
            rot, trans = decode_parameters(state, clean.timestamps)
    t_eval = time.perf_counter()
    v2v = v2v_sums(body, clean.shapes, rot, trans, clean.rotations, clean.trans)
    obs_v2v = source.observation_v2v(ids, sigma)
    joints = joints_of(body, clean.shapes, rot, trans)
    err = mpjpe(joints, clean.joints, reduction="sum")
    accel = mean_acceleration(joints, clean.fps)
    gt_accel = mean_acceleration(clean.joints, clean.fps)
    obs_accel = mean_acceleration(obs.joints.to(clean.joints), clean.fps)
    diagnostics = info.get("diagnostics")
    per_seq = [
        {"frames": T, "sums": {"v2v_m": v2v[b], "obs_v2v_m": obs_v2v[b], "mpjpe_m": err[b], "accel_mps2": accel[b] * T,
                               "gt_accel_mps2": gt_accel[b] * T, "obs_accel_mps2": obs_accel[b] * T,
                               "time_per_frame_s": timer.seconds / B},
         **({"diagnostics": diagnostics[b]} if diagnostics else {})}
        for b in range(B)
    ]
    eval_s = time.perf_counter() - t_eval
    return unit_result(unit, fp, per_seq, fit_s=timer.seconds, eval_s=eval_s, device=device, method=method,
                       fit_log=info.get("history", []))
