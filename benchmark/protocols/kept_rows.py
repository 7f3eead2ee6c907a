"""The held sequences of a plateau descent that no longer need evaluating (:class:`KeptRows`).

Under the plateau rule (:func:`benchmark.protocols.step_rules.optimise_to_plateau`) a sequence that
has reached its plateau is held: after every later step of the descent its variables are put back
where it stopped, so it is evaluated at the same point at every step until the last sequence of
the batch is held. Its objective and gradient there are the same at every one of those steps (the
sequences of a batch are independent: each one's objective depends on its own variables only). So
after one evaluation at the held point they are kept, the step evaluates only the sequences still
descending, and Adam is fed the kept gradient for the others: the same gradients, so the same
moments and the same fit as evaluating the whole batch, for the cost of the rows that still move.

The same up to float rounding: a smaller batch puts each sequence's numbers elsewhere in torch's
vector loops, whose transcendental functions round the vectorised and the leftover elements
differently (a sequence's gradient moves in its last bits; measured on quick units, a cell's MPJPE
moved by 3e-5 to 0.03 mm, docs/speed.md).
"""

from __future__ import annotations

import torch


class KeptRows:
    """The kept objective values and gradients of the held sequences of one descent.

    ``rows_loss(step, rows)``: the step's loss on the sequences ``rows`` ((R,) long, ascending,
    on the variables' device) only, its ``(loss, log)`` as ``step_loss`` returns them, appending
    to each list of ``traces`` a tensor whose last dimension is the R sequences (a whole step
    appends it with the B sequences). After the gradient, :meth:`fill` puts the kept rows' values
    back into each trace's last entry (so every trace keeps whole-batch entries) and their kept
    gradients into the variables' gradients.

    A step whose objective changes for the held sequences too (sls's adaptive weights, updated
    every few steps) is evaluated whole, and :meth:`capture` keeps the held rows' values and
    gradients again from it (``refresh``).
    """

    def __init__(self, rows_loss, traces: list[list]):
        self.rows_loss = rows_loss
        self.traces = traces
        self.kept = None  # (B,) bool: the sequences whose values and gradients are kept
        self.values = None  # per trace, a (B,) vector holding the kept rows' values
        self.grads = None  # per variable, a tensor holding the kept rows' gradients (None: no gradient)
        self.rows = None  # (R,) long: the sequences a step evaluates

    def active(self) -> bool:
        """Whether the next step evaluates a subset (some rows kept, some still descending)."""
        return self.rows is not None and 0 < self.rows.numel() < self.kept.numel()

    def step_loss(self, step: int):
        return self.rows_loss(step, self.rows)

    @torch.no_grad()
    def fill(self, tensors: list[torch.Tensor]) -> torch.Tensor:
        """Complete the step just evaluated on :attr:`rows`: the traces' last entries to (B,), the
        kept rows' gradients into ``tensors``' gradients. Returns the whole batch's objective (the
        first trace's last entry, summed) as the loss to report."""
        for trace, kept in zip(self.traces, self.values):
            full = kept.clone()
            full[..., self.rows.to(full.device)] = trace[-1].to(full.dtype)
            trace[-1] = full
        for p, g in zip(tensors, self.grads):
            if g is None:
                continue
            mask = self.kept.to(p.device)
            if p.grad is None:
                p.grad = torch.zeros_like(p)
            p.grad[mask] = g[mask]
        return self.traces[0][-1].sum()

    @torch.no_grad()
    def capture(self, held_before: torch.Tensor, tensors: list[torch.Tensor], refresh: bool = False) -> None:
        """After a step: keep the values and gradients of the sequences that were held before it
        (``held_before``, (B,) bool) and are not kept yet (``refresh``: all of them, after a step
        evaluated whole because their objective changed); the step evaluated them at their held point."""
        if self.kept is None:
            self.kept = torch.zeros_like(held_before)
            self.values = [torch.zeros_like(trace[-1]) for trace in self.traces]
            self.grads = [None if p.grad is None else torch.zeros_like(p.grad) for p in tensors]
        new = held_before if refresh else held_before & ~self.kept
        if not bool(new.any()):
            return
        for trace, kept in zip(self.traces, self.values):
            kept[..., new.to(kept.device)] = trace[-1][..., new.to(kept.device)]
        for p, g in zip(tensors, self.grads):
            if g is not None and p.grad is not None:
                mask = new.to(p.device)
                g[mask] = p.grad[mask]
        self.kept |= new
        self.rows = (~self.kept).nonzero()[:, 0].to(tensors[0].device)
