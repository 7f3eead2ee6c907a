"""``perf --only lists``: the fit's nearest-neighbour searches with and without neighbour lists
(:mod:`benchmark.metrics.neighbour_lists`), side by side on the same calls of one real fit.

A quick table1 unit (8 sequences, the table's rules: facing and start searches, the plateau rule)
is fitted once. At every Chamfer call both forms answer, each timed: the searches on the grids
(what every call did before the lists) and the lists; their answers must be identical (the fit
uses them, so it is the one fit either would make). Prints the seconds of each, per window of
steps and in all.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from benchmark.metrics import static_chamfer as sc

WINDOW = 50  # steps per printed window


def lists_compare(points: int = 10000, fps: int = 5, prior: str = "no-prior") -> dict:
    """Seconds of the searches (grids) and of the lists over one quick unit's fit; raises if an
    answer differs."""
    from benchmark.protocols import completion_unit as cu
    from benchmark.protocols.completion import fit
    from benchmark.protocols.step_rules import plateau_rule
    from benchmark.run.registry import make_adapter
    from benchmark.tools.perf_plateau import cell_batch, quick_unit

    spec, profile, body, data = quick_unit()
    adapter = make_adapter(prior, size="embedded", weights=None, device="cpu")
    batch = cell_batch(spec, data, points, fps)
    clock = {"grids": 0.0, "lists": 0.0, "calls": 0}
    windows = []

    def both(self, a_np, al, b_np, bl, b_order):
        idx_ab = np.full(a_np.shape[:2], -1, dtype=np.int64)
        idx_ba = np.full(b_np.shape[:2], -1, dtype=np.int64)
        hints = self._hints if b_order is not None else None
        if hints is not None and (hints[0].shape != idx_ab.shape or not np.array_equal(hints[2], al)):
            hints = None
        t0 = time.perf_counter()
        self._searched_indices(a_np, al, b_np, bl, b_order, hints, idx_ab, idx_ba)
        t1 = time.perf_counter()
        if b_order is not None:
            ab, ba = np.full_like(idx_ab, -1), np.full_like(idx_ba, -1)
            self._listed_indices(a_np, al, ab, ba, hints)
            clock["lists"] += time.perf_counter() - t1
            clock["grids"] += t1 - t0
            clock["calls"] += 1
            if not (np.array_equal(ab, idx_ab) and np.array_equal(ba, idx_ba)):
                raise AssertionError("perf --only lists: the lists' answers differ from the grids'")
            self._hints = (idx_ab.copy(), idx_ba.copy(), al.copy())
        return torch.from_numpy(idx_ab), torch.from_numpy(idx_ba)

    def window(step, loss):
        if step % WINDOW == 0 and clock["calls"]:
            windows.append({"step": int(step), **clock})
            clock.update(grids=0.0, lists=0.0, calls=0)

    original = sc.StaticChamfer._grid_indices
    sc.StaticChamfer._grid_indices = both
    obj = spec["objective"]
    try:
        fit(adapter, body, batch, steps=int(profile["steps"]), lr=float(obj["lr"]),
            lambda_prior=float(obj["lambda_prior"]), generator=torch.Generator().manual_seed(0), device="cpu",
            loss_vertices=cu.loss_vertex_count(profile), callback=window, facing=cu.facing_rule(spec),
            shape_lr_scale=float(obj.get("shape_lr_scale", 1.0)), latent_init=cu.latent_init_rule(spec),
            start_search=cu.start_search_rule(spec), start_fit=cu.start_fit_rule(spec), plateau=plateau_rule(spec),
            multi_start=cu.multi_start_rule(spec), optimiser=cu.optimiser_rule(spec))
    finally:
        sc.StaticChamfer._grid_indices = original
    if clock["calls"]:
        windows.append({"step": None, **clock})
    grids, lists = sum(w["grids"] for w in windows), sum(w["lists"] for w in windows)
    return {"prior": prior, "cell": f"{points}/{fps}", "sequences": int(batch.batch_size), "windows": windows,
            "grids_s": grids, "lists_s": lists, "ratio": lists / grids if grids else None}


def format_lists(r: dict) -> list[str]:
    lines = [f"## Nearest neighbours with and without neighbour lists, {r['prior']} at {r['cell']} (quick unit, "
             f"{r['sequences']} sequences; the same calls, identical answers)", "",
             "| calls up to step | calls | grids (s) | lists (s) | ratio |", "| --: | --: | --: | --: | --: |"]
    for w in r["windows"]:
        ratio = w["lists"] / w["grids"] if w["grids"] else float("nan")
        lines.append(f"| {w['step'] if w['step'] is not None else 'end'} | {w['calls']} | {w['grids']:.2f} | "
                     f"{w['lists']:.2f} | {ratio:.2f} |")
    lines += [f"| all | | {r['grids_s']:.1f} | {r['lists_s']:.1f} | {r['ratio']:.2f} |", ""]
    return lines
