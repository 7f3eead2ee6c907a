"""A batched L-BFGS for the completion fit (``objective.optimiser: lbfgs``, a table1 version 8
candidate, docs/protocol.md): every sequence of the batch is its own problem, with its own
curvature history, its own line search and its own stop.

Why: under the plateau rule, Adam needs up to 3,000 steps on the structured latent space's fits
(docs/table1.md, "A tolerance scaled to the rate"): its step length does not follow the slow,
ill-conditioned descent of a small latent vector. A quasi-Newton direction does, and a line
search makes the descent monotone, so a window of iterations that no longer lowers the objective
is a plateau, not Adam's jitter. The objective is the one Adam minimises, unchanged.

The fit's variables are batch first (the plateau rule needs them so already): sequence b's
variables are row b of every tensor, its objective depends on nothing else, so the gradient of
the batch's summed objective holds each sequence's own gradient in its rows.

Each iteration, per sequence:

- the direction ``d = -H g`` of the two-loop recursion over the sequence's last ``memory`` pairs
  (pairs with ``s.y <= 1e-10 * |s| |y|`` are not kept); the first direction, and any that is not
  a descent direction, is the steepest descent scaled so that no variable moves by more than
  ``first_step`` (the fit's learning rate, in the variables' units) at ``t = 1``;
- a backtracking Armijo search from ``t = min(1, 2 t')``, ``t'`` the sequence's last accepted step
  length (1 at the start and after a failed search): every trial is one batch evaluation (objective and
  gradient), a sequence takes the first trial with ``f(x + t d) <= f(x) + 1e-4 t g.d + 1e-6 |f(x)|``
  (the last term: the objective's float32 roundoff, so that a fit at its minimum is not refused
  every step), the others
  halve ``t`` (at most ``max_trials`` trials; a sequence that finds none resets its history and
  stays where it is);
- the plateau test of :class:`~benchmark.protocols.step_rules.PlateauRule` on the accepted
  objectives: every ``check_every`` iterations, the relative change over the last ``window``
  iterations (means of ``smoothing`` at each end); within the tolerance the sequence is held (its
  direction is zero from then on) and converged (not before ``min_steps`` iterations: the
  robustness check's longer probe). The tolerance is the one the rule applies at its
  last rate (``tolerance``, or with ``rate_scaled`` ``tolerance * factor ** reductions``); the
  rate reductions themselves and the anneal do not apply: the descent is monotone, there is no
  step jitter to settle.
"""

from __future__ import annotations

import torch

from benchmark.protocols.step_rules import LOG_EVERY, PlateauRule, check_batch_first, loss_backward

OPTIMISERS = ("adam", "lbfgs")  # objective.optimiser: every table adam; lbfgs a table1 version 8 candidate
ARMIJO = 1e-4  # the sufficient-decrease constant of the line search
ROUNDOFF = 1e-6  # relative: a trial may exceed the Armijo bound by this much of |f| (float32 objectives)
CURVATURE_EPS = 1e-10  # a pair (s, y) is kept when s.y > CURVATURE_EPS * |s| |y|


def _flat(tensors: list[torch.Tensor], B: int) -> torch.Tensor:
    return torch.cat([t.reshape(B, -1) for t in tensors], 1)


def _grads(tensors: list[torch.Tensor], B: int) -> torch.Tensor:
    return _flat([torch.zeros_like(p) if p.grad is None else p.grad for p in tensors], B)


@torch.no_grad()
def _set(tensors: list[torch.Tensor], x: torch.Tensor) -> None:
    i = 0
    for p in tensors:
        n = p[0].numel() if p.dim() else 1
        p.copy_(x[:, i:i + n].view_as(p))
        i += n


def two_loop(g: torch.Tensor, S: torch.Tensor, Y: torch.Tensor, valid: torch.Tensor, order: list[int]) -> torch.Tensor:
    """(B, D) ``-H g`` by the two-loop recursion, per sequence, over its valid pairs.

    ``S``, ``Y``: (B, m, D) the pairs; ``valid``: (B, m) bool; ``order``: the slots from the newest
    to the oldest. H's initial scale is ``s.y / y.y`` of the sequence's newest valid pair (1 when it
    has none)."""
    q = g.clone()
    sy = (S * Y).sum(-1)  # (B, m)
    rho = torch.where(valid, 1.0 / torch.where(valid, sy, torch.ones_like(sy)), torch.zeros_like(sy))
    alpha = torch.zeros_like(sy)
    gamma = torch.ones(g.shape[0], dtype=g.dtype, device=g.device)
    have = torch.zeros(g.shape[0], dtype=torch.bool, device=g.device)
    for j in order:  # newest first
        a = rho[:, j] * (S[:, j] * q).sum(-1)
        alpha[:, j] = a
        q -= a[:, None] * Y[:, j]
        new = valid[:, j] & ~have
        yy = (Y[:, j] * Y[:, j]).sum(-1)
        gamma = torch.where(new, sy[:, j] / yy.clamp_min(1e-300), gamma)
        have |= valid[:, j]
    r = gamma[:, None] * q
    for j in reversed(order):  # oldest first
        b = rho[:, j] * (Y[:, j] * r).sum(-1)
        r += (alpha[:, j] - b)[:, None] * S[:, j]
    return -r


