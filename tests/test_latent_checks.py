"""The prior contract checked where a fit uses it (benchmark.protocols.latent_checks): a hook that
breaks it stops the fit with one line naming the prior, the hook and the key, never a KeyError
inside decode, a shape error blamed on decode, or an encoder's misspelt keys dropped silently."""

import types

import pytest
import torch

from benchmark.protocols.fit_state import _check_decoded
from benchmark.protocols.latent_checks import check_latents, prior_values
from priors.base import Decoded

PRIOR = types.SimpleNamespace(name="mine")
LAYOUT = {"key": torch.zeros(2, 5, 21, 6)}


def test_latents_must_be_init_latents_keys_and_shapes():
    check_latents(PRIOR, {"key": torch.ones(2, 5, 21, 6)}, LAYOUT, "mean_latents")
    cases = [
        ({"keys": torch.ones(2, 5, 21, 6)}, {}, r"prior 'mine': mean_latents returned the keys \['keys'\], expected \['key'\]"),
        ({"key": torch.ones(2, 1, 21, 6)}, {}, r"mean_latents's 'key' has shape \(2, 1, 21, 6\), expected \(2, 5, 21, 6\)"),
        ({"key": torch.full((2, 5, 21, 6), float("nan"))}, {}, r"'key' holds NaN or inf"),
        ([torch.ones(2)], {}, r"must return a dict of latent tensors keyed like init_latents \(\['key'\]\)"),
        # an encoder may return some latents (the others keep their start), but not none of them
        ({"keys": torch.ones(2, 5, 21, 6)}, {"partial": True, "extra": True}, r"expected some of \['key'\]"),
    ]
    for got, kw, message in cases:
        with pytest.raises(ValueError, match=message):
            check_latents(PRIOR, got, LAYOUT, "mean_latents", **kw)
    # keys beyond the latents are an encoder's own (a canonical frame's heading): allowed where said
    check_latents(PRIOR, {"key": torch.ones(2, 5, 21, 6), "heading": torch.ones(2, 1)}, LAYOUT, "encode_motion",
                  extra=True)


def test_prior_term_is_one_value_per_sequence():
    latents = {"key": torch.zeros(3, 4)}
    for term, ok in ((lambda z: z["key"].mean(-1), True), (lambda z: z["key"].mean(-1, keepdim=True), False),
                     (lambda z: z["key"], False), (lambda z: z["key"].sum(), False)):
        adapter = types.SimpleNamespace(name="mine", prior_term=term)
        if ok:
            assert prior_values(adapter, latents).shape == (3,)
        else:
            with pytest.raises(ValueError, match=r"prior 'mine': prior_term returned .*, expected shape \(3,\)"):
                prior_values(adapter, latents)


def test_decoded_nan_is_named_as_the_priors():
    t = torch.zeros(1, 4)
    rot = torch.eye(3).expand(1, 4, 22, 3, 3).clone()
    _check_decoded(PRIOR, Decoded(rot, None), t)
    rot[0, 2, 5, 0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"prior 'mine': decode returned NaN or inf"):
        _check_decoded(PRIOR, Decoded(rot, None), t)
