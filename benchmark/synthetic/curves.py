"""Smooth scalar curves of a phase or of time: the building blocks of the procedural actions.

- :class:`FourierCurve`: a periodic curve (period 1 in phase), a truncated Fourier series fitted
  to keyframes (phase, value). Gait joint angles are tabulated as keyframes read off published
  gait curves and smoothed to a few harmonics, so the curve and all its derivatives are continuous.
- :class:`KeyframeCurve`: a one-shot curve on a phase interval, monotone piecewise-cubic
  (PCHIP) through keyframes, constant outside them (jumps, kicks, the cartwheel).
- :func:`smoothstep`, :func:`smootherstep`, :func:`bump`, :func:`window`: phase functions.

All evaluate vectorised over a tensor of phases of any shape and return the same shape, float64.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

_DTYPE = torch.float64


def _as_tensor(x) -> torch.Tensor:
    return torch.as_tensor(x, dtype=_DTYPE)


class FourierCurve:
    """Periodic curve ``c(p) = a0 + sum_k a_k cos(2 pi k p) + b_k sin(2 pi k p)``, period 1.

    ``keys``: (phase, value) pairs; phases in [0, 1) are taken modulo 1 and linearly
    interpolated around the circle, then the first ``order`` harmonics of that polyline are kept
    (the polyline is sampled at 512 points and transformed). Values keep their unit (the actions
    use degrees in tables and convert once).
    """

    def __init__(self, keys: Sequence[tuple[float, float]], order: int = 5):
        keys = sorted(((float(p) % 1.0, float(v)) for p, v in keys), key=lambda kv: kv[0])
        if len(keys) < 2:
            raise ValueError("FourierCurve: needs at least 2 keyframes (phase, value)")
        p = np.array([k[0] for k in keys])
        v = np.array([k[1] for k in keys])
        grid = np.arange(512) / 512
        dense = np.interp(grid, p, v, period=1.0)
        spec = np.fft.rfft(dense) / 512
        self.order = int(order)
        self.a0 = float(spec[0].real)
        self.a = torch.tensor(2 * spec[1 : order + 1].real, dtype=_DTYPE)
        self.b = torch.tensor(-2 * spec[1 : order + 1].imag, dtype=_DTYPE)

    def __call__(self, phase) -> torch.Tensor:
        phase = _as_tensor(phase)
        k = torch.arange(1, self.order + 1, dtype=_DTYPE)
        ang = 2 * math.pi * phase[..., None] * k
        return self.a0 + (torch.cos(ang) * self.a).sum(-1) + (torch.sin(ang) * self.b).sum(-1)

    def scaled(self, gain: float, offset: float = 0.0) -> "FourierCurve":
        """The curve ``offset + a0 + gain * (c - a0)``: amplitude scaled about its mean."""
        out = object.__new__(FourierCurve)
        out.order, out.a0 = self.order, self.a0 + offset
        out.a, out.b = self.a * gain, self.b * gain
        return out


class KeyframeCurve:
    """Monotone cubic (PCHIP, Fritsch-Carlson) interpolation through keyframes (x, value).

    Constant (first / last value) outside the keyframe range; C1 everywhere; no overshoot
    between keyframes, so a hold (two equal values) stays flat.
    """

    def __init__(self, keys: Sequence[tuple[float, float]]):
        keys = sorted((float(x), float(v)) for x, v in keys)
        x = np.array([k[0] for k in keys])
        y = np.array([k[1] for k in keys])
        if len(x) < 2 or np.any(np.diff(x) <= 0):
            raise ValueError(f"KeyframeCurve: needs >= 2 keyframes with distinct x, got {keys}")
        h = np.diff(x)
        delta = np.diff(y) / h
        m = np.zeros_like(y)
        for i in range(1, len(x) - 1):
            if delta[i - 1] * delta[i] > 0:
                w1 = 2 * h[i] + h[i - 1]
                w2 = h[i] + 2 * h[i - 1]
                m[i] = (w1 + w2) / (w1 / delta[i - 1] + w2 / delta[i])
        self.x = torch.tensor(x, dtype=_DTYPE)
        self.y = torch.tensor(y, dtype=_DTYPE)
        self.m = torch.tensor(m, dtype=_DTYPE)

    def __call__(self, x) -> torch.Tensor:
        x = _as_tensor(x)
        xc = x.clamp(self.x[0], self.x[-1])
        i = (torch.searchsorted(self.x, xc.contiguous(), right=True) - 1).clamp(0, len(self.x) - 2)
        x0, x1 = self.x[i], self.x[i + 1]
        h = x1 - x0
        s = (xc - x0) / h
        h00 = (1 + 2 * s) * (1 - s) ** 2
        h10 = s * (1 - s) ** 2
        h01 = s * s * (3 - 2 * s)
        h11 = s * s * (s - 1)
        return h00 * self.y[i] + h10 * h * self.m[i] + h01 * self.y[i + 1] + h11 * h * self.m[i + 1]


def smoothstep(u) -> torch.Tensor:
    """3u^2 - 2u^3 on [0, 1], clamped: 0 below, 1 above (C1)."""
    u = _as_tensor(u).clamp(0.0, 1.0)
    return u * u * (3 - 2 * u)


def smootherstep(u) -> torch.Tensor:
    """6u^5 - 15u^4 + 10u^3 on [0, 1], clamped (C2)."""
    u = _as_tensor(u).clamp(0.0, 1.0)
    return u * u * u * (u * (6 * u - 15) + 10)


def bump(phase, center: float, width: float) -> torch.Tensor:
    """Periodic bump (von Mises shape), 1 at ``center`` (mod 1), about ``width`` wide (phase units).

    ``exp((cos(2 pi (p - c)) - 1) / (2 pi w)^2)``: close to a Gaussian of standard deviation
    ``width`` near its peak, smooth and periodic with period 1.
    """
    phase = _as_tensor(phase)
    kappa = 1.0 / (2 * math.pi * width) ** 2
    return torch.exp(kappa * (torch.cos(2 * math.pi * (phase - center)) - 1.0))


def window(phase, start: float, end: float, ramp: float) -> torch.Tensor:
    """Periodic smooth window: 1 on [start + ramp, end - ramp] (mod 1), 0 outside [start, end].

    Built from two C2 steps; ``end`` may exceed 1 (the window wraps around).
    """
    phase = _as_tensor(phase)
    p = torch.remainder(phase - start, 1.0)
    length = end - start
    rise = smootherstep(p / ramp)
    fall = 1.0 - smootherstep((p - (length - ramp)) / ramp)
    return torch.where(p <= length, rise * fall, torch.zeros_like(p))


def deg(x) -> torch.Tensor:
    """Degrees -> radians (tensor)."""
    return _as_tensor(x) * (math.pi / 180.0)


def event_weights(t: torch.Tensor, events: list, profile: KeyframeCurve) -> list[torch.Tensor]:
    """Per event (start, duration, ...): its profile over t (T,), 0 outside [start, start + duration]."""
    out = []
    for ev in events:
        u = (t - ev["start"]) / ev["duration"]
        inside = (u > 0) & (u < 1)
        out.append(torch.where(inside, profile(u.clamp(0, 1)), torch.zeros_like(u)))
    return out
