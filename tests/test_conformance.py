"""The conformance kit (``check-prior``) fails adapters that are broken in ways a fit would hide."""

from __future__ import annotations

import torch

from benchmark.tools.conformance import check_prior
from benchmark.run.registry import register, unregister
from priors.base import Decoded
from priors.no_prior import NoPrior


class IgnoresItsLatents(NoPrior):
    """Decodes the rest pose whatever the latents; its prior term still gives the latents a gradient,
    so a gradient check on data + prior terms passes it."""

    name = "ignores-latents"

    def decode(self, latents, timestamps, shape=None):
        pose = latents["pose"]
        B, n = pose.shape[:2]
        eye = torch.eye(3, dtype=pose.dtype, device=pose.device)
        return Decoded(rotations=eye.expand(B, n, 22, 3, 3).clone())

    def prior_term(self, latents):
        return latents["pose"].pow(2).flatten(1).sum(1)


def test_check_prior_fails_a_decoder_that_ignores_its_latents(capsys):
    register(IgnoresItsLatents.name, IgnoresItsLatents)
    try:
        ok = check_prior(IgnoresItsLatents.name, steps=2, verbose=True)
    finally:
        unregister(IgnoresItsLatents.name)
    out = capsys.readouterr().out
    assert not ok and out.rstrip().endswith("FAIL"), out
    assert "[FAIL] 100 pts / 5 fps: gradients reach the latents" in out
    assert "does not depend on latents ['pose']" in out
    assert "[FAIL] 100 pts / 5 fps: decoded motion depends on the latents" in out
    assert "leaves the decoded motion unchanged" in out


def test_check_prior_passes_no_prior_with_the_dependence_checks(capsys):
    assert check_prior("no-prior", steps=2, verbose=True)
    out = capsys.readouterr().out
    assert "[PASS] 1000 pts / 10 fps: decoded motion depends on the latents" in out
