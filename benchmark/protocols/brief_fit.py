"""The brief fits of the limb start search (:mod:`benchmark.protocols.start_search`) under
``objective.start_fit``.

The search fits many start hypotheses for a few steps on a subset of the observation and keeps, per
frame, the one with the lowest data term. ``start_fit`` says on which data term and by which
optimiser: "exact" (table1 versions 4-7): the Chamfer, by Adam at the fit's rate; "smooth" (a
version 8 candidate): the soft-min Chamfer at START_SOFTMIN_M (:mod:`benchmark.metrics.soft_chamfer`),
smooth where the Chamfer's nearest neighbours change, by the batched L-BFGS
(:mod:`benchmark.protocols.quasi_newton`, as many iterations as Adam's steps), whose line search
does not magnify the small gradients of a flat objective as Adam's normalised steps do: a search
whose result does not follow the observation's last digits (docs/table1.md, "A start search that
does not move").

The facing search (:mod:`benchmark.protocols.facing`), which precedes it, stays on the Chamfer by
Adam under either rule: on the soft-min Chamfer its choice between a body's front and back blurred,
and two of the quick profile's 8 sequences at 100 / 5 started backwards (docs/table1.md)."""

from __future__ import annotations

import torch

from benchmark.metrics.soft_chamfer import SoftChamfer
from benchmark.metrics.static_chamfer import StaticChamfer
from benchmark.protocols.quasi_newton import lbfgs_to_plateau
from benchmark.protocols.step_rules import PlateauRule, optimise

SEARCH_FITS = ("exact", "smooth")  # the rule of one search's brief fits
# objective.start_fit: a search rule for every search, or "smooth-encoded" (a candidate too): the
# prior-free start that the encoders encode searched smooth, every fit's own search exact (search_fit)
START_FITS = SEARCH_FITS + ("smooth-encoded",)
START_SOFTMIN_M = 0.03
FIXED_ITERATIONS = PlateauRule(tolerance=-1.0)  # a plateau test no fit passes: the L-BFGS runs to its cap


def check_start_fit(start_fit: str) -> str:
    """``start_fit`` when it is one of START_FITS; otherwise a ValueError naming the key and the choices."""
    if start_fit not in START_FITS:
        raise ValueError(f"unknown objective.start_fit {start_fit!r}; choose one of {', '.join(START_FITS)}")
    return start_fit


def search_fit(start_fit: str, encoded: bool) -> str:
    """The rule (:data:`SEARCH_FITS`) of one search under ``objective.start_fit``: ``encoded``, the
    prior-free start searched for the encoders to encode; otherwise a fit's own start (no-prior's,
    which is the prior-free start too, and the per-frame priors' limb search). ``smooth-encoded``:
    smooth for the first, exact for the others (the per-frame rows pass the 1e-6 m probe on the
    exact search, and the smooth one cost them a sequence each at 100 / 5, docs/table1.md)."""
    if check_start_fit(start_fit) == "smooth-encoded":
        return "smooth" if encoded else "exact"
    return start_fit


def check_search_fit(start_fit: str) -> str:
    """``start_fit`` when it is one search's rule (:data:`SEARCH_FITS`); otherwise a ValueError."""
    if start_fit not in SEARCH_FITS:
        raise ValueError(f"start search: {start_fit!r} is not one search's rule ({', '.join(SEARCH_FITS)}); an "
                         "objective.start_fit of the spec is resolved per search by brief_fit.search_fit")
    return start_fit


def search_chamfer(points: torch.Tensor, lengths: torch.Tensor, start_fit: str):
    """The brief fits' data term against the fixed observed ``points`` (N, P, 3) with ``lengths``
    (``start_fit``: one search's rule): called with the mesh's (N, V, 3) points, (N,) metres."""
    if check_search_fit(start_fit) == "smooth":
        return SoftChamfer(points, lengths, START_SOFTMIN_M)
    return StaticChamfer(points, lengths)


def brief_fits(prior_name: str, stages, lr: float, rows_of, start_fit: str) -> None:
    """Fit the hypotheses briefly: for each ``(parameters, steps)`` of ``stages`` in turn, that many
    steps (Adam, exact) or iterations (L-BFGS, smooth; every one, no plateau test; ``start_fit``:
    one search's rule) on the sum of
    ``rows_of()``, the (rows,) objective of every hypothesis."""
    smooth = check_search_fit(start_fit) == "smooth"
    trace: list = []  # the batched L-BFGS's bookkeeping: each evaluation's rows

    def loss_of(step):
        rows = rows_of()
        trace.append(rows.detach())
        return rows.sum(), lambda: {}

    for params, steps in stages:
        if smooth:
            lbfgs_to_plateau(prior_name, params, steps, lr, loss_of, trace, FIXED_ITERATIONS)
        else:
            optimise(prior_name, params, steps, lr, 1.0, loss_of)
        trace.clear()
