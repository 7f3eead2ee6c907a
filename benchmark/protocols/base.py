"""The protocol interface: what the runner (:func:`benchmark.run.table_run.run_table`) asks of
a table's rules.

A table spec (``benchmark/tables/<name>.yaml``, or a spec registered by another package:
:mod:`benchmark.run.catalog`) names its protocol in its ``protocol`` field; the protocol registry
(:mod:`benchmark.protocols.registry`, entry-point group ``benchmark.protocols``) maps that name to a
:class:`Protocol` subclass, and the runner builds one instance per run. The runner owns everything
else: choosing the sequences, building the adapters, planning the work units and their spec
hashes, resume, the backends, deriving and writing the table. A new table is a spec plus a
protocol class (docs/adding-a-table.md), never an edit of the runner.

The runner calls, in this order:

1. :meth:`Protocol.load_motions` -- the test motions by id (default: the synthetic test split, or
   ``--data``, cut to the spec's ``data.window_s``);
2. :meth:`Protocol.make_source` -- the data source the units read (built once per run, pickled once
   per worker: keep it free of open files, locks and lambdas);
3. for every work unit, on a backend: :meth:`Protocol.na_reason` (a prior that cannot serve the
   table gets n/a cells with that reason) and :meth:`Protocol.run_unit` (the unit result);
4. :meth:`Protocol.unit_cost` -- a unit's relative cost, for parallel backends' longest-first
   order (never changes a number).

A protocol instance holds no state of its own: the executor ships it (pickled by reference to its
class) with the adapters, the body and the source to every worker.
"""

from __future__ import annotations


class Protocol:
    """Base class of a table protocol. Subclasses set :attr:`name` and implement
    :meth:`make_source` and :meth:`run_unit`; the other methods have defaults.

    The unit result :meth:`run_unit` returns (checked by
    :func:`benchmark.core.work_units.validate_unit_result`)::

        {unit_id, spec_hash, prior, cell, sequence_ids, fingerprint,
         per_sequence: [{id, frames, sums: {<SI metric>: sum over frames}}],
         timings: {fit_s, eval_s}, device, na_reason: None, ...}

    ``sums`` hold each metric of the spec's ``metrics`` in SI units (``foo_m`` for a reported
    ``foo_mm``, ``foo_rad`` for ``foo_deg``: :data:`benchmark.core.work_units.UNIT_CONVERSIONS`) summed
    over the sequence's frames; the table is their frame-weighted means.
    """

    name: str = ""  # the value of a table spec's ``protocol`` field (the registry's name for it)
    spec_keys: dict | None = None
    """The keys this protocol accepts in a spec's rule sections, ``{"data": {...}, "objective":
    {...}}``: the rules it reads and the descriptions its specs carry beside them. The runner refuses
    a spec with any other key there before any work (:func:`check_spec_keys`): a misspelt or
    unsupported rule would otherwise be ignored without a word. None (the default): not checked."""

    def load_motions(self, spec: dict, data: str | None, body) -> dict:
        """The test motions by id: the synthetic test split (``data`` None) or ``--data``, each
        at least ``spec["data"]["window_s"]`` long, shapes adapted to ``body``; a motion with a hole
        in its timestamps or a root teleport within its first ``window_s`` (after
        ``data.window_start_s``, where the spec has one) is skipped with a warning, as in the
        project's tables (:func:`benchmark.data.table_data.skip_defects`). A protocol that reads
        another part of its motions overrides this and checks that part."""
        from benchmark.data.table_data import load_motions

        d = spec["data"]
        window = float(d["window_s"])
        return load_motions(data, window, body, window=(float(d.get("window_start_s", 0.0)), window))

    def make_source(self, spec: dict, body, motions_by_id: dict, seed: int):
        """The data source the units read (builds and caches unit inputs); picklable."""
        raise NotImplementedError(f"protocol {self.name or type(self).__name__!r}: make_source is not implemented")

    def na_reason(self, spec: dict, adapter) -> str | None:
        """Why ``adapter`` cannot serve this table (its cells are n/a with this reason), or None."""
        return None

    def run_unit(self, unit, spec: dict, profile: dict, adapter, body, source, device) -> dict:
        """One work unit (a prior x a grid cell x a batch of sequences): its result dict."""
        raise NotImplementedError(f"protocol {self.name or type(self).__name__!r}: run_unit is not implemented")

    def unit_cost(self, unit, spec: dict, profile: dict) -> float:
        """A unit's relative cost, for longest-first ordering (default:
        :func:`benchmark.core.work_units.estimate_cost`)."""
        from benchmark.core.work_units import estimate_cost

        return estimate_cost(unit)

    def carry_problem(self, spec: dict) -> str | None:
        """Why a unit of this table whose every fit converged under a step cap could still change
        under a larger cap, or None where it cannot: its stored result is then carried over when the
        cap rises instead of computed again (:mod:`benchmark.run.cap_carry`). Default: not declared."""
        return f"protocol {self.name or type(self).__name__!r} does not declare its fits independent of the step cap"

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"


def check_spec_keys(spec: dict, protocol: Protocol) -> None:
    """Raise ValueError, naming the table's file, the section, the key and the keys accepted, for
    a key of the spec's ``data`` or ``objective`` section that ``protocol.spec_keys`` does not
    list (nothing is checked where it is None)."""
    import difflib

    accepted = getattr(protocol, "spec_keys", None)
    if not accepted:
        return
    where = spec.get("_source") or f"table {spec.get('name')!r} (benchmark/tables/{spec.get('name')}.yaml)"
    for section, keys in accepted.items():
        given = spec.get(section) or {}
        if not isinstance(given, dict):
            continue
        for key in given:
            if key in keys:
                continue
            close = difflib.get_close_matches(str(key), sorted(keys), n=1)
            hint = f"did you mean {section}.{close[0]}? " if close else ""
            raise ValueError(f"{where}: {section}.{key} is not a rule of protocol {protocol.name!r}, which would ignore it; "
                             f"{hint}remove or rename it (accepted in {section}: {', '.join(sorted(keys))})")
