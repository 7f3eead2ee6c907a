"""``python -m benchmark fit-check``: does the completion fit find what the data allow?

It runs table1's rules (the table spec, its protocol version, the profile's sizes) for one prior
(``no-prior`` by default: no learned model can help or hide anything) on one grid cell (10,000
points / 10 fps by default, the densest observation), through the same runner as ``run``, and
prints each figure next to its target:

- MPJPE (mm, mean over output frames), vertex Chamfer (mm), the largest per-sequence mean
  root-orientation error (degrees);
- the count of backwards fits and of unconverged fits (:mod:`benchmark.core.fit_diagnostics`).

It exits 1 when a figure misses its target, so a slow test can guard the fit itself, not only the
committed numbers. The unit files go to ``--out`` (default ``runs/fit-check``) and a rerun resumes.
"""

from __future__ import annotations

import copy
from pathlib import Path

# The targets of issue 11 for no-prior at 10,000 points / 10 fps (the ground truth scores a vertex
# Chamfer of about 7.0 mm against its own scan: the floor).
TARGETS = {"mpjpe_mm": 40.0, "chamfer_mm": 12.0, "root_err_deg_max": 10.0, "backwards": 0, "not_converged": 0}


def grid_cell(spec: dict, points, fps, who: str) -> tuple:
    """``points`` / ``fps`` as the table1 ``spec``'s grid writes them (the observation's seed reads
    the cell as written: --fps 5.0 is the cell 5); a value outside the grid is refused."""
    grid = spec["grid"]
    if points not in grid["points"] or fps not in grid["fps"]:
        raise ValueError(f"{who}: --points {points} / --fps {fps:g} is not a table1 cell "
                         f"(points {grid['points']}, fps {grid['fps']}); pick one of those")
    return next(v for v in grid["points"] if v == points), next(v for v in grid["fps"] if v == fps)


MULTI_START_NOISE = 0.5  # fit-check --multi-start's noise on the encoded copies (objective.multi_start)


def with_multi_start(spec: dict, starts: int | None, choose: str = "end", around: str = "encoded") -> str:
    """Set ``objective.multi_start`` to ``starts`` copies about ``around``, chosen by ``choose``
    (``--multi-start``, ``--around``, ``--choose``: a candidate rule, docs/protocol.md) in the table
    spec ``spec``; returns the note the report prints ("" for None)."""
    if starts is None:
        if choose != "end" or around != "encoded":
            raise ValueError("fit-check: --choose and --around shape several starts; add --multi-start K")
        return ""
    from benchmark.protocols.multi_start import MultiStart

    if isinstance(starts, bool) or not isinstance(starts, int) or starts < 1:
        raise ValueError(f"fit-check: --multi-start {starts!r}: give the number of starts, an integer >= 1")
    committed = spec["objective"].get("multi_start")
    spec["objective"]["multi_start"] = {"starts": starts, "noise": MULTI_START_NOISE,
                                        **({"choose": choose} if choose != "end" else {}),
                                        **({"around": around} if around != "encoded" else {})}
    MultiStart.from_spec(spec["objective"]["multi_start"])
    same = committed is not None and MultiStart.from_spec(committed) == MultiStart.from_spec(spec["objective"]["multi_start"])
    shown = (f", choose: {choose}" if choose != "end" else "") + (f", around: {around}" if around != "encoded" else "")
    status = "table1's rule as committed" if same else "not table1's protocol as committed"
    return f", objective.multi_start {{starts: {starts}, noise: {MULTI_START_NOISE:g}{shown}}} ({status})"


def with_rate_scaled(spec: dict, rate_scaled: bool) -> str:
    """Set ``objective.plateau.rate_scaled`` (``--rate-scaled``: a candidate rule, docs/protocol.md)
    in the table spec ``spec``; returns the note the report prints ("" when False)."""
    if not rate_scaled:
        return ""
    from benchmark.protocols.step_rules import PlateauRule

    if str(spec["objective"].get("step_rule", "cosine")) != "plateau":
        raise ValueError("fit-check: --rate-scaled needs table1's plateau step rule (objective.step_rule: plateau)")
    spec["objective"]["plateau"] = {**(spec["objective"].get("plateau") or {}), "rate_scaled": True}
    PlateauRule.from_spec(spec["objective"]["plateau"])
    return ", objective.plateau.rate_scaled true (not table1's protocol as committed)"


