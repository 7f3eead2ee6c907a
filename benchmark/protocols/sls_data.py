"""The data of an ``sls`` unit: the anchors' ground truth, input and evaluation scans and landmarks
of a batch of one-cycle sequences (:class:`SlsData`), and a cell's observation of them
(:func:`observe`: the sweep's points per scan and observed anchors). The rules:
:mod:`benchmark.protocols.sls`.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import torch

from benchmark.data.degrade import degrade, fingerprint
from benchmark.data.observations import Landmarks, PointCloudSequence, ground_truth_at
from benchmark.protocols.unit_data import UnitData
from benchmark.core.surface_sampling import sample_surface
from benchmark.core.work_units import stable_seed


@dataclass
class SlsUnitData:
    anchor_t: torch.Tensor  # (B, A) seconds from the cycle start
    scans: PointCloudSequence  # (B, A, N, 3) input scans at the anchors
    landmarks: torch.Tensor  # (B, A, 16, 3) observed landmarks (noisy when data.landmark_noise_std > 0)
    gt_landmarks: torch.Tensor  # (B, A, 16, 3) the landmark vertices of the ground-truth mesh
    eval: UnitData  # evaluation scans (gt_points) and joints at the anchors


class SlsData:
    """Builds and caches (the last batch) the anchors' ground truth of batches of sequences."""

    def __init__(self, spec: dict, body, motions_by_id: dict, seed: int):
        # the data is made on the CPU whatever the run's device (BodyModel.on_cpu)
        self.spec, self.body, self.motions, self.seed = spec, body.on_cpu(), motions_by_id, seed
        self._cache: dict = {}

    def unit_data(self, ids: list[str]) -> SlsUnitData:
        key = tuple(ids)
        if key in self._cache:
            return self._cache[key]
        d = self.spec["data"]
        n_points = int(d["points_per_scan"])
        noise = float(d.get("scan_noise_std", 0.0))
        motions = [self.motions[s] for s in ids]
        A = int(d["anchors"])
        for s, m in zip(ids, motions):
            if m.num_frames != A:
                raise ValueError(f"sls: sequence {s} has {m.num_frames} frames, expected {A} anchors (use sls.load_motions)")
        t = torch.stack([torch.as_tensor(m.timestamps, dtype=torch.float64) for m in motions])
        gt = ground_truth_at(self.body, motions, t)
        faces = self.body.faces
        scans, evals = [], []
        with torch.no_grad():
            for b, s in enumerate(ids):
                g_in = torch.Generator().manual_seed(stable_seed("sls-scan", self.seed, s))
                g_ev = torch.Generator().manual_seed(stable_seed("sls-eval-scan", self.seed, s))
                scans.append(sample_surface(gt.vertices[b:b + 1], faces, n_points, g_in, noise))
                evals.append(sample_surface(gt.vertices[b:b + 1], faces, n_points, g_ev, noise))
        points = torch.cat(scans)
        B = len(ids)
        pcs = PointCloudSequence(points=points, lengths=torch.full((B, A), n_points, dtype=torch.long, device=points.device),
                                 timestamps=t)
        gt_landmarks = self.body.landmarks(gt.vertices)
        landmarks = gt_landmarks
        lm_noise = float(d.get("landmark_noise_std", 0.0))
        if lm_noise > 0:
            rows = [torch.randn(landmarks.shape[1:], generator=torch.Generator().manual_seed(stable_seed("sls-lm", self.seed, s)))
                    for s in ids]
            landmarks = landmarks + lm_noise * torch.stack(rows).to(landmarks)
        data = SlsUnitData(anchor_t=t, scans=pcs, landmarks=landmarks, gt_landmarks=gt_landmarks,
                           eval=UnitData(scans=None, out_t=t, gt_points=torch.cat(evals), gt_joints=gt.joints))
        self._cache = {key: data}
        return data


# ============================================================================ observations
@dataclass
class Observation:
    index: torch.Tensor  # (n,) long, 0-based observed anchors
    points: torch.Tensor | None  # (B, n, P, 3) or None (landmarks only)
    landmarks: torch.Tensor  # (B, n, 16, 3)
    timestamps: torch.Tensor  # (B, n) observed anchor times (tau)
    fingerprint: str


