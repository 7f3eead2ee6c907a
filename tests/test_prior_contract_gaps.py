"""Mistakes a prior author plausibly makes, each of which used to crash with a bare torch error, pass
the conformance kit and then break table1, or give a silent wrong number: each is now named by the
harness (the prior, the hook or declaration, the fix). One small adapter, varied per case."""

from __future__ import annotations

import pytest
import torch

from benchmark.core.rotations import matrix_to_sixd, sixd_to_matrix
from benchmark.protocols.fit_state import FitState, body_parameters
from priors.base import Decoded, FitBatch, PriorAdapter, WindowSpec


class Pull(PriorAdapter):
    """The docstring example of priors/base.py: per-frame 6D poses pulled towards the T-pose."""

    name = "pull"
    window = WindowSpec(kind="per-frame")

    def __init__(self, size="embedded", weights=None, device="cpu"):
        super().__init__(size=size, weights=weights, device=device)
        self.register_buffer("eye6", matrix_to_sixd(torch.eye(3), layout="interleaved"))

    def init_latents(self, batch: FitBatch, generator: torch.Generator):
        noise = 0.01 * torch.randn(batch.batch_size, batch.num_observed, 21, 6, generator=generator)
        return {"pose": self.eye6 + noise.to(self.device)}

    def decode(self, latents, timestamps, shape=None):
        body = sixd_to_matrix(latents["pose"], layout="interleaved")
        root = torch.eye(3, dtype=body.dtype, device=body.device).expand(*body.shape[:2], 1, 3, 3)
        return Decoded(rotations=torch.cat([root, body], dim=2))

    def prior_term(self, latents):
        return (latents["pose"] - self.eye6).square().sum((-1, -2)).mean(-1)


def _state(adapter, B=1, n=4):
    t = (torch.arange(n, dtype=torch.float64) / 5)[None].expand(B, n)
    batch = FitBatch(points=torch.zeros(B, n, 1, 3), lengths=torch.ones(B, n, dtype=torch.long), timestamps=t,
                     window_s=1.0, output_timestamps=t)
    latents = {k: v.requires_grad_(v.is_floating_point()) for k, v in adapter.init_latents(batch, torch.Generator()).items()}
    return FitState(adapter=adapter, latents=latents, shape_param=torch.zeros(B, 6), obs_t=t, window_s=1.0)


def test_decode_in_float64_is_named_not_a_dtype_error_inside_the_body():
    class Float64(Pull):
        def decode(self, latents, timestamps, shape=None):
            return Decoded(rotations=super().decode(latents, timestamps, shape).rotations.double())

    st = _state(Float64())
    with pytest.raises(ValueError, match=r"prior 'pull': decode returned rotations as torch.float64 on cpu, "
                                         r"expected torch.float32 on cpu .*cast"):
        body_parameters(st, st.obs_t, observed=True)
    body_parameters(_state(Pull()), st.obs_t, observed=True)  # the example itself passes


def test_decode_returning_a_tuple_is_named():
    class Pair(Pull):
        def decode(self, latents, timestamps, shape=None):
            return super().decode(latents, timestamps, shape).rotations, None

    st = _state(Pair())
    with pytest.raises(ValueError, match=r"prior 'pull': decode returned tuple, expected a priors.base.Decoded"):
        body_parameters(st, st.obs_t, observed=True)


def test_encodes_translation_without_a_decoded_translation_is_named():
    class NoTrans(Pull):
        encodes_translation = True

    st = _state(NoTrans())
    st.offset = torch.zeros(1, 3)  # what init_state frees for a prior that encodes translation
    with pytest.raises(ValueError, match=r"prior 'pull' declares encodes_translation = True but decode returned "
                                         r"trans=None.*or declare encodes_translation = False"):
        body_parameters(st, st.obs_t, observed=True)


def test_a_frozen_network_that_is_no_submodule_is_named_as_the_declaration():
    from benchmark.run.registry import make_adapter, register, unregister

    class WrongFrozen(Pull):
        frozen_network = "model"  # the network is self.net

        def __init__(self, size="embedded", weights=None, device="cpu"):
            super().__init__(size=size, weights=weights, device=device)
            self.net = torch.nn.Linear(3, 3)

    register("wrong-frozen", WrongFrozen)
    try:
        with pytest.raises(ValueError, match=r"prior 'pull' declares frozen_network = 'model', but has no submodule "
                                             r"of that name .*e.g. self.net = ... and frozen_network = 'net'"):
            make_adapter("wrong-frozen")
    finally:
        unregister("wrong-frozen")
