"""Plug-in registries: names -> ``"module:attr"`` placeholders from an entry-point group, loaded lazily.

One piece for the three kinds the harness registers (priors, protocols, table specs). An entry
imports nothing until :meth:`PluginEntry.load`; one that fails to import is reported by name (its
error is kept, a warning logged) and never takes the CLI down. A kind subclasses
:class:`PluginEntry` (its ``kind`` names it in messages; its module's logger logs for it) and
builds a :class:`PluginRegistry` with its extras: entries of its own seeded before the entry points,
a fallback for names stale package metadata does not list, a warning when the group is empty.
"""

from __future__ import annotations

import difflib
import importlib
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from typing import ClassVar

BUILTIN_ORIGIN = "built-in"


@dataclass
class PluginEntry:
    name: str
    target: str  # "module:attr" (attr may be dotted)
    origin: str  # the distribution that registered it, "built-in", or "runtime"
    obj: object | None = None
    error: str | None = None
    extra: dict = field(default_factory=dict)

    kind: ClassVar[str] = "plugin"  # the word messages name it by

    @classmethod
    def logger(cls) -> logging.Logger:
        """The logger of the module that defines the kind (``benchmark.run.registry`` for priors)."""
        return logging.getLogger(cls.__module__)

    def load(self):
        if self.obj is None and self.error is None:
            module, _, attr = self.target.partition(":")
            try:
                obj = importlib.import_module(module)
                for part in attr.split("."):
                    obj = getattr(obj, part)
                self.obj = obj
            except Exception as exc:  # a broken plug-in must not take the harness down
                self.error = f"{type(exc).__name__}: {exc}"
                self.logger().warning("%s %r (%s) failed to load: %s", self.kind, self.name, self.target, self.error)
        return self.obj


def discover(group: str, entry_type: type[PluginEntry],
             found: dict[str, PluginEntry] | None = None) -> dict[str, PluginEntry]:
    """The entries of the entry-point group ``group`` added to ``found``. A name two distributions
    register with different targets is a clash: the name is kept, unusable (:meth:`PluginRegistry.lookup`
    raises the error naming both and the fix; ``list`` shows it), and every other name still works."""
    found = {} if found is None else found
    for ep in entry_points(group=group):
        dist = getattr(ep, "dist", None)
        origin = f"{dist.name} {dist.version}" if dist is not None else "unknown"
        prev = found.get(ep.name)
        if prev is not None and (prev.target != ep.value or "clash" in prev.extra):
            clash = list(prev.extra.get("clash") or [f"{prev.origin} ({prev.target})"])
            if f"{origin} ({ep.value})" not in clash:
                clash.append(f"{origin} ({ep.value})")
            entry = entry_type(ep.name, prev.target, prev.origin, extra={"clash": clash})
            entry.error = (f"{entry_type.kind} name collision: {ep.name!r} is registered by {' and by '.join(clash)}; "
                           "uninstall all but one of those packages (pip uninstall NAME), or rename the entry point "
                           f"in one of them (group {group!r})")
            entry_type.logger().warning("%s", entry.error)
            found[ep.name] = entry
            continue
        found[ep.name] = entry_type(ep.name, ep.value, origin)
    return found


class PluginRegistry:
    """The entries of one kind, discovered on first use; :attr:`entries` is None until then (set it
    to None to discover again).

    ``builtin``: a function returning the kind's own entries (name -> target), seeded before the
    entry points. ``fallback``: name -> target for names the entry points do not list (package
    metadata installed before they were declared). ``warn_if_empty``: warn when the group lists
    nothing (the project is not installed)."""

    def __init__(self, entry_type: type[PluginEntry], group: str, *,
                 builtin: Callable[[], Mapping[str, str]] | None = None,
                 fallback: Mapping[str, str] | None = None, warn_if_empty: bool = False):
        self.entry_type, self.group = entry_type, group
        self.builtin, self.fallback, self.warn_if_empty = builtin, fallback, warn_if_empty
        self.entries: dict[str, PluginEntry] | None = None

    @property
    def kind(self) -> str:
        return self.entry_type.kind

    def discover(self) -> dict[str, PluginEntry]:
        make, log = self.entry_type, self.entry_type.logger()
        found = {n: make(n, t, BUILTIN_ORIGIN) for n, t in (self.builtin() if self.builtin else {}).items()}
        discover(self.group, make, found)
        stale = [name for name in (self.fallback or ()) if name not in found]
        if stale:  # package metadata from before these were declared: still use them
            log.debug("%ss %s have no entry point in %r (stale package metadata: pip install -e .); "
                      "using the built-in classes", self.kind, stale, self.group)
            for name in stale:
                found[name] = make(name, self.fallback[name], BUILTIN_ORIGIN)
        if not found and self.warn_if_empty:
            log.warning("no %ss registered in entry-point group %r: is the project installed (pip install -e .)?",
                        self.kind, self.group)
        return found

    def all(self) -> dict[str, PluginEntry]:
        if self.entries is None:
            self.entries = self.discover()
        return self.entries

    def names(self) -> list[str]:
        return sorted(self.all())

    def register(self, name: str, target: str | type, origin: str = "runtime") -> None:
        """Add ``name`` for the running process: ``target`` is "module:attr" or the object itself."""
        reg = self.all()
        if name in reg:
            raise ValueError(f"{self.kind} {name!r} is already registered by {reg[name].origin} ({reg[name].target})")
        if isinstance(target, str):
            reg[name] = self.entry_type(name, target, origin)
        else:
            reg[name] = self.entry_type(name, f"{target.__module__}:{target.__qualname__}", origin, obj=target)

    def unregister(self, name: str) -> None:
        self.all().pop(name, None)

    def lookup(self, name: str, *, matches: int = 3, listed: str = "Registered") -> PluginEntry:
        """The entry of ``name``; an unknown name is a KeyError naming the close ones, a name two
        packages register (a clash) a ValueError naming both and the fix."""
        reg = self.all()
        if name not in reg:
            close = difflib.get_close_matches(str(name), list(reg), n=matches)
            hint = f" Did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
            raise KeyError(f"unknown {self.kind} {name!r}.{hint} {listed}: {', '.join(sorted(reg)) or '(none)'}")
        if "clash" in reg[name].extra:
            raise ValueError(reg[name].error)
        return reg[name]

    def load(self, name: str):
        """The object ``name`` names, imported; one that fails to import is an ImportError."""
        entry = self.lookup(name)
        obj = entry.load()
        if obj is None:
            raise ImportError(f"{self.kind} {name!r} ({entry.target}, from {entry.origin}) failed to load: {entry.error}")
        return obj
