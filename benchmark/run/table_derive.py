"""Derivation: unit results -> the public table (:func:`derive_table`).

The table is derived from the per-sequence rows of the stored unit results, never accumulated by
hand; see :mod:`benchmark.core.work_units` for the unit-result dict and the unit conventions.
"""

from __future__ import annotations

import copy
import hashlib
import logging
import math
import statistics
from typing import Any, Iterable, Mapping

import numpy as np

from benchmark.core.fit_diagnostics import cell_diagnostics
from benchmark.core.intervals import (LEVEL, MIN_SIGNIFICANCE_SEQUENCES, RESAMPLES, bootstrap_ci, excludes_zero,
                                      paired_bootstrap, weighted_mean)
from benchmark.core.json_io import canonical_json
from benchmark.run.same_cells import copy_same_cells, same_cells
from benchmark.core.work_units import (TABLE_FORMAT_VERSION, WorkUnit, spec_field, grid_cells, metric_specs,
                                       profile_sizes, si_metric, spec_source, stable_seed, table_rules,
                                       validate_unit_result)

log = logging.getLogger("benchmark.results")  # the name it had before the split

STD_DEFINITION = "population standard deviation (ddof=0) over sequences of the per-sequence means"
INTERVAL_DEFINITION = (f"{LEVEL:.0%} percentile bootstrap interval of the cell's frame-weighted mean: its sequences "
                       f"(each with its mean and its frames) resampled with replacement, {RESAMPLES} times; none with "
                       "fewer than 2 sequences, none for a measured time (timing: true)")
TIMING_NO_INTERVAL = ("a measured time (timing: true): one timing of the work unit's whole batch, shared by its "
                      "sequences, so its spread over sequences says nothing of its uncertainty; no interval and no "
                      "significance")
PAIRED_DEFINITION = ("per cell and metric, against no-prior and against the cell's best prior by the metric's mean (for "
                     "better: closest, by the frame-weighted mean of the per-sequence distances to its reference): the "
                     "frame-weighted mean of the per-sequence differences (this prior minus the other) over the "
                     f"sequences both cells have, its {LEVEL:.0%} paired bootstrap interval (sequence indices resampled "
                     "jointly), whether the interval excludes 0 (significant; claimed from "
                     f"{MIN_SIGNIFICANCE_SEQUENCES} sequences in common), and whether this prior does better; for a "
                     "measured time (timing: true) the difference alone")
SEED_RULE = ("numpy.random.default_rng(stable_seed('bootstrap', seed, prior, cell, metric)) for a cell's interval, "
             "stable_seed('paired', seed, prior, vs, cell, metric) for a paired comparison; seed: the table's seed, "
             "cell: the canonical JSON of its grid coordinates (benchmark.core.work_units.stable_seed)")
NO_PRIOR = "no-prior"


_META_KEYS = {"units", "profile", "seed", "device", "priors", "provenance", "data", "body", "sequences", "wall_s",
              "resume"}
_META_NEEDS = {
    "units": "the planned WorkUnit list from plan_units (it says how many units each cell needs)",
    "profile": "the profile dict with its name (catalog.get_profile)",
    "seed": "the table run's seed",
    "device": "the device the run used",
}


