"""Fit diagnostics: did a fit face the right way, and did its optimisation converge?

Every completion-type unit (table1, sls, captured scans) stores, per sequence, in its row of
``per_sequence`` (``row["diagnostics"]``):

- ``root_err_deg``: geodesic angle between the fitted and the ground-truth root orientation,
  mean over the output frames (degrees); absent without a ground-truth motion;
- ``facing_err_deg``: angle between the fitted and the ground-truth horizontal facing (the root's
  +z axis projected on the ground), mean over the output frames;
- ``backwards``: ``facing_err_deg > BACKWARDS_DEG``: the fit faces the other way (a fit can also
  face the right way upside down: the cell counts sequences whose ``root_err_deg`` exceeds
  ``MISORIENTED_DEG`` as ``misoriented``);
- ``final_data_mm``: the data term (the objective without the prior term) at the last step;
- ``data_decrease_last10``: the data term's relative decrease over the last
  ``CONVERGENCE_WINDOW`` of the steps, ``(d[s0] - d[last]) / d[s0]``;
- ``converged``: protocol v6-v7 (``objective.step_rule: plateau``): the objective's relative change
  over the plateau rule's window, at a constant rate (v6: the full one; v7: the last reduced one), was within its tolerance
  when the descent stopped (``plateau_decrease``; ``steps``: the steps the fit took, anneal
  included; :class:`benchmark.protocols.step_rules.PlateauRule`); versions 1-5:
  ``data_decrease_last10 <= CONVERGED_MAX_DECREASE`` (a flag a fit whose cosine schedule has
  already shrunk its steps can pass while still far from its minimum).

:func:`cell_diagnostics` sums them per table cell (the table's ``diagnostics`` and the Markdown
"Fit diagnostics" section); a cell with a backwards or unconverged fit is marked in every metric
table, so a number that is a fit failure is visible at a glance.
"""

from __future__ import annotations

import math
from typing import Iterable, Mapping

import numpy as np
import torch

BACKWARDS_DEG = 90.0  # mean facing error above which a fit is "backwards"
MISORIENTED_DEG = 90.0  # mean root-orientation error above which a fit is "misoriented" (backwards, or e.g. upside down)
CONVERGENCE_WINDOW = 0.1  # the share of the last steps the convergence figure looks at
SMOOTHING = 0.02  # the share of steps averaged at each end of the convergence window
CONVERGED_MAX_DECREASE = 0.01  # relative decrease of the data term over that window for "converged"
FLAG = "⚠"  # the mark of a cell with a backwards or unconverged fit in the Markdown tables


def heading(rotations: np.ndarray) -> np.ndarray:
    """(..., 3) horizontal facing direction of root rotations (..., 3, 3): the body's +z axis."""
    f = np.array(rotations[..., :, 2], dtype=np.float64, copy=True)
    f[..., 1] = 0.0
    return f / np.maximum(np.linalg.norm(f, axis=-1, keepdims=True), 1e-9)


