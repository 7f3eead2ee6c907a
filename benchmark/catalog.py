"""What exists: tables, priors, datasets, profiles (for ``python -m benchmark list``)."""

from __future__ import annotations

from functools import lru_cache
from importlib import resources

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


@lru_cache(maxsize=None)
def load_table_spec(name: str) -> dict:
    names = table_names()
    if name not in names:
        import difflib

        close = difflib.get_close_matches(name, names, n=1)
        hint = f" Did you mean {close[0]!r}?" if close else ""
        raise KeyError(f"unknown table {name!r}.{hint} Known: {', '.join(names)}")
    text = resources.files("benchmark.tables").joinpath(f"{name}.yaml").read_text()
    return yaml.safe_load(text)


def table_names() -> list[str]:
    return sorted(p.name[:-5] for p in resources.files("benchmark.tables").iterdir() if p.name.endswith(".yaml"))


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
    return [(n, load_table_spec(n)["title"]) for n in table_names()]


def prior_rows():
    from benchmark.registry import registry

    rows = []
    for name, entry in sorted(registry().items()):
        cls = entry.load()
        if cls is None:
            rows.append((name, f"LOAD ERROR ({entry.origin}, {entry.target}): {entry.error}"))
        else:
            paper = getattr(cls, "paper", "")
            rows.append((name, f"{paper}  [{entry.origin}: {entry.target}]"))
    return rows


def dataset_rows():
    return list(DATASETS.items())


def profile_rows():
    return [(n, p["description"]) for n, p in load_profiles().items()]