def lbfgs_to_plateau(prior_name: str, tensors: list[torch.Tensor], max_steps: int, first_step: float, step_loss,
                     trace: list, rule: PlateauRule, other_traces: tuple = (), memory: int = 20, max_trials: int = 12,
                     callback=None) -> tuple[list[dict], dict]:
    """The batched L-BFGS of this module's docstring on the leaf tensors ``tensors`` (batch first),
    for at most ``max_steps`` iterations.

    ``step_loss(step)`` as for :func:`~benchmark.protocols.step_rules.optimise_to_plateau`: it
    returns ``(summed loss, log)`` and appends the (B,) per-sequence objective to ``trace`` (and
    other per-step (B,) values to the lists of ``other_traces``). Line-search trials are taken back
    out of those lists: each holds one entry per iteration, at the accepted points (and one for the
    start). The history logs every ``LOG_EVERY``-th iteration's first trial.

    Returns the history and ``{"steps": iterations, "evaluations": batch evaluations,
    "descent_steps": (B,) the iteration each sequence was held at, "plateau_decrease": (B,),
    "converged": (B,) bool, "stopped": "plateau" | "cap", "optimiser": "lbfgs"}``."""
    lists = (trace, *other_traces)
    tolerance = float(rule.tolerance_at(torch.tensor([rule.reductions]))[0])
    history: list[dict] = []
    evaluations = 0

    def evaluate(step: int, x: torch.Tensor | None, logged: bool):
        nonlocal evaluations
        if x is not None:
            _set(tensors, x)
        for p in tensors:
            p.grad = None
        _, log = loss_backward(prior_name, step_loss, step)
        evaluations += 1
        entries = [lst.pop() for lst in lists]
        if logged:
            history.append({"step": step, **log()})
        return entries, _grads(tensors, B)

    B = int(tensors[0].shape[0])
    check_batch_first(prior_name, tensors, B, "the batched L-BFGS")
    x = _flat([p.detach() for p in tensors], B).double()
    dtype = tensors[0].dtype
    entries, g = evaluate(0, None, True)
    g = g.double()
    f = entries[0].detach().double().to(x.device)
    kept = [e.detach().clone() for e in entries]
    for lst, e in zip(lists, kept):
        lst.append(e)
    D = x.shape[1]
    S = torch.zeros(B, memory, D, dtype=torch.float64, device=x.device)
    Y = torch.zeros_like(S)
    valid = torch.zeros(B, memory, dtype=torch.bool, device=x.device)
    slots: list[int] = []  # newest first
    held = torch.zeros(B, dtype=torch.bool, device=x.device)
    decrease = torch.full((B,), float("nan"), dtype=torch.float64)
    stopped_at = torch.full((B,), max_steps, dtype=torch.long)
    failed = torch.zeros(B, dtype=torch.long)
    t_last = torch.ones(B, dtype=torch.float64, device=x.device)  # each sequence's last accepted step length
    step = 0
    while step < max_steps:
        step += 1
        d = two_loop(g, S, Y, valid, slots)
        gd = (g * d).sum(-1)
        steepest = ~valid.any(1) | ~(gd < 0)
        if bool(steepest.any()):
            scale = first_step / g.abs().amax(1).clamp_min(1e-30)
            d = torch.where(steepest[:, None], -g * scale[:, None], d)
            valid[steepest] = False
            gd = (g * d).sum(-1)
        d[held] = 0.0
        t = (2.0 * t_last).clamp_max(1.0)
        pending = ~held & (gd < 0)
        x_new, g_new, f_new = x.clone(), g.clone(), f.clone()
        new_entries = [e.clone() for e in kept]
        logged = step % LOG_EVERY == 0 or step == max_steps
        for trial in range(max_trials):
            if not bool(pending.any()):
                break
            x_try = torch.where(pending[:, None], x + t[:, None] * d, x_new)
            entries, g_try = evaluate(step, x_try.to(dtype), logged and trial == 0)
            f_try = entries[0].detach().double().to(x.device)
            ok = pending & torch.isfinite(f_try) & (f_try <= f + ARMIJO * t * gd + ROUNDOFF * f.abs())
            x_new[ok], g_new[ok], f_new[ok] = x_try[ok], g_try.double()[ok], f_try[ok]
            for kept_e, e in zip(new_entries, entries):
                kept_e[ok.to(kept_e.device)] = e.detach()[ok.to(e.device)]
            pending &= ~ok
            t = torch.where(pending, t * 0.5, t)
        failed[pending.cpu()] += 1
        t_last = torch.where(pending, torch.ones_like(t), t)
        s, y = x_new - x, g_new - g
        sy = (s * y).sum(-1)
        good = ~pending & ~held & (sy > CURVATURE_EPS * s.norm(dim=-1) * y.norm(dim=-1))
        slot = slots.pop() if len(slots) == memory else len(slots)
        S[:, slot], Y[:, slot] = s, y
        valid[:, slot] = good
        valid[pending] = False  # no acceptable step: start again from the steepest descent
        slots.insert(0, slot)
        x, g, f = x_new, g_new, f_new
        _set(tensors, x.to(dtype))
        kept = new_entries
        for lst, e in zip(lists, kept):
            lst.append(e.clone())
        if callback is not None:
            callback(step, float(f.sum()))
        if step >= rule.min_descent and (step % rule.check_every == 0 or step == max_steps):
            change = rule.decrease(trace)
            flat = (change.abs() <= tolerance) & torch.tensor(step >= rule.min_steps)
            new = ~held.cpu() & (flat | torch.tensor(step == max_steps))
            decrease[new] = change[new]
            stopped_at[new] = step
            held |= new.to(held.device)
            if bool(held.all()):
                break
    with torch.no_grad():
        _set(tensors, x.to(dtype))
    converged = [bool(v) for v in (decrease.abs() <= tolerance).tolist()]
    return history, {"optimiser": "lbfgs", "steps": step, "evaluations": evaluations,
                     "descent_steps": [int(v) for v in stopped_at.tolist()],
                     "stopped": "plateau" if all(converged) else "cap",
                     "plateau_decrease": [round(float(v), 6) for v in decrease.tolist()], "converged": converged,
                     "line_search_failures": [int(v) for v in failed.tolist()]}
