"""Shared machinery of the motion tables (denoise, inbetween, reconstruction; docs/protocol.md).

Three parts:

1. Test data (:class:`MotionSource`): clean windows of the test motions resampled to the table's
   frame rate (SLERP, ``Motion.resample_fps``), cut to ``data.window_s`` from ``data.window_start_s``,
   with the ground truth posed on the body with each motion's own shape. The shape is fixed in these
   tables: it is the ground truth's, given to the fit and never optimised.
2. Fitting a prior to observed targets (:func:`fit_motion`): joint positions, virtual-marker vertices
   and/or local rotations at observed frames. It reuses the completion protocol's fit state
   (:class:`benchmark.protocols.fit_state.FitState`, :func:`~benchmark.protocols.fit_state.init_state`,
   :func:`~benchmark.protocols.fit_state.body_parameters`), so the free rigid parameters, window kinds
   and interpolation are exactly table1's: per-frame priors get one latent per observed frame and are
   SLERPed to other times; fixed-window priors are decoded on their own grid and SLERPed; continuous
   priors decode any timestamp; per-observed-frame root orientation / translation where the prior
   does not encode them; a free heading (and offset) for heading-normalised decoders.

   Objective (per sequence, summed over the batch)::

       mean over observed frames and target points of |p - p_obs|^2  (mm^2; joints + markers)
     + w_rot * mean over observed frames and joints of |R - R_obs|_F^2  (when rotations are targets)
     + lambda_prior * prior_term(latents)

   Variables: the latents and the free rigid parameters (never the shape). Adam: under the plateau
   rule (``objective.step_rule: plateau``, denoise and inbetween from version 2) each sequence
   descends until its objective plateaus, the profile's steps a cap, and its fit diagnostics are
   stored (``converged`` per sequence); else a cosine decay of the learning rate to
   ``lr_final_fraction`` of it over the profile's steps.

   Initialisation: latents from ``encode_motion`` of the observed motion (``init="encoder"``), from
   the adapter's ``init_latents`` (``init="sample"``: a prior sample), or given. The rigid parameters
   start from the observation (:func:`set_rigid_from_observation`): root orientation per observed
   frame = the observed root, translation = the observed translation; a free heading is the mean yaw
   between the observed and the decoded root; a free offset the mean difference between the observed
   and the decoded translation. Without observed rotations / translation, completion's own start
   (centroid of the target points, heading search) is kept.
3. Metrics helpers: V2V by time chunks, joint acceleration in m/s^2, the global quaternion loss
   of Harvey et al. 2020 (HM-VAE Table 2), and a fingerprint of observation tensors.
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import roma
import torch

from benchmark.core.motion_posing import body_float
from benchmark.protocols.latent_checks import prior_values
from benchmark.protocols.fit_state import FitState, as_latent, body_parameters, init_state, set_rigid
from benchmark.protocols.step_rules import optimise, optimise_to_plateau
from benchmark.core.skeleton import NUM_JOINTS
from priors.base import FitBatch, InterpolationBaseline, has_motion_encoder

log = logging.getLogger(__name__)

MM2 = 1e6  # m^2 -> mm^2


# --------------------------------------------------------------------------------------------
# Adapter capabilities
# --------------------------------------------------------------------------------------------

def is_interpolation_baseline(adapter) -> bool:
    """The SLERP baseline (priors/slerp.py, an :class:`~priors.base.InterpolationBaseline`): latents
    are the observation, no optimisation."""
    return isinstance(adapter, InterpolationBaseline)


def device_name(device) -> str:
    """What the timings were measured on: the GPU's name for a CUDA device, else the CPU model."""
    d = str(device)
    if d.startswith("cuda") and torch.cuda.is_available():
        try:
            return torch.cuda.get_device_name(torch.device(d))
        except Exception:  # never let a name take a run down
            return d
    from benchmark.core.provenance import cpu_name

    return cpu_name() or d


def synchronize(device) -> None:
    if str(device).startswith("cuda") and torch.cuda.is_available():
        torch.cuda.synchronize(torch.device(str(device)))


# --------------------------------------------------------------------------------------------
# Test data
# --------------------------------------------------------------------------------------------