def sweep_rule(spec: dict, code: str) -> tuple[int | None, int]:
    """(points per scan or None for all, observed anchor count) of a sweep code (spec ``sweeps``)."""
    sweeps = spec.get("sweeps") or {}
    if code not in sweeps:
        raise ValueError(f"{spec.get('_source', 'benchmark/tables/sls.yaml')}: grid value {code!r} has no entry in "
                         f"'sweeps' (known: {sorted(sweeps)}); add {{points: ..., frames: ...}} for it")
    rule = sweeps[code]
    pts = rule.get("points", "all")
    return (None if pts == "all" else int(pts)), int(rule.get("frames", spec["data"]["anchors"]))


def check_same_cells(spec: dict) -> None:
    """Refuse a ``same_cells`` entry (``benchmark.run.same_cells``: a column fitted once, shown as
    another) whose column is not its source's observation: the same observed anchors and as many
    points per scan (``all`` is ``data.points_per_scan``)."""
    per_scan = int(spec["data"]["points_per_scan"])
    for e in spec.get("same_cells") or []:
        codes = [(e.get("cell") or {}).get("sweep"), (e.get("as") or {}).get("sweep")]
        seen = [((per_scan if p is None else min(p, per_scan)), f) for p, f in (sweep_rule(spec, c) for c in codes)]
        if seen[0] != seen[1]:
            raise ValueError(f"{spec.get('_source', 'benchmark/tables/sls.yaml')}: same_cells: {codes[0]!r} observes "
                             f"{seen[0][0]} points at {seen[0][1]} anchors, {codes[1]!r} {seen[1][0]} at {seen[1][1]}: "
                             "not the same observation; list it in grid.sweep instead")


def observed_anchors(anchors: int, frames: int) -> torch.Tensor:
    """0-based I_f: anchors k * A / f (1-based), k = 1..f (I_5 of 100 = 20, 40, ..., 100)."""
    if frames < 1 or anchors % frames:
        raise ValueError(f"sls: {frames} observed frames do not divide the {anchors} anchors evenly")
    step = anchors // frames
    return torch.arange(1, frames + 1) * step - 1


def observe(data: SlsUnitData, spec: dict, code: str, seed: int, ids: list[str]) -> Observation:
    """The cell's observation: the observed anchors' (sub-sampled) scans and landmarks.

    ``data.observation_offset_m`` (a robustness probe, as table1's: never set in a table) moves every
    observed scan point and landmark by that many metres along each axis; the fingerprint says so."""
    points, frames = sweep_rule(spec, code)
    A = data.anchor_t.shape[1]
    idx = observed_anchors(A, frames)
    t = data.anchor_t[:, idx]
    lm = data.landmarks[:, idx]
    B = len(ids)
    prints = []
    obs_points = None
    if points != 0:
        rows = []
        for b, s in enumerate(ids):
            pcs = PointCloudSequence(points=data.scans.points[b:b + 1, idx], lengths=data.scans.lengths[b:b + 1, idx],
                                     timestamps=t[b:b + 1])
            if points is not None:
                pcs = degrade(pcs, points, None, seed=stable_seed("sls-degrade", seed, code, s))
            rows.append(pcs.points)
            prints.append(fingerprint(pcs))
        obs_points = torch.cat(rows)
    for b in range(B):
        prints.append(fingerprint(Landmarks(positions=lm[b:b + 1], timestamps=t[b:b + 1])))
    offset = float(spec["data"].get("observation_offset_m", 0.0))
    if offset:  # a robustness probe's move of every scan point and landmark (never set in a table)
        obs_points = None if obs_points is None else obs_points + offset
        lm = lm + offset
        prints.append(f"offset {offset!r}")
    fp = hashlib.sha256("|".join([code, *prints]).encode()).hexdigest()
    return Observation(index=idx, points=obs_points, landmarks=lm, timestamps=t, fingerprint=fp)
