"""The protocol registry: entry points in the group ``benchmark.protocols``, loaded lazily.

A table spec's ``protocol`` field names a protocol; this registry maps the name to a
:class:`benchmark.protocols.base.Protocol` subclass. Like the prior registry
(:mod:`benchmark.run.registry`) it is a :class:`benchmark.core.plugins.PluginRegistry`: an entry
point is a ``"module:Class"`` placeholder imported on first use; a protocol that fails to import is
reported by name, never takes the CLI down; the project's own protocols register through the same
group (``pyproject.toml``) as another package's would; :func:`register` / :func:`unregister` add
and remove one for the running process (tests, notebooks).

The project's own protocols are also known without their entry points (:data:`BUILTIN`): a
checkout installed (``pip install -e .``) before a protocol was added to ``pyproject.toml`` has
stale package metadata, and still runs every table of its own.
"""

from __future__ import annotations

from benchmark.core.plugins import PluginEntry, PluginRegistry

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


class ProtocolEntry(PluginEntry):
    """A registered protocol: ``target`` is ``"module:Class"``, ``origin`` the distribution that
    registered it, "built-in", or "runtime"."""

    kind = "protocol"


PROTOCOLS = PluginRegistry(ProtocolEntry, GROUP, fallback=BUILTIN)
# the registry's API: registry() (name -> ProtocolEntry), register(name, target, origin="runtime") at
# run time (tests, notebooks; target is a class or "module:Class"), unregister(name)
registry = PROTOCOLS.all
register = PROTOCOLS.register
unregister = PROTOCOLS.unregister
protocol_names = PROTOCOLS.names


def get_protocol_class(name: str) -> type:
    cls = PROTOCOLS.load(name)
    if not isinstance(cls, type) or not all(callable(getattr(cls, m, None)) for m in ("make_source", "run_unit")):
        entry = PROTOCOLS.lookup(name)
        raise TypeError(f"protocol {name!r} ({entry.target}, from {entry.origin}) is not a protocol class: it needs "
                        "make_source and run_unit (subclass benchmark.protocols.base.Protocol)")
    return cls


def make_protocol(name: str):
    """An instance of the registered protocol ``name``."""
    return get_protocol_class(name)()