@dataclass
class CleanBatch:
    """Clean windows of B test sequences at the table's rate, and their ground truth."""

    ids: list
    motions: list  # the windowed Motions (absolute timestamps), at ``fps``
    timestamps: torch.Tensor  # (B, T) float64 seconds from the window start
    rotations: torch.Tensor  # (B, T, 22, 3, 3) local rotations (body dtype/device)
    trans: torch.Tensor  # (B, T, 3)
    shapes: torch.Tensor  # (B, S) the motions' own shapes (fixed)
    joints: torch.Tensor  # (B, T, 22, 3) ground-truth joints
    fps: float
    window_s: float

    @property
    def num_frames(self) -> int:
        return int(self.rotations.shape[1])


def motion_shapes(body, motions, dtype, device) -> torch.Tensor:
    """(B, S) each motion's own shape for ``body`` (the body's default shape where it has none)."""
    rows = []
    for m in motions:
        s = getattr(m, "shape", None)
        if s is None or torch.as_tensor(s).numel() == 0:
            rows.append(body.default_shape(1)[0].to(device=device, dtype=dtype))
            continue
        s = torch.as_tensor(s).reshape(-1)
        if s.numel() != body.shape_dim:
            raise ValueError(f"motion {m.source or '?'}: its shape vector has {s.numel()} values, body {body.name!r} "
                             f"takes {body.shape_dim}; load motions through benchmark.data.table_data.load_motions "
                             "(which fits shapes to the body)")
        rows.append(s.to(device=device, dtype=dtype))
    return torch.stack(rows)


def table_window(spec: dict) -> tuple[float, float, float]:
    """(fps, window_start_s, window_s) of a motion table's ``data`` block."""
    d = spec.get("data") or {}
    src = spec.get("_source") or f"benchmark/tables/{spec.get('name', '?')}.yaml"
    for key in ("fps", "window_s"):
        if key not in d:
            raise ValueError(f"{src}: field 'data.{key}' is missing (see benchmark/tables/denoise.yaml)")
    return float(d["fps"]), float(d.get("window_start_s", 0.0)), float(d["window_s"])


def load_table_motions(spec: dict, data, body, longest_window_s: float | None = None) -> dict:
    """The test motions of a motion table: :func:`benchmark.data.table_data.load_motions`, long enough
    for the window, and without a hole or a root teleport within it (the longest window of the grid)."""
    from benchmark.data.table_data import load_motions

    fps, start, window = table_window(spec)
    needed = start + (longest_window_s or window)
    motions = load_motions(data, needed, body, window=(start, longest_window_s or window))
    # resampled to the table's rate a motion covers its first to its last frame: the window's last
    # frame must lie within it (a 2.0 s motion at 24 fps ends at 1.958 s, before a 30 fps window's 1.967 s)
    short = [k for k, m in motions.items() if m.span + 1e-6 < needed - 1.0 / fps]
    if short and len(short) == len(motions):
        raise ValueError(f"{'--data ' + str(data) if data is not None else 'the test split'}: no motion spans the "
                         f"{needed - 1.0 / fps:.3f} s from its first to its last frame that a "
                         f"{needed:.1f} s window at {fps:g} fps needs (e.g. {short[0]}: {motions[short[0]].span:.3f} s); "
                         "give longer motions")
    if short:
        log.warning("skipping %d motions whose frames span less than the %.3f s a %.1f s window at %g fps needs "
                    "(its last frame must lie within the motion): %s", len(short), needed - 1.0 / fps, needed, fps,
                    short[:5])
    return {k: m for k, m in motions.items() if k not in short}


