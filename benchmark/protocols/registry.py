"""The protocol registry: entry points in the group ``benchmark.protocols``, loaded lazily.

A table spec's ``protocol`` field names a protocol; this registry maps the name to a
:class:`benchmark.protocols.base.Protocol` subclass. It mirrors the prior registry
(:mod:`benchmark.run.registry`): an entry point is a ``"module:Class"`` placeholder imported on first
use; a protocol that fails to import is reported by name, never takes the CLI down; the project's
own protocols register through the same group (``pyproject.toml``) as another package's would;
:func:`register` / :func:`unregister` add and remove one for the running process (tests,
notebooks).

The project's own protocols are also known without their entry points (:data:`BUILTIN`): a
checkout installed (``pip install -e .``) before a protocol was added to ``pyproject.toml`` has
stale package metadata, and still runs every table of its own.
"""

from __future__ import annotations

import difflib
import importlib
import logging
from dataclasses import dataclass
from importlib.metadata import entry_points

log = logging.getLogger(__name__)

GROUP = "benchmark.protocols"

# the project's own protocols, as pyproject.toml registers them (tests/test_adding_a_table.py
# checks that the two agree); used for names the installed package metadata does not list
BUILTIN = {
    "completion": "benchmark.protocols.builtin:CompletionProtocol",
    "sls": "benchmark.protocols.builtin:SlsProtocol",
    "denoise": "benchmark.protocols.builtin:DenoiseProtocol",
    "inbetween": "benchmark.protocols.builtin:InbetweenProtocol",
    "reconstruction": "benchmark.protocols.builtin:ReconstructionProtocol",
}
BUILTIN_ORIGIN = "built-in"


@dataclass
class ProtocolEntry:
    name: str
    target: str  # "module:Class"
    origin: str  # distribution that registered it, "built-in", or "runtime"
    obj: type | None = None
    error: str | None = None

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
                log.warning("protocol %r (%s) failed to load: %s", self.name, self.target, self.error)
        return self.obj


_REGISTRY: dict[str, ProtocolEntry] | None = None


def _discover() -> dict[str, ProtocolEntry]:
    found: dict[str, ProtocolEntry] = {}
    for ep in entry_points(group=GROUP):
        origin = getattr(ep, "dist", None)
        origin = f"{origin.name} {origin.version}" if origin is not None else "unknown"
        if ep.name in found and found[ep.name].target != ep.value:
            raise ValueError(
                f"protocol name collision: {ep.name!r} is registered by {found[ep.name].origin} "
                f"({found[ep.name].target}) and by {origin} ({ep.value}); uninstall one of them")
        found[ep.name] = ProtocolEntry(ep.name, ep.value, origin)
    stale = [name for name in BUILTIN if name not in found]
    if stale:  # package metadata from before these protocols were declared: still run them
        log.debug("protocols %s have no entry point in %r (stale package metadata: pip install -e .); "
                  "using the built-in classes", stale, GROUP)
        for name in stale:
            found[name] = ProtocolEntry(name, BUILTIN[name], BUILTIN_ORIGIN)
    return found


def registry() -> dict[str, ProtocolEntry]:
    global _REGISTRY
    if _REGISTRY is None:
        _REGISTRY = _discover()
    return _REGISTRY


def register(name: str, target: str | type, origin: str = "runtime") -> None:
    """Register a protocol at run time (tests, notebooks). ``target`` is a class or "module:Class"."""
    reg = registry()
    if name in reg:
        raise ValueError(f"protocol {name!r} is already registered by {reg[name].origin} ({reg[name].target})")
    if isinstance(target, str):
        reg[name] = ProtocolEntry(name, target, origin)
    else:
        reg[name] = ProtocolEntry(name, f"{target.__module__}:{target.__qualname__}", origin, obj=target)


def unregister(name: str) -> None:
    registry().pop(name, None)


def get_protocol_class(name: str) -> type:
    reg = registry()
    if name not in reg:
        close = difflib.get_close_matches(str(name), list(reg), n=3)
        hint = f" Did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
        raise KeyError(f"unknown protocol {name!r}.{hint} Registered: {', '.join(sorted(reg)) or '(none)'}")
    entry = reg[name]
    cls = entry.load()
    if cls is None:
        raise ImportError(f"protocol {name!r} ({entry.target}, from {entry.origin}) failed to load: {entry.error}")
    if not isinstance(cls, type) or not all(callable(getattr(cls, m, None)) for m in ("make_source", "run_unit")):
        raise TypeError(f"protocol {name!r} ({entry.target}, from {entry.origin}) is not a protocol class: it needs "
                        "make_source and run_unit (subclass benchmark.protocols.base.Protocol)")
    return cls


def make_protocol(name: str):
    """An instance of the registered protocol ``name``."""
    return get_protocol_class(name)()


def protocol_names() -> list[str]:
    return sorted(registry())