def with_optimiser(spec: dict, optimiser: str | None) -> str:
    """Set ``objective.optimiser`` (``--optimiser``: ``lbfgs`` is a candidate rule, docs/protocol.md)
    in the table spec ``spec``; returns the note the report prints ("" for None or the spec's own)."""
    from benchmark.protocols.quasi_newton import OPTIMISERS

    if optimiser is None or optimiser == spec["objective"].get("optimiser", "adam"):
        return ""
    if optimiser not in OPTIMISERS:
        raise ValueError(f"fit-check: --optimiser {optimiser!r}: choose one of {', '.join(OPTIMISERS)}")
    if str(spec["objective"].get("step_rule", "cosine")) != "plateau":
        raise ValueError(f"fit-check: --optimiser {optimiser} needs table1's plateau step rule (objective.step_rule: plateau)")
    spec["objective"]["optimiser"] = optimiser
    return f", objective.optimiser {optimiser} (not table1's protocol as committed)"


def with_start_fit(spec: dict, start_fit: str | None) -> str:
    """Set ``objective.start_fit`` (``--start-fit``: ``smooth`` is a candidate rule, docs/protocol.md)
    in the table spec ``spec``; returns the note the report prints ("" for None or the spec's own)."""
    from benchmark.protocols.completion_unit import start_fit_rule
    from benchmark.protocols.brief_fit import START_FITS

    if start_fit is None or start_fit == start_fit_rule(spec):
        return ""
    if start_fit not in START_FITS:
        raise ValueError(f"fit-check: --start-fit {start_fit!r}: choose one of {', '.join(START_FITS)}")
    spec["objective"]["start_fit"] = start_fit
    return f", objective.start_fit {start_fit} (not table1's protocol as committed)"


def check_cell(cell: dict, targets: dict = TARGETS) -> list[tuple[str, float | None, float, bool]]:
    """(figure, value, target, passed) for each target, from a derived table cell."""
    diag = cell.get("diagnostics") or {}
    values = {"mpjpe_mm": cell.get("mpjpe_mm"), "chamfer_mm": cell.get("chamfer_mm"),
              "root_err_deg_max": diag.get("root_err_deg_max"), "backwards": diag.get("backwards"),
              "not_converged": diag.get("not_converged")}
    out = []
    for name, target in targets.items():
        value = values.get(name)
        out.append((name, value, target, value is not None and value <= target))
    return out