class MotionSource:
    """Builds (and caches, in process) the clean windows and ground truth of batches of sequences."""

    def __init__(self, spec: dict, body, motions_by_id: dict, seed: int, cache_size: int = 32):
        self.spec = spec
        self.body = body
        self.motions = motions_by_id
        self.seed = int(seed)
        self.fps, self.start, self.window_s = table_window(spec)
        self._cache: OrderedDict = OrderedDict()
        self._cache_size = cache_size

    def cached(self, key, build):
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        value = build()
        self._cache[key] = value
        while len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return value

    def clean(self, sequence_ids, window_s: float | None = None) -> CleanBatch:
        window = float(window_s if window_s is not None else self.window_s)
        return self.cached(("clean", tuple(sequence_ids), window), lambda: self._build_clean(list(sequence_ids), window))

    def _build_clean(self, ids: list, window: float) -> CleanBatch:
        # made on the CPU whatever the run's device (BodyModel.on_cpu), then moved: the same ground truth everywhere
        _, run_device = body_float(self.body)
        body = self.body.on_cpu()
        dtype, device = body_float(body)
        n = int(round(window * self.fps))
        motions = []
        for sid in ids:
            if sid not in self.motions:
                raise KeyError(f"sequence {sid!r} is not among the loaded test motions")
            m = self.motions[sid]
            r = m.resample_fps(self.fps)
            try:
                w = r.window(float(r.timestamps[0]) + self.start, window)
            except ValueError as exc:
                raise ValueError(f"sequence {sid!r}: {exc}; the table needs {self.start + window:.3f} s "
                                 f"(data.window_start_s + window)") from exc
            if w.num_frames != n:
                raise ValueError(f"sequence {sid!r}: a {window} s window at {self.fps} fps has {w.num_frames} frames, "
                                 f"expected {n} (the motion is too short or its rate too low)")
            motions.append(w)
        rot = torch.stack([m.rotmats() for m in motions]).to(device=device, dtype=dtype)
        trans = torch.stack([m.trans for m in motions]).to(device=device, dtype=dtype)
        ts = torch.stack([m.timestamps - m.timestamps[0] for m in motions]).to(device)
        shapes = motion_shapes(body, motions, dtype, device)
        with torch.no_grad():
            rest = body.prepare(shapes)
            joints = body.skin(rest, rot, trans, vertex_indices=_one_vertex(device)).joints
        rot, trans, ts, shapes, joints = (x.to(run_device) for x in (rot, trans, ts, shapes, joints))
        return CleanBatch(ids=ids, motions=motions, timestamps=ts, rotations=rot, trans=trans, shapes=shapes,
                          joints=joints, fps=self.fps, window_s=window)


def _one_vertex(device) -> torch.Tensor:
    """A one-vertex subset: skinning for joints only."""
    return torch.zeros(1, dtype=torch.long, device=device)


# --------------------------------------------------------------------------------------------
# Fitting
# --------------------------------------------------------------------------------------------

@dataclass
class MotionTargets:
    """What a fit sees for B sequences at n observed frames (all tensors batch first)."""

    timestamps: torch.Tensor  # (B, n) observed timestamps, seconds from the window start
    shapes: torch.Tensor  # (B, S) the fixed body shapes
    window_s: float  # the window to reconstruct
    joints: torch.Tensor | None = None  # (B, n, 22, 3) observed joint positions (data term)
    markers: torch.Tensor | None = None  # (B, n, M, 3) observed marker vertices (data term)
    marker_indices: torch.Tensor | None = None  # (M,) the mesh vertices the markers are
    rotations: torch.Tensor | None = None  # (B, n, 22, 3, 3) observed local rotations (data term)
    init_rotations: torch.Tensor | None = None  # (B, n, 22, 3, 3) encoder input, root init
    init_trans: torch.Tensor | None = None  # (B, n, 3) encoder input, translation init
    output_timestamps: torch.Tensor | None = None  # (B, T_out), for FitBatch (default: observed)

    @property
    def batch_size(self) -> int:
        return int(self.timestamps.shape[0])

    def fit_batch(self) -> FitBatch:
        """A completion FitBatch whose points are the observed target positions (joints, markers)."""
        parts = [p for p in (self.joints, self.markers) if p is not None]
        if not parts:
            if self.init_rotations is None:
                raise ValueError("MotionTargets: give joints, markers or rotations to fit")
            parts = [torch.zeros(*self.timestamps.shape, 1, 3, dtype=self.shapes.dtype, device=self.shapes.device)]
        points = torch.cat(parts, dim=2)
        B, n, P = points.shape[:3]
        lengths = torch.full((B, n), P, dtype=torch.long, device=points.device)
        out_t = self.output_timestamps if self.output_timestamps is not None else self.timestamps
        return FitBatch(points=points, lengths=lengths, timestamps=self.timestamps, window_s=float(self.window_s),
                        output_timestamps=out_t)