def derive_table(table_spec: Mapping, unit_results: Iterable[Mapping], meta: Mapping) -> dict:
    """The public table JSON, derived from per-sequence unit results.

    table_spec: the table spec the units were planned from.
    unit_results: unit-result dicts (from ``run_units`` or :func:`load_unit_results`); results of
        units not in the plan are ignored; a result whose spec hash differs from its planned unit
        is an error.
    meta: ``units`` (the planned :class:`WorkUnit` list, required: it says how many units each cell
        needs), ``profile`` (the profile dict with its name), ``seed``, ``device`` (all required);
        optional ``priors`` (row order, a list or a dict keyed by name; default: order of first
        appearance in ``units``), ``provenance`` (default:
        :func:`benchmark.core.provenance.collect_provenance`), ``data`` (what the test data was, e.g.
        ``"synthetic:test"``), ``body`` (the body model's name), ``sequences`` (the sequence ids
        run), ``wall_s`` (the run's wall time), ``resume`` (what the runner did with stored unit
        files: counts of reused / recomputed / moved aside; kept in ``provenance["resume"]``). The table also records each prior's identity as
        planned (``prior_info``: name, size, weights hash...).

    Each cell holds its grid coordinates, then per metric (unit in the name): the mean over every
    scored frame of all sequences (``total sum / total frames``, in reported units) and
    ``<metric>_std`` (:data:`STD_DEFINITION`), plus ``sequences``, ``frames``, ``units``,
    ``fingerprint`` (sha256 of the sorted unit fingerprints). A cell missing any unit has
    ``na_reason: "incomplete: k of n units"`` and no metrics; a cell whose units report n/a has
    their reason. A metric that some sequences lack is ``null`` with its reason in ``metric_na``.

    Uncertainty (:mod:`benchmark.core.intervals`, seeded by :data:`SEED_RULE`): ``<metric>_ci95``,
    ``[lo, hi]`` (:data:`INTERVAL_DEFINITION`; ``null`` with the reason in ``ci_na`` below 2
    sequences or for a ``timing`` metric); ``per_sequence``, the values the intervals come from (``{"id": [...], "frames":
    [...], "<metric>": [...]}``, aligned lists, reported units); ``paired`` (:data:`PAIRED_DEFINITION`):
    metric -> ``{"no_prior": comparison, "best": comparison}`` (each where it applies), a comparison
    being ``{"vs", "sequences", "diff", "ci95", "significant", "better"}``.
    """
    unknown = set(meta) - _META_KEYS
    if unknown:
        raise ValueError(f"derive_table: unknown meta key(s) {sorted(unknown)}; known: {sorted(_META_KEYS)}")
    for key, what in _META_NEEDS.items():
        if key not in meta:
            raise ValueError(f"derive_table: meta needs {key!r}: {what}")
    units: list[WorkUnit] = list(meta["units"])
    profile = meta["profile"]
    if not isinstance(profile, Mapping) or "name" not in profile:
        raise ValueError("derive_table: meta['profile'] must be the profile dict with its 'name' (catalog.get_profile)")
    metrics = metric_specs(table_spec)
    cells = grid_cells(table_spec)
    grid_keys = list(spec_field(table_spec, "grid"))
    clash = [m["name"] for m in metrics if m["name"] in grid_keys]
    if clash:
        raise ValueError(f"{spec_source(table_spec)}: metric name(s) {clash} collide with grid axes")

    planned = {u.unit_id: u for u in units}
    results: dict[str, Mapping] = {}
    for r in unit_results:
        uid = r.get("unit_id") if isinstance(r, Mapping) else None
        unit = planned.get(uid)
        if unit is None:
            log.debug("derive_table: ignoring result %r (not in this plan)", uid)
            continue
        if r.get("spec_hash") != unit.spec_hash:
            raise ValueError(f"derive_table: result for {uid} has spec_hash {r.get('spec_hash')!r}, the plan says "
                             f"{unit.spec_hash!r}: it was computed under other rules; rerun it")
        results[uid] = validate_unit_result(r, unit, source=f"result {uid}")

    priors = list(meta.get("priors") or dict.fromkeys(u.prior for u in units))
    groups: dict[tuple[str, str], list[WorkUnit]] = {}
    for u in units:
        groups.setdefault((u.prior, u.cell_key), []).append(u)

    rows = []
    for prior in priors:
        row_cells = []
        for cell in cells:
            group = groups.get((prior, canonical_json(cell)), [])
            done = [results[u.unit_id] for u in group if u.unit_id in results]
            row_cells.append(_derive_cell(cell, len(group), done, metrics, (meta["seed"], prior)))
        rows.append({"prior": prior, "cells": row_cells})
    add_paired(rows, cells, metrics, meta["seed"])

    if "provenance" in meta and meta["provenance"] is not None:
        provenance = dict(meta["provenance"])
    else:
        from benchmark.core.provenance import collect_provenance

        provenance = collect_provenance(device=meta["device"])
    done_results = list(results.values())
    provenance["timings"] = {
        "fit_s": math.fsum(r["timings"]["fit_s"] for r in done_results),
        "eval_s": math.fsum(r["timings"]["eval_s"] for r in done_results),
        "units": len(done_results),
    }
    if meta.get("wall_s") is not None:
        provenance["timings"]["wall_s"] = float(meta["wall_s"])
    if meta.get("resume") is not None:
        provenance["resume"] = dict(meta["resume"])

    table = {
        "format_version": TABLE_FORMAT_VERSION,
        "table": table_spec["name"],
        "title": table_spec.get("title", table_spec["name"]),
        "protocol": table_spec.get("protocol"),
        "protocol_version": table_spec["protocol_version"],
        "profile": profile["name"],
        "profile_sizes": profile_sizes(profile),
        "profile_description": profile.get("description", ""),
        "comparable_to_full": profile["name"] == "full",
        "seed": meta["seed"],
        "device": meta["device"],
        "unit_devices": sorted({r["device"] for r in done_results}),
        "data": meta.get("data"),
        "body": meta.get("body"),
        "sequences": list(meta["sequences"]) if meta.get("sequences") is not None else None,
        "prior_info": {p: next((u.spec["prior"] for u in units if u.prior == p), None) for p in priors},
        "provenance": provenance,
        "spec": table_rules(table_spec),
        "grid": {k: list(v) for k, v in table_spec["grid"].items()},
        "metrics": metrics,
        "headline_metric": table_spec.get("headline_metric", metrics[0]["name"]),
        "std_definition": STD_DEFINITION,
        "interval_definition": INTERVAL_DEFINITION,
        "paired_definition": PAIRED_DEFINITION,
        "bootstrap": {"resamples": RESAMPLES, "level": LEVEL, "method": "percentile", "seed_rule": SEED_RULE},
        "counts": {
            "units_planned": len(units),
            "units_done": len(done_results),
        },
        "rows": rows,
    }
    if table_spec.get("paper"):
        table["paper"] = copy.deepcopy(table_spec["paper"])
    if table_spec.get("scored_frames"):
        table["scored_frames"] = str(table_spec["scored_frames"])
    copy_same_cells(table, same_cells(table_spec))  # columns fitted once under another name
    all_cells = [c for row in rows for c in row["cells"]]
    table["counts"].update(cells=len(all_cells), cells_na=sum(1 for c in all_cells if c.get("na_reason")))
    return table


