"""The protocols' optimiser and step rules (split from :mod:`benchmark.protocols.fit_state`):
Adam with a cosine schedule (:func:`optimise`), and the plateau rule of table1 v6+ and sls v4+
(:class:`PlateauRule`, :func:`optimise_to_plateau`): each sequence descends until its objective
plateaus, at rates it reduces itself."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from benchmark.core.memory import RELEASE_EVERY, release_free_memory
from benchmark.protocols.kept_rows import KeptRows

LOG_EVERY = 25  # optimisation history: the first, every 25th and the last step


def optimise(prior_name: str, parameters, steps: int, lr: float, lr_final_fraction: float, step_loss,
             callback=None) -> list[dict]:
    """The protocols' one optimiser: Adam at ``lr``, cosine-annealed to ``lr * lr_final_fraction``
    over ``steps``.

    ``step_loss(step)`` returns ``(loss, log)``: the scalar loss to minimise and a zero-argument
    callable giving the history entry's values (called on logged steps only). A non-finite loss
    raises FloatingPointError naming the prior and the step. ``callback(step, loss)`` is called
    after every step. Returns the history (a list of ``{"step": ..., **log()}``).
    """
    opt = torch.optim.Adam(parameters, lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(steps, 1), eta_min=lr * lr_final_fraction)
    history = []
    for step in range(steps):
        adam_step(opt, prior_name, step_loss, step, history, step == 0 or step == steps - 1 or step % LOG_EVERY == 0,
                  callback)
        sched.step()
    return history


def loss_backward(prior_name: str, step_loss, step: int):
    """``step_loss(step)``'s ``(loss, log)`` with the loss's gradient accumulated; a non-finite loss
    raises FloatingPointError naming the prior and the step."""
    loss, log = step_loss(step)
    if not torch.isfinite(loss):
        raise FloatingPointError(f"prior {prior_name!r}: non-finite loss at step {step}")
    loss.backward()
    return loss, log


def check_batch_first(prior_name: str, tensors: list, B: int, who: str) -> None:
    """Refuse optimised variables that are not batch first (``B`` sequences): ``who`` (the rule or
    optimiser) holds sequences one by one."""
    bad = [tuple(p.shape) for p in tensors if p.dim() == 0 or p.shape[0] != B]
    if bad:
        raise ValueError(f"prior {prior_name!r}: {who} holds sequences one by one and needs every optimised variable "
                         f"batch first ({B} sequences); got shapes {bad}")


def adam_step(opt, prior_name: str, step_loss, step: int, history: list, logged: bool, callback=None,
              after_backward=None) -> None:
    """One optimiser step of :func:`optimise` and :func:`optimise_to_plateau`: the loss of
    ``step_loss(step)`` and its gradient (:func:`loss_backward`), the step; the history entry when
    ``logged``; ``callback(step, loss)``. ``after_backward()``, where given, runs between the
    gradient and the step and may return the loss to report instead."""
    opt.zero_grad(set_to_none=True)
    loss, log = loss_backward(prior_name, step_loss, step)
    if after_backward is not None:
        loss = after_backward()
    opt.step()
    if step % RELEASE_EVERY == RELEASE_EVERY - 1:  # long fits: freed memory back to the system (no value changes)
        release_free_memory()
    if logged:
        history.append({"step": step, **log()})
    if callback is not None:
        callback(step, float(loss.detach()))


@dataclass(frozen=True)
class PlateauRule:
    """The step rule of table1 and sls protocol v6 (``objective.step_rule: plateau``): descend at the
    constant learning rate until every sequence of the batch has reached its plateau, then anneal.

    Every ``check_every`` steps, each sequence's objective (its data term plus its weighted prior
    term: what the optimiser minimises) is compared over the last ``window`` steps (means of
    ``smoothing`` steps at each end): its relative change ``(f[s - window] - f[s]) / f[s - window]``.
    A sequence stops descending at the first check where its change is within ``tolerance`` either
    way (still falling: not there yet; rising: the step is too large for where it is) and is held
    there; the descent ends when every sequence is held, or at the step cap; then ``anneal_steps``
    steps of cosine decay from ``lr`` to ``lr * lr_final_fraction`` settle Adam's jitter. A sequence
    is *converged* when its change was within ``tolerance`` when it stopped descending: it is judged at the full, constant learning
    rate, so a schedule that has already shrunk the steps cannot make a fit that still descends
    look flat (the flaw of the versions 1-5 flag).

    ``floor``: the change is relative to ``max(f[s - window], floor)``: an objective that falls to
    about 0 (sls's landmark term, fitted exactly by a free body) has a relative change that is all
    jitter, so below ``floor`` the tolerance is absolute, ``tolerance * floor``. 0 (table1): purely
    relative.

    ``reductions``: a sequence that meets the rule first has its step scaled by ``factor`` (its own
    learning rate, ``lr * factor ** stage``) and is judged anew once a whole window has passed at
    that rate; it is held when it meets the rule at its ``reductions``-th reduced rate. 0 (table1
    version 6): held at the first plateau, at the full rate. At the full rate Adam's steps knock a
    fit between basins; the reduced rates let it settle in the one it is in (docs/table1.md,
    "Robustness of version 6"). ``min_steps``: no sequence is held before that many descent steps
    (the robustness check's longer probe: it keeps descending at its last rate).

    ``rate_scaled``: the tolerance at a reduced rate is ``tolerance * factor ** stage``, the change
    a window at that rate shows when the fit descends as fast, per unit of step, as one that the
    rule would pass at the full rate. False (table1 version 7): the same tolerance at every rate,
    which at 0.09 x the rate passes a fit descending 11 x faster per unit of step.
    """

    window: int = 50
    tolerance: float = 0.005
    smoothing: int = 10
    check_every: int = 10
    anneal_steps: int = 50
    floor: float = 0.0
    reductions: int = 0
    factor: float = 0.3
    min_steps: int = 0
    rate_scaled: bool = False

    def tolerance_at(self, stage: torch.Tensor) -> torch.Tensor:
        """(B,) float64 tolerance of sequences at rate stages ``stage`` ((B,) reductions taken)."""
        tol = torch.full(stage.shape, self.tolerance, dtype=torch.float64)
        return tol * self.factor ** stage.double() if self.rate_scaled else tol

    @classmethod
    def from_spec(cls, value) -> "PlateauRule":
        """The rule of an ``objective.plateau`` mapping (missing keys keep their defaults)."""
        if value is None:
            return cls()
        known = ("window", "tolerance", "smoothing", "check_every", "anneal_steps", "floor", "reductions", "factor",
                 "min_steps", "rate_scaled")
        unknown = set(value) - set(known)
        if unknown:
            raise ValueError(f"objective.plateau: unknown key(s) {sorted(unknown)}; known: {', '.join(known)}")
        if not isinstance(value.get("rate_scaled", False), bool):
            raise ValueError(f"objective.plateau: rate_scaled must be true or false, got {value['rate_scaled']!r}")
        rule = cls(**{k: (v if k == "rate_scaled" else float(v) if k in ("tolerance", "floor", "factor") else int(v))
                      for k, v in value.items()})
        if (rule.window < 1 or rule.smoothing < 1 or rule.check_every < 1 or rule.anneal_steps < 0 or rule.tolerance < 0
                or rule.floor < 0 or rule.reductions < 0 or rule.min_steps < 0 or not 0 < rule.factor < 1):
            raise ValueError(f"objective.plateau: {value!r}: window, smoothing and check_every must be >= 1, "
                             "anneal_steps, tolerance, floor, reductions and min_steps >= 0, factor in (0, 1)")
        return rule

    @property
    def min_descent(self) -> int:
        """The fewest descent steps before the first check can judge a plateau."""
        return self.window + self.smoothing

    def decrease(self, trace: list[torch.Tensor]) -> torch.Tensor:
        """(B,) float64 relative decrease of the objective over the last ``window`` steps of
        ``trace`` (a list of (B,) per-step objectives, at least ``min_descent`` long; negative: it rose)."""
        d = torch.stack([t.detach().double().cpu() for t in trace[-self.min_descent:]])
        k = self.smoothing
        start, last = d[:k].mean(0), d[-k:].mean(0)
        if self.floor > 0:
            return (start - last) / start.clamp_min(self.floor)
        return torch.where(start > 0, (start - last) / start, torch.zeros_like(start))


def optimise_to_plateau(prior_name: str, parameters, max_steps: int, lr: float, lr_final_fraction: float, step_loss,
                        trace: list, rule: PlateauRule, callback=None, rows_loss=None,
                        row_traces: tuple = (), whole_at=None, race: int = 1) -> tuple[list[dict], dict]:
    """Adam at the constant ``lr``, each sequence stopping at its own plateau
    (:class:`PlateauRule`), then ``rule.anneal_steps`` steps of cosine decay to
    ``lr * lr_final_fraction`` for every sequence.

    A sequence that meets the rule at a check is held where it is (its variables are put back after
    every later step of the descent: the first dimension of every parameter is the batch); the
    descent ends when every sequence is held, or after ``max_steps - rule.anneal_steps`` steps, when
    the sequences still moving are judged as they are. ``step_loss(step)`` as in :func:`optimise`;
    it must append the step's (B,) per-sequence objective to ``trace``. A cap below the rule's least
    steps (``min_descent + anneal_steps``, e.g. the smoke profile's) runs :func:`optimise`'s cosine
    schedule over the cap instead and flags every sequence unconverged (``plateau_decrease`` None).

    Returns the history and ``{"steps": total steps, "descent_steps": (B,) list, the step each
    sequence stopped descending at, "plateau_decrease": (B,) list, "converged": (B,) list of bool,
    "stopped": "plateau" | "cap"}``.

    ``rows_loss(step, rows)``, where given, is ``step_loss`` on the sequences ``rows`` only, appending
    (R,) vectors to ``trace`` and to every list of ``row_traces`` (the caller's other per-step
    traces; any shape whose last dimension is the sequences). The descent then evaluates only the sequences not yet held, and feeds Adam the held
    ones' objective and gradient kept from their first step at the held point
    (:class:`~benchmark.protocols.kept_rows.KeptRows`): the same fit for the rows' cost.
    ``whole_at(step)``, where given, names the steps whose objective changes for every sequence
    (e.g. re-weighted terms): they are evaluated whole and the held ones' values kept again.

    ``race`` > 1: the batch is groups of that many copies of one sequence (copy-minor, as
    :func:`benchmark.protocols.multi_start.repeat_state`). At the first check where every copy of a
    group has reached its first plateau (a rate reduction, or its hold), the copy with the lowest
    objective (the mean of the last ``rule.smoothing`` steps) is the group's winner and the other
    copies are held where they are (:class:`~benchmark.protocols.multi_start.MultiStart`'s
    ``choose: plateau``). The result's ``race`` holds each group's ``winner`` (the copy's index in
    its group; -1 where the copies had not all reached a plateau at the cap) and the ``step`` of the
    choice."""
    if max_steps < rule.min_descent + rule.anneal_steps:
        history = optimise(prior_name, parameters, max_steps, lr, lr_final_fraction, step_loss, callback=callback)
        B = int(trace[-1].shape[0]) if trace else 0
        return history, {"descent_steps": [0] * B, "steps": max_steps, "stopped": "cap below the rule's least steps",
                         "plateau_decrease": [None] * B, "converged": [False] * B}
    opt = torch.optim.Adam(parameters, lr=lr)
    tensors = [p for group in opt.param_groups for p in group["params"]]
    history = []
    descent_cap = max_steps - rule.anneal_steps
    step = 0
    held = held_on = decrease = stopped_at = snapshot = stage = since = scale_on = None
    kept = None if rows_loss is None else KeptRows(rows_loss, [trace, *row_traces])

    while step < descent_cap:
        before = None
        if scale_on is not None:  # some sequence descends at a reduced rate: its step is scaled below
            before = [p.detach().clone() for p in tensors]
        held_before = None if held is None else held.clone()
        whole = whole_at is not None and bool(whole_at(step))
        if kept is not None and kept.active() and not whole:  # the held sequences' values and gradients are kept
            adam_step(opt, prior_name, kept.step_loss, step, history, step % LOG_EVERY == 0, callback,
                      after_backward=lambda: kept.fill(tensors))
        else:
            adam_step(opt, prior_name, step_loss, step, history, step % LOG_EVERY == 0, callback)
        step += 1
        if kept is not None and held_before is not None:
            kept.capture(held_before, tensors, refresh=whole)
        if before is not None:
            _scale_steps(tensors, before, scale_on)
        if held is None:  # the batch size, known from the first step's objective
            B = int(trace[-1].shape[0])
            check_batch_first(prior_name, tensors, B, "the plateau rule")
            held = torch.zeros(B, dtype=torch.bool)
            decrease = torch.full((B,), float("nan"), dtype=torch.float64)
            stopped_at = torch.full((B,), descent_cap, dtype=torch.long)
            snapshot = [p.detach().clone() for p in tensors]
            stage = torch.zeros(B, dtype=torch.long)
            since = torch.zeros(B, dtype=torch.long)  # descent steps since the sequence's rate last changed
            judged = torch.zeros(B, dtype=torch.bool)  # held after a whole window at its rate (not cut by the cap)
            if race > 1 and B % race:
                raise ValueError(f"prior {prior_name!r}: a race of {race} copies per sequence needs a batch of whole "
                                 f"groups; got {B} rows")
            winner = torch.full((max(B // race, 1),), -1, dtype=torch.long)
            chosen_at = torch.full_like(winner, -1)
        since += 1
        with torch.no_grad():
            if bool(held.any()):  # the held sequences stay where they stopped
                for p, snap in zip(tensors, snapshot):
                    p[held_on] = snap[held_on]
        if step >= rule.min_descent and (step % rule.check_every == 0 or step == descent_cap):
            change = rule.decrease(trace)
            flat = ~held & (change.abs() <= rule.tolerance_at(stage)) & (since >= rule.min_descent)
            down = flat & (stage < rule.reductions)  # a plateau at a rate with reductions left: reduce it
            if bool(down.any()):
                stage[down] += 1
                since[down] = 0
                scale_on = (rule.factor ** stage.double()).to(tensors[0].device)
            last = flat & ~down & torch.tensor(step >= rule.min_steps)
            new = last | (~held & torch.tensor(step == descent_cap))
            if race > 1:  # the copies of a sequence that lost its race are held from here
                # reached: a rate cut or a hold at a plateau (a copy stopped by the cap has reached none:
                # its group is chosen after the anneal, by the caller)
                new |= ~held & _race_losers(trace, rule.smoothing, race, (stage >= 1) | held | last, winner, chosen_at,
                                            step)
            if bool(new.any()):
                decrease[new] = change[new]
                stopped_at[new] = step
                judged[new] = since[new] >= rule.min_descent  # 0 where the rate was cut at this very check
                held |= new
                held_on = held.to(tensors[0].device)  # the mask on the variables' device, moved only when it changes
                new_on = new.to(tensors[0].device)
                with torch.no_grad():
                    for p, snap in zip(tensors, snapshot):
                        snap[new_on] = p.detach()[new_on]
            if bool(held.all()):
                break
    descent = step
    if rule.anneal_steps:  # every sequence from its own last rate
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=rule.anneal_steps, eta_min=lr * lr_final_fraction)
        for i in range(rule.anneal_steps):
            before = None if scale_on is None else [p.detach().clone() for p in tensors]
            adam_step(opt, prior_name, step_loss, step, history, i == rule.anneal_steps - 1 or step % LOG_EVERY == 0,
                      callback)
            if before is not None:
                _scale_steps(tensors, before, scale_on)
            sched.step()
            step += 1
    # converged: within the tolerance when it stopped, at its last reduced rate, over a whole window at
    # that rate (a sequence cut to its last rate at the cap's check, or less than a window before it,
    # was measured across two rates: not converged)
    within = (decrease.abs() <= rule.tolerance_at(stage)).tolist()
    converged = [bool(w and k >= rule.reductions and j) for w, k, j in zip(within, stage.tolist(), judged.tolist())]
    out = {"descent_steps": [int(v) for v in stopped_at.tolist()], "steps": step,
           "stopped": "plateau" if descent < descent_cap or all(converged) else "cap",
           "plateau_decrease": [round(float(v), 6) for v in decrease.tolist()], "converged": converged}
    if rule.reductions:
        out["reductions"] = [int(k) for k in stage.tolist()]
    if race > 1:
        out["race"] = {"winner": [int(v) for v in winner.tolist()], "step": [int(v) for v in chosen_at.tolist()]}
    return history, out


def _race_losers(trace: list, smoothing: int, race: int, reached: torch.Tensor, winner: torch.Tensor,
                 chosen_at: torch.Tensor, step: int) -> torch.Tensor:
    """(B,) mask of the copies that lose their group's race at this check (``optimise_to_plateau``'s
    ``race``): in each undecided group whose copies have all ``reached`` their first plateau, every
    copy but the one with the lowest objective over the last ``smoothing`` steps. Records the winners
    and the step in ``winner`` and ``chosen_at`` (in place)."""
    groups = reached.view(-1, race).all(1) & (winner < 0)
    losers = torch.zeros(reached.shape, dtype=torch.bool)
    if not bool(groups.any()):
        return losers
    recent = torch.stack([t.detach().double().cpu() for t in trace[-smoothing:]]).mean(0).view(-1, race)
    best = recent.argmin(1)
    winner[groups] = best[groups]
    chosen_at[groups] = step
    lose = groups.view(-1, 1) & (torch.arange(race).view(1, -1) != best.view(-1, 1))
    return lose.flatten()


STEP_RULES = ("cosine", "plateau")  # objective.step_rule: versions 1-5 cosine over the profile's steps; v6 plateau


def plateau_rule(spec: dict):
    """The step rule of ``objective.step_rule`` (``plateau``, with ``objective.plateau``'s sizes:
    :class:`PlateauRule`; table1 from version 6, sls from 4, denoise and inbetween from 2), or None
    for the cosine schedule over the profile's steps (``cosine``, the default)."""
    obj = spec["objective"]
    schedule = str(obj.get("step_rule", "cosine"))
    if schedule not in STEP_RULES:
        src = spec.get("_source") or f"benchmark/tables/{spec.get('name', '?')}.yaml"
        raise ValueError(f"{src}: field 'objective.step_rule' is {schedule!r}; choose one of {', '.join(STEP_RULES)}")
    return PlateauRule.from_spec(obj.get("plateau")) if schedule == "plateau" else None


def cap_independent_problem(objective) -> str | None:
    """Why a fit under the rules ``objective`` (a spec's section) could depend on the step cap
    before reaching it, or None where a fit whose every sequence converged is the same computation
    under any larger cap: :func:`optimise_to_plateau` reads the cap only to end the descent
    (:mod:`benchmark.run.cap_carry` carries such units over when a profile's cap rises)."""
    rule = str(objective.get("step_rule", "cosine"))
    if rule != "plateau":
        return f"its step rule is {rule!r}, a schedule over the profile's steps"
    if str(objective.get("optimiser", "adam")) != "adam":
        return f"its optimiser is {objective.get('optimiser')!r}; only Adam's plateau descent is declared cap-independent"
    starts = (objective.get("multi_start") or {}).get("starts", 1)
    if int(starts) > 1:
        return "it keeps the best of several starts, and the choice depends on every copy's end"
    if int((objective.get("plateau") or {}).get("min_steps", 0)) > 0:
        return "its plateau rule holds no fit before a minimum step count"
    return None


@torch.no_grad()
def _scale_steps(tensors: list, before: list, scale: torch.Tensor) -> None:
    """Scale each sequence's last optimiser step by ``scale`` (B,): its own learning rate (Adam's
    step does not depend on the gradient's scale, so a per-sequence rate is the scaled step)."""
    for p, b in zip(tensors, before):
        s = scale.to(p.dtype).view(-1, *([1] * (p.dim() - 1)))
        p.copy_(b + s * (p - b))