def init_motion_state(adapter, body, targets: MotionTargets, generator: torch.Generator, device,
                      init: str = "sample", latents: dict | None = None) -> FitState:
    """The fit state before optimisation (module docstring): completion's ``init_state``, then the
    fixed shape, the initial latents (``init`` "encoder" | "sample", or ``latents`` given), and the
    rigid parameters from the observation."""
    if init not in ("encoder", "sample"):
        raise ValueError(f"init must be 'encoder' or 'sample', got {init!r}")
    batch = targets.fit_batch()
    state = init_state(adapter, body, batch, generator, device)
    state.bounded_shape = False
    state.shape_param = targets.shapes.detach().to(device).clone()  # fixed: never in the optimiser
    if latents is None and init == "encoder":
        if not has_motion_encoder(adapter):
            raise ValueError(f"prior {adapter.name!r} has no encode_motion: use init='sample'")
        if targets.init_rotations is None:
            raise ValueError("init='encoder' needs targets.init_rotations (and init_trans)")
        trans = targets.init_trans if targets.init_trans is not None else torch.zeros_like(targets.init_rotations[..., 0, :, 0])
        with torch.no_grad():
            latents = adapter.encode_motion(targets.init_rotations, trans, targets.timestamps)
    if latents is not None:
        if not isinstance(latents, dict) or not latents:
            raise ValueError(f"prior {adapter.name!r}: encode_motion must return a non-empty dict of latent tensors")
        state.latents = {k: as_latent(adapter, k, v.detach().to(device).clone()) for k, v in latents.items()}
    set_rigid_from_observation(state, targets)
    return state


def set_rigid_from_observation(state: FitState, targets: MotionTargets) -> None:
    """Start the free rigid parameters at the observed root orientation and translation
    (:func:`benchmark.protocols.fit_state.set_rigid`)."""
    set_rigid(state, targets.timestamps, targets.init_rotations, targets.init_trans)


def free_parameters(state: FitState) -> list[torch.Tensor]:
    """What the optimiser moves: the latents and the free rigid parameters (not the shape)."""
    params = [v for v in state.latents.values() if v.is_floating_point() and v.requires_grad]
    params += [p for p in (state.root, state.trans, state.heading, state.offset) if p is not None]
    return params


def data_term(body, rest, rot: torch.Tensor, trans: torch.Tensor, targets: MotionTargets,
              rotation_weight_mm2: float = 0.0) -> torch.Tensor:
    """(B,) the data term of the module docstring at the observed frames."""
    idx = targets.marker_indices if targets.markers is not None else _one_vertex(rot.device)
    out = body.skin(rest, rot, trans, vertex_indices=idx)
    sq = []
    if targets.joints is not None:
        sq.append((out.joints - targets.joints.to(out.joints)).square().sum(-1))
    if targets.markers is not None:
        sq.append((out.vertices - targets.markers.to(out.vertices)).square().sum(-1))
    B = rot.shape[0]
    loss = torch.cat(sq, dim=2).mean(dim=(1, 2)) * MM2 if sq else rot.new_zeros(B)
    if targets.rotations is not None and rotation_weight_mm2:
        d = (rot - targets.rotations.to(rot)).square().sum(dim=(-1, -2))  # (B, n, 22)
        loss = loss + rotation_weight_mm2 * d.mean(dim=(1, 2))
    return loss


