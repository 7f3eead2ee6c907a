"""``fit-check --start-probe``: how far the prior-free start moves when the observation moves by
1e-6 m, stage by stage.

Every prior with a motion encoder starts from the prior-free start, encoded (table1 version 5); the
robustness check (:func:`benchmark.tools.fit_check.run_robustness`) found frequency-guided's and
the structured latent space's cells moving by millimetres under a 1e-6 m move of the observation
(docs/table1.md). This probe runs the start's stages (the facing, then each stage of the limb
search, :func:`benchmark.protocols.start_search.limb_start_search`) on one table1 cell's
observation of the quick sequences and on that observation moved by
:data:`~benchmark.tools.fit_check.PERTURBATION_M`, and prints after each stage how far the body's
joints moved (mean over the output frames and joints, per sequence) and how the limb search's
per-frame choices changed: the place where a start rule's digits become another start.
"""

from __future__ import annotations

import dataclasses
import time

import torch


def start_probe(points: int = 100, fps: float = 5, sequences: int | None = None, profile_name: str = "quick",
                seed: int = 0, offset_m: float | None = None, start_fit: str = "exact") -> dict:
    """The prior-free start's stages on table1's ``points`` / ``fps`` observation of the profile's
    first batch (``sequences``: at most that many of it), and on it moved by ``offset_m`` (default
    PERTURBATION_M); ``start_fit``: the search's data term (``objective.start_fit``).
    Returns ``{"ids", "cell", "offset_m", "stages": [{"stage", "move_mm": per sequence, "choices":
    (base, moved)}], "seconds"}``."""
    from benchmark.body import get_body
    from benchmark.core.work_units import select_sequences
    from benchmark.data.degrade import degrade
    from benchmark.data.table_data import load_motions
    from benchmark.protocols import completion_unit as cu
    from benchmark.protocols.completion import decode_output, observation_batch
    from benchmark.protocols.brief_fit import search_fit
    from benchmark.protocols.facing import observed_facing
    from benchmark.protocols.start_search import limb_search_stages
    from benchmark.run.catalog import get_profile, load_table_spec
    from benchmark.tools.fit_check import PERTURBATION_M, grid_cell
    from priors.no_prior import NoPrior

    spec = load_table_spec("table1")
    points, fps = grid_cell(spec, points, fps, "fit-check --start-probe")
    profile = get_profile(profile_name, table="table1")
    body = get_body("anny")
    data_rules = spec["data"]
    motions = load_motions(None, float(data_rules["window_s"]), body)
    ids = select_sequences(motions, profile["sequences"])[: int(profile["batch_sequences"])]
    if sequences is not None:
        ids = ids[: int(sequences)]
    data = cu.make_source(spec, body, motions, seed).unit_data(ids)
    obs = degrade(data.scans, int(points), float(fps), seed=cu.cell_degrade_seed(seed, points, fps, ids, rule=cu.seed_rule(spec)),
                  capture_fps=float(data_rules["capture_fps"]))
    obj = spec["objective"]
    lr, lam = float(obj["lr"]), float(obj["lambda_prior"])
    rule = search_fit(start_fit, encoded=True)  # the prior-free start, as the encoders encode it
    t0 = time.perf_counter()

    def stages(offset: float):
        batch = observation_batch(dataclasses.replace(obs, points=obs.points + offset), float(data_rules["window_s"]),
                                  data.out_t, "cpu")
        prior = NoPrior(device="cpu")
        state, _ = observed_facing(prior, body, batch, torch.Generator().manual_seed(0), "cpu", lr, lam,
                                   latent_init="mean")

        def joints(st):
            return decode_output(st, body, batch.output_timestamps)[0].joints

        out = [("facing", joints(state), None)]
        for stage, (state, counts) in enumerate(limb_search_stages(prior, body, batch, state, lr, lam, rule)):
            out.append((f"limb stage {stage + 1}", joints(state), counts))
        return out

    offset = PERTURBATION_M if offset_m is None else float(offset_m)
    base, moved = stages(0.0), stages(offset)
    rows = []
    for (name, ja, ca), (_, jb, cb) in zip(base, moved):
        move = ((ja - jb).norm(dim=-1).mean((1, 2)) * 1000.0).tolist()
        rows.append({"stage": name, "move_mm": [round(float(m), 3) for m in move], "choices": (ca, cb)})
    return {"ids": list(ids), "cell": f"{points} / {fps:g}", "offset_m": offset, "stages": rows, "start_fit": start_fit,
            "seconds": time.perf_counter() - t0}


def format_probe(result: dict) -> list[str]:
    """The probe's lines: per stage, the joints' move per sequence and the choices on both observations."""
    lines = [f"fit-check --start-probe: the prior-free start at table1 {result['cell']}, {len(result['ids'])} "
             f"sequence(s), start_fit {result.get('start_fit', 'exact')}, on the observation and on it moved by "
             f"{result['offset_m']:g} m ({result['seconds']:.0f} s)",
             f"{'stage':<16}{'joints moved, mm (mean; per sequence)':<60}choices (observation | moved)"]
    for row in result["stages"]:
        moves = row["move_mm"]
        shown = f"{sum(moves) / len(moves):6.2f}; " + " ".join(f"{m:.1f}" for m in moves)
        choices = "" if row["choices"][0] is None else f"{row['choices'][0]} | {row['choices'][1]}"
        lines.append(f"{row['stage']:<16}{shown:<60}{choices}")
    return lines
