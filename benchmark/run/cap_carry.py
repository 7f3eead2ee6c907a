"""Stored units that carry over when a profile's step cap rises (:func:`carry_problem`, :func:`carry_unit`).

Under the plateau rule (table1 version 6 and later, sls version 4 and later) a profile's ``steps``
is a cap, not a count. Each sequence descends until its own plateau and is then held; the batch's
descent ends when every sequence is held, or at the cap. Before the cap, nothing in
:func:`~benchmark.protocols.step_rules.optimise_to_plateau` reads it: the steps, the checks, the
rate reductions and the holds are the same under any cap. So a fit whose every sequence *converged*
(held at its plateau, at its last reduced rate, before the cap) is the same computation under
every larger cap. Its unit, made under a cap of N steps, is value for value the unit under a cap of
M > N.

A run whose cap rose therefore reuses such units instead of computing them again. The runner
(:func:`benchmark.run.runner.run_units`) asks the table's protocol
(:meth:`~benchmark.protocols.base.Protocol.carry_problem`) whether its rules allow it. It then
checks that the stored unit differs from the planned one in the cap alone, that the cap rose, and
that every fit converged. The stored JSON moves to ``units/stale/``; its ``.npz`` is copied there.
The unit is rewritten under the new spec and hash, with a ``carried`` record of where it came from.

A unit with a fit at the cap is computed again: that fit would go on. So is a unit whose cap fell,
and one whose protocol does not declare its fits cap-independent: several starts (the copy kept
depends on every copy's end), L-BFGS, a cosine schedule over the steps, a minimum step count.
"""

from __future__ import annotations

import copy
import os
import shutil
from pathlib import Path
from typing import Mapping

import numpy as np

from benchmark.core.work_units import WorkUnit, checksum_problem, with_checksum
from benchmark.data.unit_arrays import arrays_path, read_arrays, write_arrays

CARRIED_KEY = "carried"


def _steps(spec) -> int | None:
    value = (spec.get("profile") or {}).get("steps") if isinstance(spec, Mapping) else None
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def _without_steps(spec: Mapping) -> dict:
    out = copy.deepcopy(dict(spec))
    out["profile"] = {k: v for k, v in (out.get("profile") or {}).items() if k != "steps"}
    return out


def carry_problem(stored: Mapping, unit: WorkUnit, rules_problem: str | None) -> str | None:
    """Why the stored result ``stored`` (a unit file's JSON) cannot stand for ``unit``, planned under
    a larger step cap, or None when it can. ``rules_problem``: the protocol's answer for the unit's
    rules (:meth:`~benchmark.protocols.base.Protocol.carry_problem`; None: its fits are
    cap-independent once converged)."""
    if rules_problem:
        return rules_problem
    old = stored.get("spec")
    if not isinstance(old, Mapping):
        return "the stored result holds no spec"
    if checksum_problem(stored):
        return "its checksum does not vouch for it"
    old_steps, new_steps = _steps(old), _steps(unit.spec)
    if old_steps is None or new_steps is None:
        return "no step cap in its profile"
    if _without_steps(old) != _without_steps(unit.spec):
        return "it differs from the planned unit in more than the step cap"
    if new_steps <= old_steps:
        return f"the cap did not rise ({old_steps} -> {new_steps} steps)"
    if stored.get("na_reason") is not None:
        return "it holds no fit (n/a)"
    per_sequence = stored.get("per_sequence")
    if not isinstance(per_sequence, list) or not per_sequence:
        return "it records no sequences"
    flags = [(p.get("diagnostics") or {}).get("converged") if isinstance(p, Mapping) else None for p in per_sequence]
    if not all(f is True for f in flags):
        n = sum(f is not True for f in flags)
        return f"{n} of its {len(flags)} fits did not converge within its cap of {old_steps} steps"
    return None


def carry_unit(stored: Mapping, unit: WorkUnit, out_dir: str | os.PathLike, stale_json: Path) -> dict:
    """``stored`` rewritten as ``unit``'s result (spec, hash, a ``carried`` record, its checksum).

    The caller has moved the stored JSON to ``stale_json``; the unit's ``.npz``, if any, is copied
    beside it and rewritten with the new hash (its arrays are the same). Returns the record the caller
    stores as the unit's JSON."""
    old_hash = stored.get("spec_hash")
    record = {k: v for k, v in stored.items() if k != "checksum"}
    record["spec"] = unit.spec
    record["spec_hash"] = unit.spec_hash
    record[CARRIED_KEY] = {
        "from_spec_hash": old_hash, "from_steps": _steps(stored["spec"]), "to_steps": _steps(unit.spec),
        "stale_file": stale_json.name,
        "why": "every fit converged before its cap; under the plateau rule the steps before the cap do not depend on it",
    }
    npz = arrays_path(out_dir, unit.unit_id)
    if npz.exists():
        arrays = read_arrays(npz)
        if str(arrays.get("spec_hash")) == old_hash:
            shutil.copy2(npz, stale_json.with_suffix(".npz"))
            arrays["spec_hash"] = np.array(unit.spec_hash)
            write_arrays(npz, arrays)
    return with_checksum(record)