def cell_fingerprint(units) -> str:
    """A cell's ``fingerprint``: sha256 of its units' sorted observation fingerprints."""
    return hashlib.sha256(canonical_json(sorted(str(u["fingerprint"]) for u in units)).encode()).hexdigest()


def sequence_values(rows, metric: str) -> list:
    """Each per-sequence row's value of ``metric`` in reported units (its sum over the row's frames);
    None for a row without it."""
    key, factor = si_metric(metric)
    return [factor * r["sums"][key] / r["frames"] if key in (r.get("sums") or {}) else None for r in rows]


def _derive_cell(cell: Mapping, n_units: int, done: list[Mapping], metrics: list[dict], seed_parts: tuple) -> dict:
    """One cell from its units' results; ``seed_parts``: (table seed, prior), for its intervals' seeds."""
    out: dict[str, Any] = dict(cell)
    out["units"] = n_units
    if n_units == 0:
        out["na_reason"] = "not run: no work units were planned for this cell"
        return out
    if len(done) < n_units:
        out["na_reason"] = f"incomplete: {len(done)} of {n_units} units"
        return out
    out["fingerprint"] = cell_fingerprint(done)
    reasons = list(dict.fromkeys(r["na_reason"] for r in done if r["na_reason"] is not None))
    if reasons:
        out["na_reason"] = "; ".join(reasons)
        return out
    seqs = [row for r in done for row in r["per_sequence"]]
    ids = [row["id"] for row in seqs]
    if len(set(ids)) != len(ids):
        raise ValueError(f"cell {dict(cell)}: a sequence appears in two units: {sorted({i for i in ids if ids.count(i) > 1})[:5]}")
    frames = [row["frames"] for row in seqs]
    metric_na, ci_na = {}, {}
    per_sequence: dict[str, list] = {"id": ids, "frames": frames}
    for m in metrics:
        name = m["name"]
        key, factor = si_metric(name)
        have = [row for row in seqs if key in row["sums"]]
        if len(have) < len(seqs):
            out[name] = None
            out[f"{name}_std"] = None
            out[f"{name}_ci95"] = None
            given = list(dict.fromkeys(row["na"][key] for row in seqs
                                       if key not in row["sums"] and key in (row.get("na") or {})))
            metric_na[name] = ("; ".join(given) if given and not have
                               else f"not reported: no sequence has {key!r}" if not have
                               else f"incomplete: reported for {len(have)} of {len(seqs)} sequences")
            continue
        total = math.fsum(row["sums"][key] for row in seqs)
        out[name] = factor * total / sum(frames)
        per_seq = sequence_values(seqs, name)
        _check_finite(cell, done, seqs, per_seq, out[name], key, name)
        out[f"{name}_std"] = statistics.pstdev(per_seq) if len(per_seq) > 1 else 0.0
        if m.get("timing"):
            out[f"{name}_ci95"] = None
            ci_na[name] = TIMING_NO_INTERVAL
        elif len(per_seq) > 1:
            rng = np.random.default_rng(stable_seed("bootstrap", *seed_parts, canonical_json(cell), name))
            out[f"{name}_ci95"] = list(bootstrap_ci(per_seq, frames, rng))
        else:
            out[f"{name}_ci95"] = None
            ci_na[name] = f"{len(per_seq)} sequence: no interval"
        per_sequence[name] = per_seq
    out["sequences"] = len(seqs)
    out["frames"] = sum(frames)
    diagnostics = cell_diagnostics(seqs)
    if diagnostics is not None:
        out["diagnostics"] = diagnostics
    out["fit_s"] = math.fsum(r["timings"]["fit_s"] for r in done)
    out["eval_s"] = math.fsum(r["timings"]["eval_s"] for r in done)
    if metric_na:
        out["metric_na"] = metric_na
    if ci_na:
        out["ci_na"] = ci_na
    out["per_sequence"] = per_sequence
    return out


