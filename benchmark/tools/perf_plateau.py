"""The plateau row of ``python -m benchmark perf --only plateau``: one quick table1 unit's descent
with the held sequences evaluated at every step (the whole batch) and kept instead
(:class:`~benchmark.protocols.kept_rows.KeptRows`), side by side in one process."""

from __future__ import annotations

import numpy as np
import torch

from benchmark.tools.perf_clock import CLOCK


def quick_unit():
    """table1's spec, its quick profile, the body, and the data of the quick profile's first unit
    (its sequences): what perf's fit rows time."""
    from benchmark.body import get_body
    from benchmark.core.work_units import select_sequences
    from benchmark.data.table_data import load_motions
    from benchmark.protocols import completion_unit as cu
    from benchmark.run.catalog import get_profile, load_table_spec

    spec = load_table_spec("table1")
    profile = get_profile("quick", table="table1")
    body = get_body("anny")
    motions = load_motions(None, float(spec["data"]["window_s"]), body)
    ids = select_sequences(motions, profile["sequences"])[: int(profile["batch_sequences"])]
    return spec, profile, body, cu.make_source(spec, body, motions, 0).unit_data(ids)


def cell_batch(spec: dict, data, points: int, fps: int):
    """The fit batch of ``data``'s sequences degraded to ``points`` / ``fps`` (perf's own seed)."""
    from benchmark.core.work_units import stable_seed
    from benchmark.data.degrade import degrade
    from benchmark.protocols.completion import observation_batch

    obs = degrade(data.scans, int(points), float(fps), seed=stable_seed("perf", points, fps),
                  capture_fps=float(spec["data"]["capture_fps"]))
    return observation_batch(obs, float(spec["data"]["window_s"]), data.out_t, "cpu")


def plateau_descent_compare(prior: str = "sequential-primitives", points: int = 100, fps: int = 5) -> dict:
    """CPU seconds of the descent (the first to the last Adam step; the start search, shared
    through its cache, is left out) of ``prior``'s quick table1 unit at ``points`` / ``fps``, under
    the committed table1 rules, evaluating the whole batch at every step and keeping the held
    sequences; the steps, each sequence's stop and the largest difference of the final data terms."""
    from benchmark.protocols import completion_unit as cu
    from benchmark.protocols.step_rules import plateau_rule
    from benchmark.protocols.completion import fit
    from benchmark.run.registry import make_adapter

    spec, profile, body, data = quick_unit()
    batch = cell_batch(spec, data, points, fps)
    obj = spec["objective"]
    adapter = make_adapter(prior, size="embedded", weights=None, device="cpu")
    runs = {}
    for form, keep in (("whole", False), ("kept", True)):
        stamps = []
        _, info = fit(adapter, body, batch, steps=int(profile["steps"]), lr=float(obj["lr"]),
                      lambda_prior=float(obj["lambda_prior"]), generator=torch.Generator().manual_seed(0), device="cpu",
                      loss_vertices=cu.loss_vertex_count(profile), facing=cu.facing_rule(spec),
                      shape_lr_scale=float(obj.get("shape_lr_scale", 1.0)), latent_init=cu.latent_init_rule(spec),
                      start_search=cu.start_search_rule(spec), plateau=plateau_rule(spec),
                      callback=lambda step, loss: stamps.append(CLOCK()), keep_held=keep)
        runs[form] = {"s": stamps[-1] - stamps[0], "steps": info["plateau"]["steps"],
                      "descent_steps": info["plateau"]["descent_steps"], "final_data_mm": info["data_trace"][-1].double()}
    whole, kept = runs["whole"], runs["kept"]
    descent = np.asarray(whole["descent_steps"])
    # sequence-steps the whole batch computes in the descent, and those the held sequences needed
    total = len(descent) * int(descent.max())
    needed = int(np.minimum(descent + 1, descent.max()).sum())
    return {"prior": prior, "cell": f"{points}/{fps}", "sequences": batch.batch_size, "steps": [whole["steps"], kept["steps"]],
            "descent_steps": [whole["descent_steps"], kept["descent_steps"]], "whole_s": whole["s"], "kept_s": kept["s"],
            "kept_vs_whole": kept["s"] / whole["s"], "descent_rows_needed": needed / total,
            "max_final_data_diff_mm": float((whole["final_data_mm"] - kept["final_data_mm"]).abs().max())}


def format_plateau(p: dict) -> list[str]:
    return [f"## Plateau descent, {p['prior']} at {p['cell']} (quick unit, {p['sequences']} sequences): whole batch "
            f"{p['whole_s']:.1f} s ({p['steps'][0]} steps), held sequences kept {p['kept_s']:.1f} s ({p['steps'][1]} steps): "
            f"ratio {p['kept_vs_whole']:.2f}; the descent's sequence-steps still needed: {p['descent_rows_needed']:.2f}; "
            f"largest difference of a final data term {p['max_final_data_diff_mm']:.2g} mm", ""]
