"""What exists: tables, priors, datasets, profiles (for ``python -m benchmark list``).

Table specs: the project's own ``benchmark/tables/*.yaml``, the specs other packages register in
the entry-point group ``benchmark.tables`` (a table name -> ``"package:file.yaml"``), and those
registered at run time (:func:`register_table`). A spec's ``protocol`` field names its protocol in
:mod:`benchmark.protocols.registry` (docs/adding-a-table.md).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from importlib.metadata import entry_points
from pathlib import Path

import yaml

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
BUILTIN_ORIGIN = "built-in"


@dataclass
class TableEntry:
    """Where a table spec lives: a YAML file in a package (``"package:file.yaml"``, read through
    importlib.resources) or a path (``"/path/to/file.yaml"``)."""

    name: str
    target: str
    origin: str  # "built-in" (benchmark/tables/), the distribution that registered it, or "runtime"

    def read_text(self) -> str:
        if _RESOURCE.fullmatch(self.target) and not Path(self.target).is_file():
            package, _, resource = self.target.partition(":")
            return resources.files(package).joinpath(resource).read_text()
        return Path(self.target).read_text()


_RESOURCE = re.compile(r"[A-Za-z_][\w.]*:[\w.\-/]+")
_TABLES: dict[str, TableEntry] | None = None


def _discover_tables() -> dict[str, TableEntry]:
    """The project's own specs (``benchmark/tables/*.yaml``), then the entry-point group
    ``benchmark.tables`` (specs of other packages)."""
    found = {p.name[:-5]: TableEntry(p.name[:-5], f"benchmark.tables:{p.name}", BUILTIN_ORIGIN)
             for p in resources.files("benchmark.tables").iterdir() if p.name.endswith(".yaml")}
    for ep in entry_points(group=TABLES_GROUP):
        dist = getattr(ep, "dist", None)
        origin = f"{dist.name} {dist.version}" if dist is not None else "unknown"
        if ep.name in found and found[ep.name].target != ep.value:
            raise ValueError(f"table name collision: {ep.name!r} is registered by {found[ep.name].origin} "
                             f"({found[ep.name].target}) and by {origin} ({ep.value}); uninstall one of them")
        found[ep.name] = TableEntry(ep.name, ep.value, origin)
    return found


def table_registry() -> dict[str, TableEntry]:
    global _TABLES
    if _TABLES is None:
        _TABLES = _discover_tables()
    return _TABLES


def register_table(name: str, target, origin: str = "runtime") -> None:
    """Register a table spec at run time (tests, notebooks): ``target`` is the spec's path or
    ``"package:file.yaml"``. Its ``protocol`` must be registered too
    (:func:`benchmark.protocols.registry.register`)."""
    reg = table_registry()
    if name in reg:
        raise ValueError(f"table {name!r} is already registered by {reg[name].origin} ({reg[name].target})")
    reg[name] = TableEntry(name, str(target), origin)
    load_table_spec.cache_clear()


def unregister_table(name: str) -> None:
    table_registry().pop(name, None)
    load_table_spec.cache_clear()


@lru_cache(maxsize=None)
def load_table_spec(name: str) -> dict:
    names = table_names()
    if name not in names:
        import difflib

        close = difflib.get_close_matches(name, names, n=1)
        hint = f" Did you mean {close[0]!r}?" if close else ""
        raise KeyError(f"unknown table {name!r}.{hint} Known: {', '.join(names)}")
    entry = table_registry()[name]
    spec = yaml.safe_load(entry.read_text())
    if entry.origin == BUILTIN_ORIGIN:
        return spec
    where = f"table {name!r} ({entry.target}, from {entry.origin})"
    if not isinstance(spec, dict) or spec.get("name") != name:
        got = spec.get("name") if isinstance(spec, dict) else type(spec).__name__
        raise ValueError(f"{where}: the spec's 'name' field must be {name!r}, got {got!r}")
    spec["_source"] = entry.target  # for error messages; keys starting with "_" are not rules
    return spec


def table_names() -> list[str]:
    return sorted(table_registry())


@lru_cache(maxsize=None)
def load_profiles() -> dict:
    return yaml.safe_load(resources.files("benchmark").joinpath("profiles.yaml").read_text())


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
        try:
            spec = load_table_spec(name)
        except Exception as exc:  # a broken plug-in's spec must not take `list` down
            rows.append((name, f"LOAD ERROR ({entry.origin}, {entry.target}): {type(exc).__name__}: {exc}"))
            continue
        where = "" if entry.origin == BUILTIN_ORIGIN else f"  [{entry.origin}: {entry.target}]"
        rows.append((name, f"{spec.get('title', name)}{where}"))
    return rows


def prior_rows():
    from benchmark.run.registry import registry
    from priors.base import PriorAdapter

    rows = []
    for name, entry in sorted(registry().items()):
        cls = entry.load()
        if cls is None:
            rows.append((name, f"LOAD ERROR ({entry.origin}, {entry.target}): {entry.error}"))
        else:
            paper = cls.paper if isinstance(cls, type) and issubclass(cls, PriorAdapter) else "(not a priors.base.PriorAdapter)"
            rows.append((name, f"{paper}  [{entry.origin}: {entry.target}]"))
    return rows


def protocol_rows():
    from benchmark.protocols.registry import registry

    rows = []
    for name, entry in sorted(registry().items()):
        cls = entry.load()
        if cls is None:
            rows.append((name, f"LOAD ERROR ({entry.origin}, {entry.target}): {entry.error}"))
        else:
            doc = ((getattr(cls, "__doc__", None) or "").strip().splitlines() or [""])[0]
            rows.append((name, f"{doc}  [{entry.origin}: {entry.target}]"))
    return rows


def dataset_rows():
    return list(DATASETS.items())


def profile_rows():
    return [(n, p["description"]) for n, p in load_profiles().items()]
