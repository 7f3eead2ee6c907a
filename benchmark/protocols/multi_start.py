"""Several starts per sequence (``objective.multi_start``, a table1 version 8 candidate,
docs/protocol.md), and the copy bookkeeping it shares with the facing search: a state repeated per
sequence, the copies' starts, and one copy per sequence taken back."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from benchmark.protocols.fit_state import FitState, as_latent


AROUND_RULES = ("encoded", "own")  # MultiStart.around: the copies about the encoded start, or about the fit's own
CHOOSE_RULES = ("end", "plateau")  # MultiStart.choose: after every copy's whole fit, or at the copies' first plateau


@dataclass(frozen=True)
class MultiStart:
    """Several starts per sequence for the priors whose start is encoded (``objective.multi_start``,
    table1 from version 8, docs/protocol.md): ``starts`` copies of every sequence are fitted
    side by side from the encoded start (:func:`benchmark.protocols.start_search.encoded_start`),
    the fit's own start before it (the prior's mean latents, turned to the facing, the neutral
    shape), and ``starts - 2`` encoded starts with seeded Gaussian noise of
    ``noise`` (in the latents' own units: the standard priors' standard deviation) added to their
    latents; each sequence keeps the copy with the lowest objective at the last step. The encoded
    copies share the encoded start's rigid parameters and shape.

    ``choose``: when a sequence's copy is chosen. ``"end"``: after every copy's whole fit (the copy
    with the lowest objective at the last step). ``"plateau"`` (a race): once every copy of the
    sequence has reached its first plateau (the plateau rule's first rate reduction, or its hold),
    the copy with the lowest objective there (the mean over the rule's ``smoothing`` last steps)
    goes on alone and the others are held where they are, so they cost no more steps
    (:func:`benchmark.protocols.step_rules.optimise_to_plateau`'s ``race``); a sequence whose copies
    had not all reached it at the step cap is chosen at the end.

    ``around``: ``"encoded"`` (above); ``"own"``: no copy starts from the encoded start, whose
    prior-free source moves with the observation's last digits (docs/table1.md): copy 0 is the
    fit's own start, copies 1.. the own start with seeded Gaussian noise of ``noise`` on its latents
    (its rigid parameters and shape, from the facing, shared)."""

    starts: int = 1
    noise: float = 0.5
    choose: str = "end"
    around: str = "encoded"

    @classmethod
    def from_spec(cls, value) -> "MultiStart | None":
        """The rule of an ``objective.multi_start`` mapping; None (one start) when absent."""
        if value is None:
            return None
        if not isinstance(value, dict):
            raise ValueError(f"objective.multi_start: expected a mapping like {{starts: 4, noise: 0.5}}, got {value!r}")
        unknown = set(value) - {"starts", "noise", "choose", "around"}
        if unknown:
            raise ValueError(f"objective.multi_start: unknown key(s) {sorted(unknown)}; known: starts, noise, choose, "
                             "around")
        around = value.get("around", "encoded")
        if around not in AROUND_RULES:
            raise ValueError(f"objective.multi_start: around is {around!r}; choose one of {', '.join(AROUND_RULES)}")
        starts, noise, choose = value.get("starts", 1), value.get("noise", 0.5), value.get("choose", "end")
        if not isinstance(starts, int) or isinstance(starts, bool) or starts < 1 or not float(noise) > 0:
            raise ValueError(f"objective.multi_start: {value!r}: 'starts' must be an integer >= 1 and 'noise' > 0")
        if choose not in CHOOSE_RULES:
            raise ValueError(f"objective.multi_start: choose is {choose!r}; choose one of {', '.join(CHOOSE_RULES)}")
        return cls(starts=starts, noise=float(noise), choose=choose, around=around)


def repeat_state(state: FitState, k: int) -> FitState:
    """Every variable of ``state`` repeated ``k`` times per sequence, hypothesis-major like
    :func:`repeat_batch` (b0k0, b0k1, ...), as fresh leaves."""
    rep = lambda x: None if x is None else x.detach().repeat_interleave(k, dim=0).clone().requires_grad_(True)  # noqa: E731
    latents = {n: as_latent(state.adapter, n, v.detach().repeat_interleave(k, dim=0).clone()) for n, v in state.latents.items()}
    return FitState(adapter=state.adapter, latents=latents,
                    shape_param=rep(state.shape_param), obs_t=state.obs_t.repeat_interleave(k, dim=0),
                    window_s=state.window_s, root=rep(state.root), trans=rep(state.trans), heading=rep(state.heading),
                    offset=rep(state.offset), bounded_shape=state.bounded_shape)


@torch.no_grad()
def vary_copies(state: FitState, start: FitState, rule: MultiStart, generator: torch.Generator) -> None:
    """Set the starts of a state of ``rule.starts`` copies per sequence whose copies all hold the
    encoded start (:func:`benchmark.protocols.start_search.encoded_start` with ``copies``): copy 1
    takes every variable of ``start`` (batch B: the fit's own start before the encoded one, the
    prior's mean turned to the facing), copies 2.. the encoded latents plus seeded Gaussian noise of
    ``rule.noise``; copy 0 stays. ``rule.around == "own"``: every copy takes ``start``'s variables,
    and copies 1.. get the noise. In place."""
    K = rule.starts
    own_copies = slice(None) if rule.around == "own" else slice(1, 2)
    noisy = 1 if rule.around == "own" else 2
    pairs = [(state.latents[n], start.latents.get(n)) for n in state.latents]
    pairs += [(getattr(state, n), getattr(start, n)) for n in ("shape_param", "root", "trans", "heading", "offset")]
    for v, own in pairs:
        if v is None:
            continue
        view = v.view(-1, K, *v.shape[1:])
        if K > 1 and own is not None and own.shape == view[:, 1].shape:
            view[:, own_copies] = own.detach().to(v).unsqueeze(1)
    if K > noisy:
        for v in state.latents.values():
            if not v.requires_grad:  # constant_latents (a window duration) are not the start's to vary
                continue
            view = v.view(-1, K, *v.shape[1:])
            noise = torch.randn((view.shape[0], K - noisy, *v.shape[1:]), generator=generator, dtype=v.dtype)
            view[:, noisy:] += rule.noise * noise.to(v.device)


def select_copies(state: FitState, pick: torch.Tensor, like: FitState) -> FitState:
    """The copies ``pick`` ((B,) flat indices, one per sequence) of a state of several copies per
    sequence (the facing search's hypotheses, :func:`vary_copies`' starts) as a fresh leaf state
    shaped like ``like``."""
    def take(x, ref, grad=True):
        if x is None:
            return None
        y = x.detach()[pick].clone()
        if ref is not None and y.shape != ref.shape:
            raise ValueError(f"a variable of shape {tuple(x.shape)} is not batch-first "
                             f"(expected {tuple(ref.shape)} after selection)")
        return y.requires_grad_(True) if grad else y

    latents = {k: as_latent(like.adapter, k, take(v, like.latents.get(k), grad=False)) for k, v in state.latents.items()}
    return FitState(adapter=like.adapter, latents=latents, shape_param=take(state.shape_param, like.shape_param),
                    obs_t=like.obs_t, window_s=like.window_s, root=take(state.root, like.root),
                    trans=take(state.trans, like.trans), heading=take(state.heading, like.heading),
                    offset=take(state.offset, like.offset), bounded_shape=like.bounded_shape)