def run_fit_check(prior: str = "no-prior", points: int = 10000, fps: float = 10, profile_name: str | None = None,
                  device: str = "cpu", out: str = "runs/fit-check", seed: int = 0, jobs: int | None = None,
                  targets: dict = TARGETS, start_search: str | None = None, multi_start: int | None = None,
                  rate_scaled: bool = False, optimiser: str | None = None, choose: str = "end",
                  around: str = "encoded", start_fit: str | None = None) -> int:
    from benchmark.body import get_body
    from benchmark.run.catalog import get_profile, load_table_spec
    from benchmark.core.outdir import OutDirLock, check_out_dir
    from benchmark.run.registry import get_prior_class
    from benchmark.run.table_run import run_table

    spec = copy.deepcopy(load_table_spec("table1"))
    spec.pop("paper", None)  # the paper's columns are not this run's one-cell grid
    points, fps = grid_cell(spec, points, fps, "fit-check")
    spec["grid"] = {"points": [points], "fps": [fps]}
    rule_note = ""
    if start_search is not None:
        from benchmark.protocols.start_search import START_SEARCH_RULES
        from benchmark.protocols.completion_unit import start_search_rule

        if start_search not in START_SEARCH_RULES:
            raise ValueError(f"fit-check: --start-search {start_search!r}: choose one of {', '.join(START_SEARCH_RULES)}")
        if start_search != start_search_rule(spec):
            rule_note = (f", objective.start_search {start_search} (the table spec says "
                         f"{start_search_rule(spec)}: not table1's protocol as committed)")
        spec["objective"]["start_search"] = start_search
    rule_note += (with_multi_start(spec, multi_start, choose, around) + with_rate_scaled(spec, rate_scaled)
                  + with_optimiser(spec, optimiser) + with_start_fit(spec, start_fit))
    profile = get_profile(profile_name or ("full" if device.startswith("cuda") else "quick"), table="table1")
    get_prior_class(prior)
    out_dir = check_out_dir(out)
    with OutDirLock(out_dir, command=f"python -m benchmark fit-check --prior {prior}"):
        body = get_body("anny", device=device)
        result = run_table(spec, profile, [prior], body, device, seed, out_dir,
                           backend_options=None if jobs is None else {"jobs": jobs})
    if result["failures"]:
        raise RuntimeError(f"fit-check: {len(result['failures'])} unit(s) failed; see the log above")
    cell = result["table"]["rows"][0]["cells"][0]
    if cell.get("na_reason"):
        raise RuntimeError(f"fit-check: the cell is n/a: {cell['na_reason']}")
    rows = check_cell(cell, targets)
    print(f"\nfit-check: {prior}, table1 protocol v{spec['protocol_version']}, profile {profile['name']}, "
          f"{points} points / {fps:g} fps, {cell['sequences']} sequences{rule_note} ({out_dir}/table1.md)")
    print(f"{'figure':<20}{'value':>10}{'target':>10}  result")
    for name, value, target, ok in rows:
        shown = "n/a" if value is None else f"{value:.1f}" if isinstance(value, float) else str(value)
        print(f"{name:<20}{shown:>10}{'<= ' + format(target, 'g'):>10}  {'ok' if ok else 'FAIL'}")
    failed = [r[0] for r in rows if not r[3]]
    print("fit-check: " + ("every target met" if not failed else f"FAILED: {', '.join(failed)}"))
    return 1 if failed else 0


# ---------------------------------------------------------------------------------------------
# Robustness: does a cell's number survive a float perturbation and three times the steps?
# ---------------------------------------------------------------------------------------------

ROBUSTNESS_CELLS = ((100, 5), (10000, 10))  # the sparsest and the densest table1 cell
PERTURBATION_M = 1e-6  # every observed point moved by this along x, y and z
LONGER = 3  # the long run's steps: this times the most steps a base fit took, descending throughout
MAX_MOVE_MM = 1.0  # the largest move of a cell's MPJPE (mm) a number may show and still mean something


def robustness_specs(spec: dict, profile: dict, base_steps: int) -> dict:
    """The two probes of a base run (table1 ``spec`` restricted to its cells, under ``profile``):
    ``perturbed``, the same rules with the observation moved by PERTURBATION_M
    (``data.observation_offset_m``); ``longer``, the step cap LONGER times ``base_steps`` and the
    descent not stopped early: under a rule without reductions (table1 version 6) its tolerance set
    to 0, so it descends at the constant rate to the cap; under a rule with reductions, the same
    rule with ``min_steps`` set so that each sequence reduces its rate as usual and then keeps
    descending at its last rate until the anneal. Returns ``{name: (spec, profile)}``."""
    perturbed = copy.deepcopy(spec)
    perturbed["data"]["observation_offset_m"] = PERTURBATION_M
    longer = copy.deepcopy(spec)
    plateau = dict(longer["objective"].get("plateau") or {})
    if int(plateau.get("reductions", 0)):
        from benchmark.protocols.step_rules import PlateauRule

        plateau["min_steps"] = LONGER * int(base_steps) - PlateauRule.from_spec(plateau).anneal_steps
    else:
        plateau["tolerance"] = 0.0
    longer["objective"]["plateau"] = plateau
    long_profile = dict(profile, steps=LONGER * int(base_steps))
    return {"perturbed": (perturbed, profile), "longer": (longer, long_profile)}