def fit_motion(adapter, body, targets: MotionTargets, steps: int, lr: float, lambda_prior: float,
               generator: torch.Generator, device, init: str = "sample", latents: dict | None = None,
               rotation_weight_mm2: float = 0.0, lr_final_fraction: float = 0.1,
               callback=None, rule=None) -> tuple[FitState, dict]:
    """Fit the prior's latents and the free rigid parameters to ``targets`` (module docstring).

    ``rule``: a :class:`~benchmark.protocols.step_rules.PlateauRule` (``objective.step_rule:
    plateau``): each sequence descends until its objective plateaus, ``steps`` is the cap; None:
    the cosine schedule over ``steps``. ``steps`` 0 returns the initial state. Returns (state,
    {"history": [...], "diagnostics": per-sequence fit diagnostics, with the plateau rule}); decode
    the result at any timestamps with :func:`decode_parameters`.
    """
    state = init_motion_state(adapter, body, targets, generator, device, init=init, latents=latents)
    with torch.no_grad():
        rest = body.prepare(state.shape())
    params = free_parameters(state)
    history, out = [], {}
    if steps > 0 and params:
        objective, data_trace = [], []

        def step_loss(step):
            rot, trans = body_parameters(state, targets.timestamps, observed=True)
            data = data_term(body, rest, rot, trans, targets, rotation_weight_mm2)
            prior = prior_values(adapter, state.latents)
            total = data + lambda_prior * prior
            objective.append(total.detach())
            data_trace.append(data.detach())
            return total.sum(), lambda: {"data_mm2": float(data.detach().mean()), "prior": float(prior.detach().mean())}

        if rule is None:
            history = optimise(adapter.name, params, steps, lr, lr_final_fraction, step_loss, callback=callback)
        else:
            from benchmark.core.fit_diagnostics import sequence_diagnostics

            history, plateau = optimise_to_plateau(adapter.name, params, steps, lr, lr_final_fraction, step_loss,
                                                   objective, rule, callback=callback)
            # the data term is a mean of squares (mm^2): its root (mm) is what the diagnostics report
            out["diagnostics"] = sequence_diagnostics(torch.stack(data_trace).clamp_min(0).sqrt(), plateau=plateau)
            out["steps"] = int(plateau["steps"])
    return state, {"history": history, **out}


