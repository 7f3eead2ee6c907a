"""check-prior (:func:`benchmark.tools.conformance.check_prior`) over every registered prior, in the
default suite: a prior whose adapter drifts from the contract (``priors/base.py``) fails here, not
first in a table run. Each check is the full kit (instantiate, declarations, latents, decode,
gradients, dependence on the latents, finite losses, determinism) with 2 optimiser steps."""

from __future__ import annotations

import pytest

from benchmark.tools.conformance import check_prior
from benchmark.run.registry import prior_names


@pytest.mark.parametrize("name", prior_names())
def test_check_prior_passes(name, capsys):
    ok = check_prior(name, steps=2)
    out = capsys.readouterr().out
    assert ok, out
    assert out.rstrip().endswith("PASS"), out
