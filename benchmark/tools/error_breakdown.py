"""Where a completion fit's joint error comes from: ``python -m benchmark error-breakdown RUN_DIR``.

A table cell's MPJPE mixes several failures: a body in the wrong place, limbs folded into a local
minimum of the data term, or motion lost between observed frames. This module splits it, from the
fitted and ground-truth motions every completion unit stores beside its JSON
(:mod:`benchmark.data.unit_arrays`), re-posed with the run's body:

- ``mpjpe_mm``: the cell's MPJPE (22 joints, no alignment), recomputed from the stored motions
  (float32 quaternions: within about 0.1 mm of the unit's own figure);
- ``observed_mm`` / ``between_mm``: the same over the output frames that coincide with an observed
  frame (within 1 ms) / over the others (what the prior fills in between observations);
- ``pelvis_mm``: the root joint's position error (where the body is);
- ``aligned_mm``: the error with both skeletons' pelvises moved to the origin (the pose), and the
  same by part: ``torso_mm`` (pelvis, spine, neck, head), ``legs_mm`` (hips to feet) and
  ``arms_mm`` (collars to hands).

Means are over every output frame of every sequence of the cell (the table's own weighting).
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

# SMPL 22-joint order (the project's convention)
PARTS = {
    "torso_mm": (0, 3, 6, 9, 12, 15),
    "legs_mm": (1, 2, 4, 5, 7, 8, 10, 11),
    "arms_mm": (13, 14, 16, 17, 18, 19, 20, 21),
}
FIGURES = ("mpjpe_mm", "observed_mm", "between_mm", "pelvis_mm", "aligned_mm", *PARTS)
OBSERVED_TOL_S = 1e-3


def _joints(body, quat: np.ndarray, trans: np.ndarray, shape: np.ndarray) -> torch.Tensor:
    from benchmark.core.rotations import quaternion_to_matrix

    rot = quaternion_to_matrix(torch.from_numpy(np.asarray(quat, dtype=np.float32)))
    rest = body.prepare(torch.from_numpy(np.asarray(shape, dtype=np.float32)))
    # the joints only: skin a single vertex
    out = body.skin(rest, rot, torch.from_numpy(np.asarray(trans, dtype=np.float32)), vertex_indices=torch.zeros(1, dtype=torch.long))
    return out.joints.double()


def unit_errors(body, arrays: dict) -> dict[str, torch.Tensor]:
    """Per-frame error sums of one unit's stored motions: ``{figure: (sum over frames in mm, frames)}``
    as two (B,) tensors per figure (see the module docstring for the figures)."""
    for key in ("fit_quat", "fit_trans", "fit_shape", "gt_quat", "gt_trans", "gt_shape", "t", "obs_t"):
        if key not in arrays:
            raise ValueError(f"error-breakdown: the unit arrays have no {key!r} (not a completion unit with ground truth)")
    with torch.no_grad():
        jf = _joints(body, arrays["fit_quat"], arrays["fit_trans"], arrays["fit_shape"])
        jg = _joints(body, arrays["gt_quat"], arrays["gt_trans"], arrays["gt_shape"])
    err = (jf - jg).norm(dim=-1) * 1000.0  # (B, T, 22)
    aligned = ((jf - jf[:, :, :1]) - (jg - jg[:, :, :1])).norm(dim=-1) * 1000.0
    t, obs_t = np.asarray(arrays["t"], dtype=np.float64), np.asarray(arrays["obs_t"], dtype=np.float64)
    observed = torch.from_numpy(np.abs(t[:, :, None] - obs_t[:, None, :]).min(-1) <= OBSERVED_TOL_S)  # (B, T)
    ones = torch.ones_like(observed, dtype=torch.float64)
    per_frame = {
        "mpjpe_mm": (err.mean(-1), ones),
        "observed_mm": (err.mean(-1), observed.double()),
        "between_mm": (err.mean(-1), (~observed).double()),
        "pelvis_mm": (err[..., 0], ones),
        "aligned_mm": (aligned.mean(-1), ones),
        **{name: (aligned[..., list(idx)].mean(-1), ones) for name, idx in PARTS.items()},
    }
    return {k: ((v * w).sum(1), w.sum(1)) for k, (v, w) in per_frame.items()}


def units_folder(run_dir) -> Path:
    """``run_dir/units``, checked before anything loads (the body model is slow to): a FileNotFoundError
    naming the folder and the fix when it is not there."""
    root = Path(run_dir)
    if not root.is_dir():
        what = "is a file, not a run folder" if root.is_file() else "does not exist"
        raise FileNotFoundError(f"error-breakdown: {run_dir} {what} (give the --out folder of a table1 or sls run)")
    units = root / "units"
    if not units.is_dir():
        raise FileNotFoundError(f"error-breakdown: no units/ folder in {run_dir} (give the --out folder of a "
                                f"table1 or sls run)")
    return units


def run_breakdown(run_dir, body, priors: list[str] | None = None) -> list[dict]:
    """One row per (prior, cell) of the completion units in ``run_dir/units`` (JSON + arrays):
    ``{"prior", "cell", "sequences", figure: mm, ...}``, in the order the units sort."""
    from benchmark.data.unit_arrays import read_arrays

    units = units_folder(run_dir)
    sums: dict = defaultdict(lambda: defaultdict(float))
    counts: dict = defaultdict(int)
    skipped = []
    left_out: dict = defaultdict(list)  # (prior, cell) -> [(unit file, why)]
    for js in sorted(units.glob("*.json")):
        try:
            unit = json.loads(js.read_text())
            if not isinstance(unit, dict):
                raise ValueError("not a JSON object")
        except (OSError, ValueError) as exc:
            raise ValueError(f"error-breakdown: {js}: not a readable unit result ({exc}); move it away (or rerun the "
                             "table into the folder: it moves it to units/stale/ and computes the unit again)") from None
        npz = js.with_suffix(".npz")
        if priors and unit.get("prior") not in priors:
            continue
        key = (unit.get("prior"), tuple((unit.get("cell") or {}).items()))
        if unit.get("na_reason") or not npz.exists():
            skipped.append(js.name)
            left_out[key].append((js.name, "n/a" if unit.get("na_reason") else f"no {npz.name}"))
            continue
        arrays = read_arrays(npz)
        if str(arrays.get("spec_hash")) != unit.get("spec_hash"):
            raise ValueError(f"error-breakdown: {npz} belongs to another specification than {js.name} "
                             f"(spec_hash {arrays.get('spec_hash')} vs {unit.get('spec_hash')}); rerun the unit")
        if "gt_quat" not in arrays:
            skipped.append(js.name)
            left_out[key].append((js.name, "no ground-truth motion stored"))
            continue
        for name, (total, frames) in unit_errors(body, arrays).items():
            sums[key][name] += float(total.sum())
            sums[key][name + "/frames"] += float(frames.sum())
        counts[key] += len(unit.get("sequence_ids", []))
    if not sums:
        raise ValueError(f"error-breakdown: no completion unit with ground-truth motion in {units}"
                         + (f" for priors {priors}" if priors else "") + (f" (skipped: {', '.join(skipped[:5])})" if skipped else ""))
    rows = []
    for key, s in sums.items():
        prior, cell = key
        row = {"prior": prior, "cell": dict(cell), "sequences": counts[key]}
        if left_out.get(key):  # a cell figured from part of its units only: said, never silent
            row["left_out"] = left_out[key]
        for name in FIGURES:
            frames = s[name + "/frames"]
            row[name] = s[name] / frames if frames else float("nan")
        rows.append(row)
    for key, why in left_out.items():  # a cell none of whose units could be read: a row saying so
        if key not in sums:
            rows.append({"prior": key[0], "cell": dict(key[1]), "sequences": 0, "left_out": why,
                         **{name: float("nan") for name in FIGURES}})
    return rows


def format_rows(rows: list[dict]) -> str:
    """A plain-text table of :func:`run_breakdown`'s rows."""
    def cell_name(c):
        keys = [k for k in ("points", "fps") if k in c] + sorted(k for k in c if k not in ("points", "fps"))
        return "/".join(f"{c[k]:g}" if isinstance(c[k], float) else str(c[k]) for k in keys) or "-"

    head = ["prior", "cell", "seq"] + [f.replace("_mm", "") for f in FIGURES]
    lines = [head]
    for r in rows:
        seq = str(r["sequences"]) + (" *" if r.get("left_out") else "")
        lines.append([r["prior"], cell_name(r["cell"]), seq] + [f"{r[f]:.1f}" for f in FIGURES])
    widths = [max(len(line[i]) for line in lines) for i in range(len(head))]
    out = ["  ".join(x.ljust(w) if i < 2 else x.rjust(w) for i, (x, w) in enumerate(zip(line, widths))) for line in lines]
    partial = [r for r in rows if r.get("left_out")]
    if partial:
        out.append("* from part of the cell's units only; left out: " + "; ".join(
            f"{name} ({why})" for r in partial for name, why in r["left_out"]))
    return "\n".join(out)
