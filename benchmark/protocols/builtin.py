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


class PlateauRuleProtocol(ModuleProtocol):
    """A protocol whose fits run the plateau step rule (table1, sls): a unit whose every fit
    converged is the same under any larger step cap, where its rules say so
    (:func:`benchmark.protocols.step_rules.cap_independent_problem`)."""

    def carry_problem(self, spec: dict) -> str | None:
        from benchmark.protocols.step_rules import cap_independent_problem

        return cap_independent_problem(spec["objective"])


class CompletionProtocol(PlateauRuleProtocol):
    """Completion of sparse point-cloud sequences (table1; benchmark/protocols/completion_unit.py)."""

    name = "completion"
    spec_keys = {
        "data": frozenset({"split", "window_s", "window_start_s", "capture_fps", "points_per_frame", "scan_noise_std",
                           "observation_offset_m"}),  # observation_offset_m: fit-check's perturbation probe
        "objective": frozenset({"data_term", "lambda_prior", "lr", "optimiser", "schedule", "step_rule", "plateau",
                                "convergence", "facing", "start_search", "start_fit", "latent_init", "shape_init", "shape_lr_scale",
                                "translation_init", "outside_observed_span", "multi_start"}),
    }

    def functions(self):
        from benchmark.protocols import completion_unit

        return completion_unit


class SlsProtocol(PlateauRuleProtocol):
    """Completion of one-cycle sequences with landmarks (sls; benchmark/protocols/sls.py)."""

    name = "sls"
    spec_keys = {
        "data": frozenset({"split", "source_fps", "cycles", "cycle_min_s", "cycle_max_s", "cycles_per_motion", "gait_starts",
                           "anchors", "align", "points_per_scan", "scan_noise_std", "landmarks", "landmark_noise_std",
                           "observation_offset_m"}),  # the perturbation probe, as table1's
        "objective": frozenset({"form", "dense", "mocap", "time", "time_term", "adaptive", "lambda_prior", "optimiser", "lr",
                                "lr_final_fraction", "schedule", "step_rule", "plateau", "start_search", "start_fit", "variables",
                                "facing", "shape_lr_scale", "latent_init", "convergence", "init_points",
                                "init_scan_points", "decoding"}),
    }

    def functions(self):
        from benchmark.protocols import sls

        return sls


class DenoiseProtocol(ModuleProtocol):
    """Denoising of noisy motion capture (denoise; benchmark/protocols/denoise.py)."""

    name = "denoise"
    spec_keys = {
        "data": frozenset({"split", "fps", "window_s", "window_start_s", "shape", "observations", "noise", "num_markers"}),
        "objective": frozenset({"data_term", "lambda_prior", "lr", "optimiser", "schedule", "init", "regression",
                                "optimisation", "step_rule", "plateau", "denoiser_iterations"}),
    }

    def functions(self):
        from benchmark.protocols import denoise

        return denoise


class InbetweenProtocol(ModuleProtocol):
    """Filling a gap between key frames (inbetween; benchmark/protocols/inbetween.py)."""

    name = "inbetween"
    spec_keys = {
        "data": frozenset({"split", "fps", "window_s", "window_start_s", "shape", "observations", "context_frames"}),
        "objective": frozenset({"data_term", "lambda_prior", "lr", "optimiser", "schedule", "init", "rigid",
                                "rotation_weight_mm2", "baseline", "step_rule", "plateau"}),
    }

    def functions(self):
        from benchmark.protocols import inbetween

        return inbetween


class ReconstructionProtocol(ModuleProtocol):
    """Encode, then decode (reconstruction; benchmark/protocols/reconstruction.py)."""

    name = "reconstruction"
    spec_keys = {
        "data": frozenset({"split", "fps", "window_s", "window_start_s", "shape"}),
        "objective": frozenset({"method", "no_encoder", "not_encoded"}),
    }

    def functions(self):
        from benchmark.protocols import reconstruction

        return reconstruction
