"""The project's own protocols, as :class:`~benchmark.protocols.base.Protocol` classes.

Each is a thin wrapper of its protocol module's functions (``make_source``, ``run_unit`` and, where
the module has them, ``load_motions``, ``na_reason``, ``unit_cost``); the module docstrings give the
rules in full. They register in the entry-point group ``benchmark.protocols`` (``pyproject.toml``),
exactly as another package's protocol would; importing this module imports none of the protocol
modules (each is imported on a protocol's first use).
"""

from __future__ import annotations

from benchmark.protocols.base import Protocol


class ModuleProtocol(Protocol):
    """A protocol whose rules are the functions of one module (:meth:`functions`)."""

    def functions(self):
        """The protocol module."""
        raise NotImplementedError

    def load_motions(self, spec: dict, data: str | None, body) -> dict:
        module = self.functions()
        if hasattr(module, "load_motions"):
            return module.load_motions(spec, data, body)
        return super().load_motions(spec, data, body)

    def make_source(self, spec: dict, body, motions_by_id: dict, seed: int):
        return self.functions().make_source(spec, body, motions_by_id, seed)

    def na_reason(self, spec: dict, adapter) -> str | None:
        module = self.functions()
        return module.na_reason(spec, adapter) if hasattr(module, "na_reason") else None

    def run_unit(self, unit, spec: dict, profile: dict, adapter, body, source, device) -> dict:
        return self.functions().run_unit(unit, spec, profile, adapter, body, source, device)

    def unit_cost(self, unit, spec: dict, profile: dict) -> float:
        module = self.functions()
        if hasattr(module, "unit_cost"):
            return float(module.unit_cost(unit, spec, profile))
        return super().unit_cost(unit, spec, profile)


class CompletionProtocol(ModuleProtocol):
    """Completion of sparse point-cloud sequences (table1; benchmark/protocols/completion_unit.py)."""

    name = "completion"

    def functions(self):
        from benchmark.protocols import completion_unit

        return completion_unit


class SlsProtocol(ModuleProtocol):
    """Completion of one-cycle sequences with landmarks (sls; benchmark/protocols/sls.py)."""

    name = "sls"

    def functions(self):
        from benchmark.protocols import sls

        return sls


class DenoiseProtocol(ModuleProtocol):
    """Denoising of noisy motion capture (denoise; benchmark/protocols/denoise.py)."""

    name = "denoise"

    def functions(self):
        from benchmark.protocols import denoise

        return denoise


class InbetweenProtocol(ModuleProtocol):
    """Filling a gap between key frames (inbetween; benchmark/protocols/inbetween.py)."""

    name = "inbetween"

    def functions(self):
        from benchmark.protocols import inbetween

        return inbetween


class ReconstructionProtocol(ModuleProtocol):
    """Encode, then decode (reconstruction; benchmark/protocols/reconstruction.py)."""

    name = "reconstruction"

    def functions(self):
        from benchmark.protocols import reconstruction

        return reconstruction
