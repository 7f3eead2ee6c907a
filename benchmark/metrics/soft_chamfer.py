"""A soft-min Chamfer against a fixed point set (:class:`SoftChamfer`): the start search's smooth
data term (``objective.start_fit: smooth``, a table1 version 8 candidate, docs/protocol.md).

The Chamfer of :func:`benchmark.metrics.chamfer.chamfer_loss` takes, for each point, the distance
to its nearest neighbour: a function whose gradient jumps wherever the nearest neighbour changes.
At 100 observed points per frame those jumps are everywhere, and a brief fit's path through them
is decided by the observation's last digits (docs/table1.md, "A start search that does not
move"). Here each minimum is a soft minimum at temperature ``tau`` (metres),

    softmin_tau(d_1, ..., d_m) = -tau * log(sum_j exp(-d_j / tau)),

smooth in the points, at most the minimum and at least the minimum less ``tau * log(m)``; it tends
to the Chamfer as ``tau`` goes to 0. The value is ``0.5 * (mean_a softmin_b d + mean_b softmin_a d)``
per element, in metres, over every pair (dense: for the start search's subsets, a few hundred
points and vertices per frame), in chunks of elements that bound the memory.
"""

from __future__ import annotations

import torch

MAX_PAIR_ELEMENTS = 1 << 24  # pairwise distances held at once (per chunk of elements)
PADDING_M = 1e3  # the distance given to padding points: finite (no NaN in the gradient), out of every soft minimum's reach


class SoftChamfer:
    """The soft-min Chamfer of a changing point set ``a`` against the fixed ``points`` (N, P, 3)
    with ``lengths`` (N,) valid points per element (the rest is padding), at ``temperature_m``.

    Called as :class:`~benchmark.metrics.static_chamfer.StaticChamfer` is (``chamfer(a)`` with ``a``
    (N, V, 3), every point valid): returns (N,) metres, differentiable in ``a``."""

    def __init__(self, points: torch.Tensor, lengths: torch.Tensor, temperature_m: float):
        if points.dim() != 3 or points.shape[-1] != 3:
            raise ValueError(f"SoftChamfer: points must be (N, P, 3); got {tuple(points.shape)}")
        if not temperature_m > 0:
            raise ValueError(f"SoftChamfer: the temperature must be > 0 metres; got {temperature_m!r}")
        self.b = points
        self.tau = float(temperature_m)
        self.mask = torch.arange(points.shape[1], device=points.device)[None] < lengths.to(points.device)[:, None]
        if not bool(self.mask.any(1).all()):
            raise ValueError("SoftChamfer: every element needs at least one valid point (a length >= 1)")

    def __call__(self, a: torch.Tensor) -> torch.Tensor:
        if a.dim() != 3 or a.shape[0] != self.b.shape[0] or a.shape[-1] != 3:
            raise ValueError(f"SoftChamfer: a must be ({self.b.shape[0]}, V, 3); got {tuple(a.shape)}")
        per = max(1, MAX_PAIR_ELEMENTS // max(1, a.shape[1] * self.b.shape[1]))
        return torch.cat([self._chunk(a[i:i + per], self.b[i:i + per], self.mask[i:i + per])
                          for i in range(0, a.shape[0], per)])

    def _chunk(self, a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        d = ((a[:, :, None, :] - b[:, None, :, :]).square().sum(-1) + 1e-12).sqrt()  # (n, V, P)
        d = torch.where(mask[:, None, :], d, torch.full_like(d, PADDING_M))
        a_to_b = -self.tau * torch.logsumexp(-d / self.tau, 2)  # (n, V): each vertex to the observed points
        b_to_a = -self.tau * torch.logsumexp(-d / self.tau, 1)  # (n, P): each observed point to the vertices
        b_to_a = torch.where(mask, b_to_a, torch.zeros_like(b_to_a)).sum(1) / mask.sum(1).to(d.dtype)
        return 0.5 * (a_to_b.mean(1) + b_to_a)