def mpjpe_moves(base: dict, probe: dict) -> tuple[float, float]:
    """(move of the cell's MPJPE, largest move of a sequence's MPJPE), mm, between two derived cells."""
    cell_move = abs(float(probe["mpjpe_mm"]) - float(base["mpjpe_mm"]))
    seq_b = dict(zip(base["per_sequence"]["id"], base["per_sequence"]["mpjpe_mm"]))
    seq_p = dict(zip(probe["per_sequence"]["id"], probe["per_sequence"]["mpjpe_mm"]))
    seq_move = max(abs(seq_p[k] - seq_b[k]) for k in seq_b)
    return cell_move, seq_move


def probe_dir(out_dir, name: str, cell) -> Path:
    """The run folder of ``fit-check --robustness``'s ``name`` run (base, perturbed, longer) of
    ``cell`` (points, fps) under ``out_dir``."""
    return Path(out_dir) / f"{name}-{cell[0]}x{cell[1]}"


def seed_base_units(base_run, out_dir, prior: str, cells=ROBUSTNESS_CELLS) -> list:
    """Copy the units of ``prior`` at ``cells`` from the table1 run folder ``base_run``
    (``units/table1__PRIOR__points=P_fps=F__bNNN.json`` and ``.npz``) into
    ``out_dir/base-PxF/units/``, where the robustness check's base run finds them. The run folder
    is only read; a file already in ``out_dir`` is kept. The base run reuses a copied unit only when
    its spec hash and checksum match (the same rules, profile, seed, weights and data); any other is
    moved aside to ``units/stale/`` there and fitted again. Returns the copied paths."""
    import shutil

    units = Path(base_run).expanduser() / "units"
    if not units.is_dir():
        raise FileNotFoundError(f"--base-run {base_run}: no units/ folder there; give the --out folder of a "
                                "'python -m benchmark run table1' run")
    copied = []
    for points, fps in cells:
        dest = probe_dir(out_dir, "base", (points, fps)) / "units"
        for src in sorted(units.glob(f"table1__{prior}__points={points}_fps={fps}__b*")):
            if src.suffix not in (".json", ".npz") or (dest / src.name).exists():
                continue
            dest.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / src.name)
            copied.append(dest / src.name)
    return copied