def root_errors(fit_root: np.ndarray, gt_root: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame: geodesic angle between fitted and ground-truth root orientations and the angle
    between their horizontal facing directions, both in degrees, from (..., 3, 3) rotations."""
    fit_root, gt_root = np.asarray(fit_root, dtype=np.float64), np.asarray(gt_root, dtype=np.float64)
    rel = np.swapaxes(gt_root, -1, -2) @ fit_root
    cos = np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    fh, gh = heading(fit_root), heading(gt_root)
    cos_h = np.clip((fh * gh).sum(-1), -1.0, 1.0)
    return np.degrees(np.arccos(cos)), np.degrees(np.arccos(cos_h))


def convergence(trace: Iterable[float]) -> float:
    """The relative decrease of a per-step data term over the last CONVERGENCE_WINDOW of the steps,
    ``(d0 - d1) / d0``: ``d1`` the mean of the last ``k`` steps, ``d0`` the mean of the ``k`` steps
    ending ``window`` steps before the last (``window`` = CONVERGENCE_WINDOW of the steps, at least
    one; ``k`` = 2 % of the steps, at least one: the mean smooths a data term estimated on a random
    subset of the points at each step)."""
    d = np.asarray([float(v) for v in trace], dtype=np.float64)
    if len(d) < 2:
        return float("nan")
    window = min(max(1, math.ceil(CONVERGENCE_WINDOW * len(d))), len(d) - 1)
    k = max(1, min(round(SMOOTHING * len(d)), len(d) - window))
    end = len(d) - window  # d0's last step + 1
    start, last = float(d[end - k:end].mean()), float(d[-k:].mean())
    return (start - last) / start if start > 0 else 0.0


def sequence_diagnostics(data_trace: torch.Tensor, fit_root: torch.Tensor | None = None,
                         gt_root: torch.Tensor | None = None, plateau: Mapping | None = None) -> list[dict]:
    """Per sequence (see the module docstring).

    data_trace: (steps, B) the data term (mm) of every sequence at every step.
    fit_root, gt_root: (B, T, 3, 3) root rotations at the output timestamps, or None (no ground truth).
    plateau: the log of :func:`benchmark.protocols.step_rules.optimise_to_plateau` (protocol v6), or
    None (versions 1-5: the last-10 % flag decides ``converged``).
    """
    trace = data_trace.detach().to("cpu", torch.float64).numpy()
    out = []
    for b in range(trace.shape[1]):
        dec = convergence(trace[:, b])
        known = math.isfinite(dec)  # a fit of one step has no decrease to measure (JSON holds no NaN)
        d = {"final_data_mm": round(float(trace[-1, b]), 4), "data_decrease_last10": round(float(dec), 5) if known else None,
             "converged": bool(known and dec <= CONVERGED_MAX_DECREASE)}
        if plateau is not None:
            dec_b = plateau["plateau_decrease"][b]
            d.update(converged=bool(plateau["converged"][b]), plateau_decrease=None if dec_b is None else float(dec_b),
                     steps=int(plateau["steps"]), descent_steps=int(plateau["descent_steps"][b]))
            if "evaluations" in plateau:  # objective.optimiser lbfgs: the batch's objective evaluations (line searches)
                d["evaluations"] = int(plateau["evaluations"])
        if fit_root is not None and gt_root is not None:
            root, facing = root_errors(fit_root[b].detach().cpu().numpy(), gt_root[b].detach().cpu().numpy())
            d.update(root_err_deg=round(float(root.mean()), 3), facing_err_deg=round(float(facing.mean()), 3),
                     backwards=bool(facing.mean() > BACKWARDS_DEG))
        out.append(d)
    return out


def cell_diagnostics(rows: Iterable[Mapping]) -> dict | None:
    """The diagnostics of a cell's per-sequence rows: counts of backwards and unconverged fits,
    the mean root-orientation error and the largest final decrease; None when no row has any."""
    diags = [row["diagnostics"] for row in rows if isinstance(row.get("diagnostics"), Mapping)]
    if not diags:
        return None
    with_gt = [d for d in diags if "root_err_deg" in d]
    out = {
        "sequences": len(diags),
        "backwards": sum(bool(d.get("backwards")) for d in with_gt),
        "misoriented": sum(float(d["root_err_deg"]) > MISORIENTED_DEG for d in with_gt),
        "not_converged": sum(not d.get("converged", True) for d in diags),
        "data_decrease_last10_max": max((float(d["data_decrease_last10"]) for d in diags
                                         if d.get("data_decrease_last10") is not None), default=None),
        "final_data_mm": float(np.mean([float(d["final_data_mm"]) for d in diags])),
    }
    with_plateau = [d for d in diags if "plateau_decrease" in d]
    if with_plateau:
        changes = [abs(float(d["plateau_decrease"])) for d in with_plateau if d["plateau_decrease"] is not None]
        out["plateau_change_max"] = max(changes) if changes else None
        out["steps_max"] = max(int(d["steps"]) for d in with_plateau)
    if with_gt:
        out["root_err_deg"] = float(np.mean([float(d["root_err_deg"]) for d in with_gt]))
        out["root_err_deg_max"] = max(float(d["root_err_deg"]) for d in with_gt)
    return out


def cell_flagged(diag: Mapping | None) -> bool:
    """True when a cell holds a backwards, misoriented or unconverged fit."""
    return bool(diag) and any(diag.get(k, 0) > 0 for k in ("backwards", "misoriented", "not_converged"))
