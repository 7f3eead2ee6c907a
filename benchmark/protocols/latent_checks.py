"""What a fit takes from an adapter's hooks, checked where it takes it (the prior contract,
:mod:`priors.base`): the latents of ``mean_latents`` and ``encode_motion`` against the layout of the
adapter's own ``init_latents`` (keys, shapes, finite values), and ``prior_term``'s (B,) values.

A hook that breaks the contract stops the fit with one line naming the prior, the hook, the key and
what was expected, where it happens, instead of a KeyError inside ``decode``, a shape error blamed
on ``decode``, an index error inside the step rule, or, worst, an encoder whose misspelt keys are
dropped without a word while the start is recorded as encoded. ``check-prior``
(:mod:`benchmark.tools.conformance`) runs the same checks on a toy batch.
"""

from __future__ import annotations

from typing import Mapping

import torch

from priors.base import PriorAdapter


def check_latents(adapter: PriorAdapter, got, layout: Mapping[str, torch.Tensor], hook: str,
                  partial: bool = False, shapes: bool = True, extra: bool = False) -> None:
    """ValueError unless ``got`` (what ``hook`` returned) is a dict of finite tensors with the keys of
    ``layout`` (the adapter's ``init_latents`` for the same batch; with ``partial``, some of them,
    at least one) and, with ``shapes``, their shapes. ``extra``: keys beyond the latents are allowed
    (an encoder's, e.g. the canonical frame's heading and offset, which a fit frees itself)."""
    name = getattr(adapter, "name", type(adapter).__name__)
    want = sorted(layout)
    if not isinstance(got, Mapping) or not all(isinstance(k, str) and torch.is_tensor(v) for k, v in got.items()):
        raise ValueError(f"prior {name!r}: {hook} must return a dict of latent tensors keyed like init_latents "
                         f"({want}); got {type(got).__name__}")
    unknown = [] if extra else sorted(set(got) - set(layout))
    missing = [] if partial else sorted(set(layout) - set(got))
    if unknown or missing or not set(got) & set(layout):
        what = f"some of {want}" if partial else f"{want}"
        raise ValueError(f"prior {name!r}: {hook} returned the keys {sorted(got)}, expected {what} (the keys of its "
                         f"init_latents){f'; unknown: {unknown}' if unknown else ''}")
    for k, v in got.items():
        if k not in layout:
            continue
        if shapes and v.shape != layout[k].shape:
            raise ValueError(f"prior {name!r}: {hook}'s {k!r} has shape {tuple(v.shape)}, expected "
                             f"{tuple(layout[k].shape)} (as init_latents' for the same batch)")
        if v.is_floating_point() and not bool(torch.isfinite(v).all()):
            raise ValueError(f"prior {name!r}: {hook}'s {k!r} holds NaN or inf")


def prior_values(adapter: PriorAdapter, latents: Mapping[str, torch.Tensor]) -> torch.Tensor:
    """``adapter.prior_term(latents)``, checked: one value per sequence, shape (B,)."""
    value = adapter.prior_term(latents)
    batch = next(iter(latents.values())).shape[0] if latents else None
    if not torch.is_tensor(value) or (batch is not None and tuple(value.shape) != (batch,)):
        got = tuple(value.shape) if torch.is_tensor(value) else type(value).__name__
        raise ValueError(f"prior {adapter.name!r}: prior_term returned {got}, expected shape ({batch},): one value "
                         "per sequence of the batch (e.g. a mean over frames and dimensions, without keepdim)")
    return value
