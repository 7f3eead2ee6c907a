"""``perf --only soft-chamfer``: the soft-min Chamfer of the smooth start search
(:class:`benchmark.metrics.soft_chamfer.SoftChamfer`) against autograd through every pair
(:func:`~benchmark.metrics.soft_chamfer.reference_soft_chamfer`), forward and backward, side by
side on the same points at the start search's sizes (its mesh-vertex subset against the observed
subset of 100 and 256 points per frame; one frame of 8 sequences x 9 arm hypotheses)."""

from __future__ import annotations

import torch

from benchmark.metrics.soft_chamfer import SoftChamfer, reference_soft_chamfer
from benchmark.protocols.brief_fit import START_SOFTMIN_M as TEMPERATURE_M  # the start search's
from benchmark.tools.perf_clock import timeit


def soft_chamfer_compare(elements: int = 72, vertices: int = 400, points=(100, 256), repeats: int = 3) -> list[dict]:
    """ms per element of each form (forward + backward, the best of ``repeats``, perf's clock), their ratio and
    the largest differences of value (m) and gradient (relative to the largest component)."""
    g = torch.Generator().manual_seed(0)
    rows = []
    for p in points:
        a0 = torch.randn(elements, vertices, 3, generator=g) * 0.4 + 3.0  # metres from the origin, as a walk's
        b = torch.randn(elements, p, 3, generator=g) * 0.4 + 3.0
        lengths = torch.full((elements,), p)
        lengths[::4] = max(1, p // 2)  # padded elements
        soft = SoftChamfer(b, lengths, TEMPERATURE_M)
        out = {}
        for name, fn in (("project", soft), ("reference", lambda a: reference_soft_chamfer(a, b, lengths, TEMPERATURE_M))):
            a = a0.clone().requires_grad_(True)

            def step():
                a.grad = None
                value = fn(a)
                value.sum().backward()
                out[name] = (value.detach(), a.grad)

            out[name + "_ms"] = timeit(step, repeats) * 1000.0 / elements
        (v0, g0), (v1, g1), ms0, ms1 = out["project"], out["reference"], out["project_ms"], out["reference_ms"]
        rows.append({"elements": elements, "vertices": vertices, "points": p, "project_ms": ms0, "reference_ms": ms1,
                     "ratio": ms0 / ms1, "max_value_diff_m": float((v0 - v1).abs().max()),
                     "max_grad_diff_rel": float((g0 - g1).abs().max() / g1.abs().max())})
    return rows


def format_soft(rows: list[dict]) -> list[str]:
    lines = ["## Soft-min Chamfer of the smooth start search, ms per frame (one thread, forward + backward); "
             "ratio = project / autograd through the pairs", "",
             "| vertices x points | project | autograd through the pairs | ratio | largest value difference (m) "
             "| largest gradient difference (relative) |", "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {r['vertices']} x {r['points']} | {r['project_ms']:.3f} | {r['reference_ms']:.3f} | {r['ratio']:.2f} "
              f"| {r['max_value_diff_m']:.1g} | {r['max_grad_diff_rel']:.1g} |" for r in rows]
    return lines + [""]
