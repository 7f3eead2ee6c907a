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

Computed by one autograd function (:class:`_SoftChamferFn`) rather than by autograd through the
pairwise differences: the distances come from ``torch.cdist`` (exact differences, not the
matrix-product form, whose cancellation would cost digits at the small distances that matter),
each element's gradient is computed in the forward pass from the soft minima's weights (through
``cdist``'s own backward pass), and only it is kept for the backward pass, not the pairs. The same
function to float rounding as autograd through the pairs (:func:`reference_soft_chamfer`;
``tests/test_soft_chamfer.py`` compares them); its speed beside it: ``python -m benchmark perf
--only soft-chamfer``.
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
        self.tau = float(temperature_m)
        self.mask = torch.arange(points.shape[1], device=points.device)[None] < lengths.to(points.device)[:, None]
        self.b = points.masked_fill(~self.mask[..., None], 0.0)  # whatever the padding holds (NaN too)
        if not bool(self.mask.any(1).all()):
            raise ValueError("SoftChamfer: every element needs at least one valid point (a length >= 1)")

    def __call__(self, a: torch.Tensor) -> torch.Tensor:
        if a.dim() != 3 or a.shape[0] != self.b.shape[0] or a.shape[-1] != 3:
            raise ValueError(f"SoftChamfer: a must be ({self.b.shape[0]}, V, 3); got {tuple(a.shape)}")
        per = max(1, MAX_PAIR_ELEMENTS // max(1, a.shape[1] * self.b.shape[1]))
        return torch.cat([self._chunk(a[i:i + per], self.b[i:i + per], self.mask[i:i + per])
                          for i in range(0, a.shape[0], per)])

    def _chunk(self, a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        grad = torch.is_grad_enabled()
        return _SoftChamferFn.apply(a, b, mask, self.tau, grad and a.requires_grad, grad and b.requires_grad)


def _softmax_and_logsumexp(s: torch.Tensor, dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``softmax(s, dim)`` and ``logsumexp(s, dim)`` from one pass of exponentials."""
    top = s.amax(dim, keepdim=True)
    e = (s - top).exp_()
    z = e.sum(dim, keepdim=True)
    return e.div_(z), (z.log_() + top).squeeze(dim)


class _SoftChamferFn(torch.autograd.Function):
    """The soft-min Chamfer of ``a`` (n, V, 3) against ``b`` (n, P, 3) with valid points ``mask``
    (n, P) at temperature ``tau``: (n,) values. Each element's value depends on its own points only,
    so its gradients are computed here, in the forward pass (``want_a``, ``want_b``), and the
    backward pass scales them: what is kept is (n, V + P, 3), not the (n, V, P) pairs."""

    @staticmethod
    def forward(ctx, a, b, mask, tau, want_a, want_b):
        with torch.enable_grad():
            a_, b_ = a.detach().requires_grad_(want_a), b.detach().requires_grad_(want_b)
            pairs = torch.cdist(a_, b_, compute_mode="donot_use_mm_for_euclid_dist")  # (n, V, P)
        d = pairs.detach().masked_fill(~mask[:, None, :], PADDING_M)
        s = d.mul_(-1.0 / tau)
        w, lse_v = _softmax_and_logsumexp(s, 2)  # each vertex's weights over the observed points
        u, lse_p = _softmax_and_logsumexp(s, 1)  # each observed point's weights over the vertices
        del s, d
        count = mask.sum(1).to(w.dtype)
        value = 0.5 * (-tau * lse_v.mean(1) + (-tau * lse_p).masked_fill_(~mask, 0.0).sum(1) / count)
        grad_a = grad_b = None
        if want_a or want_b:
            # d value / d distance_vp: 0.5 (w_vp / V + u_vp / count), 0 at the padding; through the
            # distances by cdist's own backward pass (exact differences, 0 where two points coincide;
            # the matrix-product form a * sum_p c_vp - c @ b would lose every digit near a coincidence)
            c = w.mul_(0.5 / a.shape[1]).addcmul_(u, (0.5 * mask / count[:, None])[:, None, :])
            del u
            wanted = [x for x, want in ((a_, want_a), (b_, want_b)) if want]
            grads = iter(torch.autograd.grad(pairs, wanted, c))
            grad_a = next(grads) if want_a else None
            grad_b = next(grads) if want_b else None
        ctx.save_for_backward(grad_a, grad_b)
        return value

    @staticmethod
    def backward(ctx, grad):
        grad_a, grad_b = ctx.saved_tensors
        scale = grad[:, None, None]
        return (None if grad_a is None else grad_a * scale, None if grad_b is None else grad_b * scale,
                None, None, None, None)


def reference_soft_chamfer(a: torch.Tensor, points: torch.Tensor, lengths: torch.Tensor, temperature_m: float) -> torch.Tensor:
    """The same soft-min Chamfer by autograd through the pairwise differences (the plain form, all
    pairs held for the backward pass): what the tests and ``perf --only soft-chamfer`` compare
    :class:`SoftChamfer` with."""
    mask = torch.arange(points.shape[1], device=points.device)[None] < lengths.to(points.device)[:, None]
    d = ((a[:, :, None, :] - points[:, None, :, :]).square().sum(-1) + 1e-12).sqrt()  # (N, V, P)
    d = torch.where(mask[:, None, :], d, torch.full_like(d, PADDING_M))
    a_to_b = -temperature_m * torch.logsumexp(-d / temperature_m, 2)
    b_to_a = -temperature_m * torch.logsumexp(-d / temperature_m, 1)
    b_to_a = torch.where(mask, b_to_a, torch.zeros_like(b_to_a)).sum(1) / mask.sum(1).to(d.dtype)
    return 0.5 * (a_to_b.mean(1) + b_to_a)