@torch.no_grad()
def decode_parameters(state: FitState, timestamps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Local rotations (B, T, 22, 3, 3) and translation (B, T, 3) at ``timestamps`` (B, T)."""
    t = timestamps.to(state.obs_t.device)
    observed = tuple(t.shape) == tuple(state.obs_t.shape) and bool(torch.equal(t.to(state.obs_t.dtype), state.obs_t))
    rot, trans = body_parameters(state, t, observed=observed)
    if trans is None:
        raise ValueError(f"prior {state.adapter.name!r}: no translation (the prior encodes none and the state has none)")
    return rot, trans


# --------------------------------------------------------------------------------------------
# Metrics
# --------------------------------------------------------------------------------------------

def chunk_frames(batch: int, budget: int = 512) -> int:
    return max(1, budget // max(batch, 1))


@torch.no_grad()
def joints_of(body, shapes, rot, trans) -> torch.Tensor:
    rest = body.prepare(shapes)
    return body.skin(rest, rot, trans, vertex_indices=_one_vertex(rot.device)).joints


@torch.no_grad()
def v2v_sums(body, shapes, rot_a, trans_a, rot_b, trans_b) -> torch.Tensor:
    """(B,) float64 sums over frames of the mean vertex distance between two posings (metres),
    every vertex, posed in time chunks (never the whole (B, T, V, 3) at once)."""
    rest = body.prepare(shapes)
    B, T = rot_a.shape[:2]
    step = chunk_frames(B)
    total = torch.zeros(B, dtype=torch.float64, device=rot_a.device)
    for t0 in range(0, T, step):
        sl = slice(t0, min(T, t0 + step))
        va = body.skin(rest, rot_a[:, sl], trans_a[:, sl]).vertices
        vb = body.skin(rest, rot_b[:, sl], trans_b[:, sl]).vertices
        total += (va - vb).norm(dim=-1).mean(-1).double().sum(1)
    return total


def pelvis_centred(joints: torch.Tensor) -> torch.Tensor:
    """(..., 22, 3) joints relative to the pelvis (joint 0) of their frame: the local pose VIBE's
    metrics score (HM-VAE's Tables 2 and 3 use them)."""
    return joints - joints[..., :1, :]


def global_rotations(rotations: torch.Tensor) -> torch.Tensor:
    """(..., 22, 3, 3) local -> world rotations of every joint (forward kinematics)."""
    from benchmark.body.lbs import forward_kinematics

    rest = torch.zeros(NUM_JOINTS, 3, dtype=rotations.dtype, device=rotations.device)
    return forward_kinematics(rotations, rest)[0]


def quaternion_loss(pred_rot: torch.Tensor, gt_rot: torch.Tensor) -> torch.Tensor:
    """(B, T) global quaternion loss per frame (Harvey et al. 2020 "L2Q", HM-VAE Table 2).

    pred_rot, gt_rot: (B, T, 22, 3, 3) local rotations. Per frame, the world rotations of the 22
    joints are unit quaternions; each predicted quaternion takes the sign closer to the ground
    truth's (q and -q are one rotation), and the loss is the Euclidean norm of the difference of
    the two 88-vectors (all joints' quaternions concatenated), as in the LAFAN1 benchmark.
    """
    qp = roma.rotmat_to_unitquat(global_rotations(pred_rot.double()))
    qg = roma.rotmat_to_unitquat(global_rotations(gt_rot.double()))
    d2 = torch.minimum((qp - qg).square().sum(-1), (qp + qg).square().sum(-1))  # (B, T, 22)
    return d2.sum(-1).sqrt().to(pred_rot.dtype)


def tensor_fingerprint(**arrays: torch.Tensor) -> str:
    """sha256 of named tensors (name, shape, dtype, little-endian bytes; floats as float32, -0 -> 0)."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = arrays[name].detach().cpu().contiguous()
        if a.is_floating_point():
            a = a.to(torch.float64 if a.dtype == torch.float64 else torch.float32) + 0.0
        data = a.numpy()
        data = data.astype(data.dtype.newbyteorder("<"), copy=False)
        h.update(f"|{name}:{tuple(data.shape)}:{data.dtype.str}|".encode())
        h.update(data.tobytes())
    return h.hexdigest()


@dataclass
class Timer:
    """Wall seconds of the prior's work, CUDA-synchronised at both ends."""

    device: object
    seconds: float = 0.0
    _t0: float = field(default=0.0, repr=False)

    def __enter__(self):
        synchronize(self.device)
        self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        synchronize(self.device)
        self.seconds += time.perf_counter() - self._t0
        return False


def unit_result(unit, fingerprint: str, per_sequence: list, fit_s: float, eval_s: float, device, **extra) -> dict:
    """The unit-result dict of benchmark.core.work_units (plus ``device_name`` and any extra fields)."""
    for sid, row in zip(unit.sequence_ids, per_sequence):
        row["id"] = sid
        row["sums"] = {k: float(v) for k, v in row["sums"].items()}
    out = {
        "unit_id": unit.unit_id, "spec_hash": unit.spec_hash, "prior": unit.prior, "cell": dict(unit.cell),
        "sequence_ids": list(unit.sequence_ids), "fingerprint": fingerprint, "per_sequence": per_sequence,
        "timings": {"fit_s": float(fit_s), "eval_s": float(eval_s)}, "device": str(device),
        "device_name": device_name(device), "na_reason": None,
    }
    out.update(extra)
    return out


def finite_or_raise(name: str, values: torch.Tensor) -> None:
    if not bool(torch.isfinite(values).all()):
        raise FloatingPointError(f"metric {name}: non-finite values {values.tolist()}")


def objective_value(spec: dict, key: str, default=None):
    obj = spec.get("objective") or {}
    if key not in obj and default is None:
        src = spec.get("_source") or f"benchmark/tables/{spec.get('name', '?')}.yaml"
        raise ValueError(f"{src}: field 'objective.{key}' is missing")
    return obj.get(key, default)


__all__ = ["CleanBatch", "MotionSource", "MotionTargets", "Timer", "data_term", "decode_parameters", "device_name",
           "fit_motion", "free_parameters", "global_rotations", "init_motion_state", "is_interpolation_baseline",
           "joints_of", "load_table_motions", "motion_shapes", "pelvis_centred", "quaternion_loss",
           "set_rigid_from_observation", "table_window", "tensor_fingerprint", "unit_result", "v2v_sums"]
