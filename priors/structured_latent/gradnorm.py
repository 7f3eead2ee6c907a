"""GradNorm (Chen, Badrinarayanan, Lee, Rabinovich, ICML 2018): adaptive weights of loss terms.

Marsot et al. weigh their partial reconstruction losses (pose / translation / time, then mesh /
time) with GradNorm, weights initialised to 1.0 (paper 001 §3.3, Supp. §2). One step, for losses
L_i and weights w_i (T terms):

    G_i    = || d(w_i L_i) / dW ||_2          W = the network's last shared layer (see below)
    r_i    = (L_i / L_i(0)) / mean_j (L_j / L_j(0))          relative inverse training rate
    L_grad = sum_i | G_i - mean_j(G_j) * r_i ** alpha |      (the target is a constant)

The weights take one optimiser step on dL_grad/dw (only), then are renormalised to sum to T
(and floored at ``min_weight``); the network itself is trained on sum_i w_i L_i with the weights
held constant. L_i(0) are the losses of the first step. ``alpha`` (the restoring force) and the
weights' learning rate are not given by Marsot et al.: 1.5 and 0.025 by default.

``shared`` may be a weight tensor (Chen et al.: the last shared layer's weights) or an activation
(the last shared representation, as MGDA-UB, Sener & Koltun 2018, does for the same purpose);
the structured-latent training passes the decoder's last shared activation, whose per-term
gradients cost one small matrix product each instead of a transposed-convolution backward.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn


class GradNorm(nn.Module):
    """Adaptive loss weights; see the module docstring.

    Usage, once per training step, before ``loss.backward()``::

        total = gradnorm.combine(losses, shared_weight)   # updates the weights; returns sum w_i L_i
        (total + other_terms).backward()
    """

    def __init__(self, names: Sequence[str], alpha: float = 1.5, lr: float = 0.025, min_weight: float = 1e-3):
        super().__init__()
        if len(names) < 2:
            raise ValueError(f"GradNorm needs at least 2 loss terms, got {list(names)}")
        self.names = tuple(names)
        self.alpha, self.min_weight = float(alpha), float(min_weight)
        self.weights = nn.Parameter(torch.ones(len(self.names)))
        self.register_buffer("initial", torch.zeros(len(self.names)))
        self.register_buffer("started", torch.tensor(False))
        self.optimizer = torch.optim.Adam([self.weights], lr=lr)

    def as_dict(self) -> dict[str, float]:
        return {n: float(w) for n, w in zip(self.names, self.weights.detach())}

    def combine(self, losses: dict[str, torch.Tensor], shared: torch.Tensor, update: bool = True) -> torch.Tensor:
        """sum_i w_i L_i with the current weights held constant; then (if ``update``) one GradNorm
        step on the weights using the gradients of each L_i with respect to ``shared``."""
        missing = [n for n in self.names if n not in losses]
        if missing:
            raise KeyError(f"GradNorm: losses {missing} missing (terms: {list(self.names)})")
        L = torch.stack([losses[n] for n in self.names])
        w = self.weights.detach().clone().to(L)
        total = (w * L).sum()
        if update:
            self._step(L, shared)
        return total

    def _step(self, L: torch.Tensor, shared: torch.Tensor) -> None:
        norms = []
        for i in range(len(self.names)):
            (g,) = torch.autograd.grad(L[i], shared, retain_graph=True, allow_unused=True)
            norms.append(torch.zeros((), device=L.device) if g is None else g.detach().norm())
        g = torch.stack(norms).to(self.weights)
        Ld = L.detach().to(self.weights)
        if not bool(self.started):
            self.initial.copy_(Ld.clamp_min(1e-12))
            self.started.fill_(True)
        ratio = Ld / self.initial
        r = ratio / ratio.mean().clamp_min(1e-12)
        G = self.weights * g
        target = (G.mean() * r.pow(self.alpha)).detach()
        loss = (G - target).abs().sum()
        self.optimizer.zero_grad(set_to_none=True)
        (grad,) = torch.autograd.grad(loss, self.weights)
        self.weights.grad = grad
        self.optimizer.step()
        with torch.no_grad():
            self.weights.clamp_(min=self.min_weight)
            self.weights.mul_(len(self.names) / self.weights.sum())


__all__ = ["GradNorm"]