def run_robustness(prior: str, profile_name: str | None = None, device: str = "cpu", out: str = "runs/fit-check",
                   seed: int = 0, jobs: int | None = None, base_run: str | None = None,
                   multi_start: int | None = None, rate_scaled: bool = False, optimiser: str | None = None,
                   choose: str = "end", around: str = "encoded", start_fit: str | None = None) -> int:
    """``fit-check --robustness``: ``prior`` on table1's sparsest and densest cell under the
    profile's sequences and rules (the base), then under each probe of :func:`robustness_specs`.
    Prints each cell's MPJPE and how far each probe moves it; exit 1 when a move exceeds
    MAX_MOVE_MM (a number a float perturbation or more steps moves by more measures the optimiser,
    not the prior). ``base_run``: a table1 run folder whose units serve as the base fits
    (:func:`seed_base_units`) and whose stored prior-free starts the base runs read where they match;
    the longer probe reads the base run's (the same observation and search, another step rule:
    :data:`~benchmark.protocols.start_cache.DESCENT_ONLY_KEYS`). ``multi_start``: check the candidate rule of that many starts
    (:func:`with_multi_start`, about ``around``, chosen by ``choose``) instead of table1's own; ``rate_scaled``: the candidate plateau rule of
    :func:`with_rate_scaled`; ``optimiser``: :func:`with_optimiser`'s; ``start_fit``: :func:`with_start_fit`'s."""
    from benchmark.body import get_body
    from benchmark.core.outdir import OutDirLock, check_out_dir
    from benchmark.protocols.start_cache import share_starts
    from benchmark.run.catalog import get_profile, load_table_spec
    from benchmark.run.registry import get_prior_class
    from benchmark.run.table_run import run_table

    spec = copy.deepcopy(load_table_spec("table1"))
    if str(spec["objective"].get("step_rule", "cosine")) != "plateau":
        raise ValueError("fit-check --robustness: table1's objective.step_rule is not 'plateau' (protocol v6); "
                         "the longer probe needs the plateau rule")
    spec.pop("paper", None)  # the paper's columns are not this run's grid
    rule_note = (with_multi_start(spec, multi_start, choose, around) + with_rate_scaled(spec, rate_scaled)
                 + with_optimiser(spec, optimiser) + with_start_fit(spec, start_fit))
    profile = get_profile(profile_name or ("full" if device.startswith("cuda") else "quick"), table="table1")
    get_prior_class(prior)
    out_dir = check_out_dir(out)
    backend = None if jobs is None else {"jobs": jobs}

    def run(name, run_spec, run_profile, key):
        one = dict(run_spec, grid={"points": [key[0]], "fps": [key[1]]})
        result = run_table(one, run_profile, [prior], body, device, seed, probe_dir(out_dir, name, key),
                           backend_options=backend)
        if result["failures"]:
            raise RuntimeError(f"fit-check: {len(result['failures'])} unit(s) of the {name} run failed; see the log above")
        cell = result["table"]["rows"][0]["cells"][0]
        if cell.get("na_reason"):
            raise RuntimeError(f"fit-check: the {name} run's cell {key[0]} / {key[1]} is n/a: {cell['na_reason']}")
        return cell

    base, probes = {}, {"perturbed": {}, "longer": {}}
    with OutDirLock(out_dir, command=f"python -m benchmark fit-check --robustness --prior {prior}"):
        if base_run is not None:
            copied = seed_base_units(base_run, out_dir, prior)
            print(f"--base-run {base_run}: {len(copied)} unit file(s) of {prior} copied as base fits"
                  + ("" if copied else " (none there, or already in --out: the base fits are run as usual)"))
            for points, fps in ROBUSTNESS_CELLS:  # its prior-free starts too, for the cells' base and longer runs
                share_starts(base_run, probe_dir(out_dir, "base", (points, fps)))
        body = get_body("anny", device=device)
        for key in ROBUSTNESS_CELLS:
            base[key] = run("base", spec, profile, key)
            steps = int((base[key].get("diagnostics") or {}).get("steps_max") or profile["steps"])
            for name, (s, p) in robustness_specs(spec, profile, steps).items():
                if name == "longer":  # the base's observation and start search under another step rule
                    share_starts(probe_dir(out_dir, "base", key), probe_dir(out_dir, name, key))
                probes[name][key] = run(name, s, p, key)
    print(f"\nfit-check --robustness: {prior}, table1 protocol v{spec['protocol_version']}{rule_note}, profile {profile['name']}, "
          f"{next(iter(base.values()))['sequences']} sequences; probes: observation moved by {PERTURBATION_M:g} m, "
          f"{LONGER} x the steps each base fit took ({out_dir})")
    print(f"{'cell':<14}{'MPJPE':>9}{'converged':>11}{'steps':>7}{'perturbed':>22}{'longer':>22}  result")
    failed = []
    for key in ROBUSTNESS_CELLS:
        b = base[key]
        diag = b.get("diagnostics") or {}
        shown, ok = [], True
        for name in ("perturbed", "longer"):
            cell_move, seq_move = mpjpe_moves(b, probes[name][key])
            ok &= cell_move <= MAX_MOVE_MM
            shown.append(f"{cell_move:6.2f} (seq {seq_move:6.2f})")
        conv = f"{diag.get('sequences', 0) - diag.get('not_converged', 0)}/{diag.get('sequences', 0)}"
        steps = diag.get("steps_max", "–")
        print(f"{f'{key[0]} / {key[1]}':<14}{b['mpjpe_mm']:>9.1f}{conv:>11}{steps:>7}{shown[0]:>22}{shown[1]:>22}  "
              f"{'ok' if ok else 'FAIL'}")
        if not ok:
            failed.append(f"{key[0]} / {key[1]}")
    print(f"moves in mm (cell mean; largest single sequence); a cell passes when both cell moves are <= {MAX_MOVE_MM:g} mm")
    print("fit-check --robustness: " + ("every cell robust" if not failed else f"FAILED: {', '.join(failed)}"))
    return 1 if failed else 0
