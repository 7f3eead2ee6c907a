"""The prior registry: entry points in the group ``benchmark.priors``, loaded lazily.

Registering imports nothing heavy: an entry point is a ``"module:Class"`` placeholder that is
imported on first use. A plug-in that fails to import is reported by name (``list`` shows the
error) and skipped; it never takes the CLI down. The project's own priors register through the
same group (``pyproject.toml``), exactly like a third-party package would.
"""

from __future__ import annotations

import difflib
import importlib
import logging
from dataclasses import dataclass, field
from importlib.metadata import entry_points

log = logging.getLogger(__name__)

GROUP = "benchmark.priors"


@dataclass
class PriorEntry:
    name: str
    target: str  # "module:Class"
    origin: str  # distribution that registered it, or "runtime"
    obj: object | None = None
    error: str | None = None
    extra: dict = field(default_factory=dict)

    def load(self):
        if self.obj is None and self.error is None:
            module, _, attr = self.target.partition(":")
            try:
                self.obj = getattr(importlib.import_module(module), attr)
            except Exception as exc:  # a broken plug-in must not take the harness down
                self.error = f"{type(exc).__name__}: {exc}"
                log.warning("prior %r (%s) failed to load: %s", self.name, self.target, self.error)
        return self.obj


_REGISTRY: dict[str, PriorEntry] | None = None


def _discover() -> dict[str, PriorEntry]:
    found: dict[str, PriorEntry] = {}
    for ep in entry_points(group=GROUP):
        origin = getattr(ep, "dist", None)
        origin = f"{origin.name} {origin.version}" if origin is not None else "unknown"
        if ep.name in found and found[ep.name].target != ep.value:
            raise ValueError(
                f"prior name collision: {ep.name!r} is registered by {found[ep.name].origin} ({found[ep.name].target}) "
                f"and by {origin} ({ep.value}); uninstall one of them"
            )
        found[ep.name] = PriorEntry(ep.name, ep.value, origin)
    if not found:
        log.warning("no priors registered in entry-point group %r: is the project installed (pip install -e .)?", GROUP)
    return found


def registry() -> dict[str, PriorEntry]:
    global _REGISTRY
    if _REGISTRY is None:
        _REGISTRY = _discover()
    return _REGISTRY


def register(name: str, target: str | type, origin: str = "runtime") -> None:
    """Register a prior at run time (tests, notebooks). ``target`` is a class or "module:Class"."""
    reg = registry()
    if name in reg:
        raise ValueError(f"prior {name!r} is already registered by {reg[name].origin} ({reg[name].target})")
    if isinstance(target, str):
        reg[name] = PriorEntry(name, target, origin)
    else:
        reg[name] = PriorEntry(name, f"{target.__module__}:{target.__qualname__}", origin, obj=target)


def unregister(name: str) -> None:
    registry().pop(name, None)


def get_prior_class(name: str):
    reg = registry()
    if name not in reg:
        close = difflib.get_close_matches(name, list(reg), n=3)
        hint = f" Did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
        raise KeyError(f"unknown prior {name!r}.{hint} Registered: {', '.join(sorted(reg)) or '(none)'}")
    entry = reg[name]
    cls = entry.load()
    if cls is None:
        raise ImportError(f"prior {name!r} ({entry.target}, from {entry.origin}) failed to load: {entry.error}")
    return cls


def prior_names() -> list[str]:
    return sorted(registry())


def make_adapter(name: str, size: str = "embedded", weights: str | None = None, device: str = "cpu"):
    """Construct the registered prior ``name`` (``size``: "embedded" or "paper"; ``weights``: a
    checkpoint path or None for the embedded weights), moved to ``device`` and in eval mode."""
    cls = get_prior_class(name)
    adapter = cls(size=size, weights=weights, device=device)
    return adapter.to(device).eval()