def _check_finite(cell, done, seqs, per_seq, mean, key: str, name: str) -> None:
    """Refuse a sequence (or cell) value that is not finite in reported units: a finite SI sum can
    overflow once converted (``1e307`` m is ``inf`` mm); the message names the unit and the sequence."""
    for row, value in zip(seqs, per_seq):
        if not math.isfinite(value):
            unit = next((r["unit_id"] for r in done if any(x is row for x in r["per_sequence"])), "?")
            raise ValueError(f"result {unit}: sequence {row['id']!r}: sums[{key!r}] = {row['sums'][key]!r} over "
                             f"{row['frames']} frames is {value!r} {name}, not a finite number; the unit result is "
                             "corrupt: delete it and rerun the unit")
    if not math.isfinite(mean):
        raise ValueError(f"cell {dict(cell)}: {name} = {mean!r} over its sequences, not a finite number "
                         f"(sums[{key!r}] too large); its unit results are corrupt: rerun them")


def add_paired(rows: list[dict], cells: list[Mapping], metrics: list[dict], table_seed) -> None:
    """The table-level pass: each cell's ``paired`` comparisons (:data:`PAIRED_DEFINITION`), against
    ``no-prior`` and against the cell's best prior, for every metric with per-sequence values."""
    for j, coords in enumerate(cells):
        cell_json = canonical_json(coords)
        for m in metrics:
            name, ref_name = m["name"], m.get("reference")
            if m["better"] == "none":  # a reference figure: never ranked
                continue
            have = ranked_cells(rows, j, m)
            if not have:
                continue
            best = best_prior(have, m)
            for prior, cell in have.items():
                refs = {}
                if prior != NO_PRIOR and NO_PRIOR in have:
                    refs["no_prior"] = NO_PRIOR
                if prior != best:
                    refs["best"] = best
                comparisons = {}
                for role, ref in refs.items():
                    fa, fb = cell.get("fingerprint"), have[ref].get("fingerprint")
                    if fa and fb and fa != fb:  # merged rows seen on another observation: not a paired comparison
                        continue
                    rng = np.random.default_rng(stable_seed("paired", table_seed, prior, ref, cell_json, name))
                    comparison = _paired(_distances(cell["per_sequence"], name, ref_name),
                                         _distances(have[ref]["per_sequence"], name, ref_name), name,
                                         "lower" if ref_name else m["better"], ref, rng,
                                         no_interval=TIMING_NO_INTERVAL if m.get("timing") else None)
                    if comparison is not None:
                        comparisons[role] = comparison
                if comparisons:
                    cell.setdefault("paired", {})[name] = comparisons


