"""What exists: tables, priors, datasets, profiles (for ``python -m benchmark list``).

Table specs: the project's own ``benchmark/tables/*.yaml``, the specs other packages register in
the entry-point group ``benchmark.tables`` (a table name -> ``"package:file.yaml"``), and those
registered at run time (:func:`register_table`). A spec's ``protocol`` field names its protocol in
:mod:`benchmark.protocols.registry` (docs/adding-a-table.md).
"""

from __future__ import annotations

import re
from functools import lru_cache
from importlib import resources
from pathlib import Path

from benchmark.core.yaml_io import load_yaml

from benchmark.core.plugins import BUILTIN_ORIGIN, PluginEntry, PluginRegistry

DATASETS = {
    "synthetic:test": "embedded, procedural: 4 subjects (2 male, 2 female), 170 sequences >= 4 s at 50 fps (datasets/synthetic.md)",
    "synthetic:train": "embedded, procedural: disjoint subjects and seeds, for training the embedded priors",
    "synthetic:val": "embedded, procedural: validation split for the embedded priors",
    "amass": "user data: AMASS .npz (SMPL-H / SMPL-X), --data amass=/path (datasets/amass.md)",
    "bvh": "user data: BVH (CMU conversion), converted with `python -m benchmark data convert`",
    "scans": "user data: captured point clouds, one folder per sequence (per-frame PLY/OBJ/NPZ + timestamps.txt): "
             "run table1 --data scans=DIR [--up z] [--units mm]; complete DIR/SEQ --prior NAME",
}


TABLES_GROUP = "benchmark.tables"  # entry points: table name -> "package:spec.yaml" (docs/adding-a-table.md)


class TableEntry(PluginEntry):
    """Where a table spec lives: a YAML file in a package (``"package:file.yaml"``, read through
    importlib.resources) or a path (``"/path/to/file.yaml"``). ``origin``: "built-in"
    (benchmark/tables/), the distribution that registered it, or "runtime"."""

    kind = "table"

    def read_text(self) -> str:
        if _RESOURCE.fullmatch(self.target) and not Path(self.target).is_file():
            package, _, resource = self.target.partition(":")
            return resources.files(package).joinpath(resource).read_text()
        return Path(self.target).read_text()


_RESOURCE = re.compile(r"[A-Za-z_][\w.]*:[\w.\-/]+")


def _builtin_tables() -> dict[str, str]:
    """The project's own specs (``benchmark/tables/*.yaml``), seeded before the entry-point group
    ``benchmark.tables`` (specs of other packages)."""
    return {p.name[:-5]: f"benchmark.tables:{p.name}"
            for p in resources.files("benchmark.tables").iterdir() if p.name.endswith(".yaml")}


TABLES = PluginRegistry(TableEntry, TABLES_GROUP, builtin=_builtin_tables)


table_registry = TABLES.all  # name -> TableEntry
table_names = TABLES.names


def register_table(name: str, target, origin: str = "runtime") -> None:
    """Register a table spec at run time (tests, notebooks): ``target`` is the spec's path or
    ``"package:file.yaml"``. Its ``protocol`` must be registered too
    (:func:`benchmark.protocols.registry.register`)."""
    TABLES.register(name, str(target), origin)
    load_table_spec.cache_clear()


def unregister_table(name: str) -> None:
    TABLES.unregister(name)
    load_table_spec.cache_clear()


@lru_cache(maxsize=None)
def load_table_spec(name: str) -> dict:
    entry = TABLES.lookup(name, matches=1, listed="Known")
    spec = load_yaml(entry.read_text(), f"table spec {entry.target}")
    if entry.origin == BUILTIN_ORIGIN:
        return spec
    where = f"table {name!r} ({entry.target}, from {entry.origin})"
    if not isinstance(spec, dict) or spec.get("name") != name:
        got = spec.get("name") if isinstance(spec, dict) else type(spec).__name__
        raise ValueError(f"{where}: the spec's 'name' field must be {name!r}, got {got!r}")
    spec["_source"] = entry.target  # for error messages; keys starting with "_" are not rules
    return spec


DEFAULT_PRIORS = ("no-prior", "vposer-slerp")  # when a table spec has no ``default_priors``


def default_priors(spec: dict) -> list[str]:
    """The rows a table runs without --prior: the spec's ``default_priors``, else DEFAULT_PRIORS."""
    return list(spec.get("default_priors") or DEFAULT_PRIORS)


@lru_cache(maxsize=None)
def load_profiles() -> dict:
    return load_yaml(resources.files("benchmark").joinpath("profiles.yaml").read_text(), "benchmark/profiles.yaml")


def get_profile(name: str, table: str | None = None) -> dict:
    """A profile's sizes, with the profile's per-table overrides (``tables: {TABLE: {...}}`` in
    profiles.yaml) applied for ``table``: some tables cost far more per sequence than others."""
    profiles = load_profiles()
    if name not in profiles:
        raise KeyError(f"unknown profile {name!r}; known: {', '.join(profiles)}")
    prof = dict(profiles[name])
    overrides = prof.pop("tables", None) or {}
    if table is not None and table in overrides:
        prof.update(overrides[table])
        prof["table_override"] = table
    return {"name": name, **prof}


def table_rows():
    rows = []
    for name in table_names():
        entry = table_registry()[name]
        if "clash" in entry.extra:
            rows.append((name, f"NAME CLASH: {entry.error}"))
            continue
        try:
            spec = load_table_spec(name)
        except Exception as exc:  # a broken plug-in's spec must not take `list` down
            rows.append((name, f"LOAD ERROR ({entry.origin}, {entry.target}): {type(exc).__name__}: {exc}"))
            continue
        where = "" if entry.origin == BUILTIN_ORIGIN else f"  [{entry.origin}: {entry.target}]"
        rows.append((name, f"{spec.get('title', name)}{where}"))
    return rows


def _plugin_rows(entries, describe) -> list[tuple[str, str]]:
    """A row per registered plug-in: ``describe(obj)`` and where it comes from, or its load error."""
    rows = []
    for name, entry in sorted(entries.items()):
        obj = entry.load()
        if "clash" in entry.extra:  # two packages register the name: only using it fails
            rows.append((name, f"NAME CLASH: {entry.error}"))
        elif obj is None:
            rows.append((name, f"LOAD ERROR ({entry.origin}, {entry.target}): {entry.error}"))
        else:
            rows.append((name, f"{describe(obj)}  [{entry.origin}: {entry.target}]"))
    return rows


def prior_rows():
    from benchmark.run.registry import registry
    from priors.base import PriorAdapter

    return _plugin_rows(registry(), lambda cls: cls.paper if isinstance(cls, type) and issubclass(cls, PriorAdapter)
                        else "(not a priors.base.PriorAdapter)")


def protocol_rows():
    from benchmark.protocols.registry import registry

    return _plugin_rows(registry(), lambda cls: ((getattr(cls, "__doc__", None) or "").strip().splitlines() or [""])[0])


def dataset_rows():
    return list(DATASETS.items())


def profile_rows():
    return [(n, p["description"]) for n, p in load_profiles().items()]