def ranked_cells(rows: list[Mapping], j: int, metric: Mapping) -> dict[str, Mapping]:
    """Prior -> its cell ``j``, for the rows whose cell can be ranked on ``metric`` (a served number
    with its per-sequence values, and its reference's for ``better: closest``), in row order."""
    name, ref_name = metric["name"], metric.get("reference")
    return {row["prior"]: row["cells"][j] for row in rows
            if not row["cells"][j].get("na_reason") and row["cells"][j].get(name) is not None
            and name in (row["cells"][j].get("per_sequence") or {})
            and (ref_name is None or ref_name in row["cells"][j]["per_sequence"])}


def best_prior(have: Mapping[str, Mapping], metric: Mapping) -> str | None:
    """The best of ``have`` (:func:`ranked_cells`) on ``metric``: the lowest or highest mean, or for
    ``better: closest`` the lowest frame-weighted mean of the per-sequence distances to the
    reference (what its paired comparisons compare, not the distance between the two means); ties:
    the first row. None for ``better: none`` or no cell."""
    if metric.get("better", "lower") == "none" or not have:
        return None
    name, ref_name = metric["name"], metric.get("reference")
    if ref_name is not None:
        def distance(prior):
            per = _distances(have[prior]["per_sequence"], name, ref_name)
            return weighted_mean(per[name], per["frames"])
        return min(have, key=distance)
    return (min if metric.get("better", "lower") == "lower" else max)(have, key=lambda p: have[p][name])


def _distances(per_sequence: Mapping, metric: str, reference: str | None) -> Mapping:
    """``per_sequence`` with ``metric``'s values replaced by their distance to ``reference``'s (a
    ``better: closest`` metric's paired comparison is of that distance); as it is without one."""
    if reference is None:
        return per_sequence
    return {**per_sequence, metric: [abs(v - r) for v, r in zip(per_sequence[metric], per_sequence[reference])]}


def _paired(a: Mapping, b: Mapping, metric: str, better: str, vs: str, rng: np.random.Generator,
            no_interval: str | None = None) -> dict | None:
    """One paired comparison of ``a``'s metric against ``b``'s (``per_sequence`` blocks) over the
    sequences both have, weighted by ``a``'s frames; None when they share no sequence.
    ``no_interval``: why this metric gets the difference alone (no interval, no significance)."""
    where = {sid: k for k, sid in enumerate(b["id"])}
    pairs = [(i, where[sid]) for i, sid in enumerate(a["id"]) if sid in where]
    if not pairs:
        return None
    va = [a[metric][i] for i, _ in pairs]
    vb = [b[metric][k] for _, k in pairs]
    w = [a["frames"][i] for i, _ in pairs]
    out: dict[str, Any] = {"vs": vs, "sequences": len(pairs)}
    if no_interval is not None or len(pairs) < 2:
        out.update(diff=weighted_mean(np.subtract(va, vb), w), ci95=None, significant=None,
                   ci_na=no_interval or "1 sequence in common: no interval")
    else:
        diff, ci = paired_bootstrap(va, vb, w, rng)
        out.update(diff=diff, ci95=list(ci), significant=excludes_zero(ci))
        if len(pairs) < MIN_SIGNIFICANCE_SEQUENCES:
            out.update(significant=None, ci_na=(
                f"{len(pairs)} sequences in common: too few to call a difference significant (an interval of "
                f"{len(pairs)} same-sign differences excludes 0 by chance with probability {2.0 ** (1 - len(pairs)):.0%}); "
                f"needs {MIN_SIGNIFICANCE_SEQUENCES}"))
    gain = -out["diff"] if better == "lower" else out["diff"]
    out["better"] = None if gain == 0 else bool(gain > 0)
    return out


UNIT_SUFFIXES = ("mps2", "mm", "cm", "m", "deg", "rad", "s")  # the unit suffixes a metric name may end with, checked in this order


def metric_unit(name: str) -> str | None:
    """The unit a metric name ends with (``chamfer_mm`` -> ``mm``), or None."""
    for unit in UNIT_SUFFIXES:
        if name.endswith("_" + unit):
            return unit
    return None


def cell_reason(cell: Mapping, metric: str) -> str | None:
    """Why a cell shows no number for ``metric`` (the cell's or the metric's n/a reason), or None."""
    if cell.get("na_reason"):
        return cell["na_reason"]
    if cell.get(metric) is None:
        return cell.get("metric_na", {}).get(metric, "no value")
    return None
