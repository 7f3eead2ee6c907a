"""Ground-contact solver: places the root so that the body stands on the floor (y = 0).

Given local poses (with the heading already in the root rotation) on a fine, uniform internal
time grid, and the subject's :class:`~benchmark.synthetic.rest.RestSkeleton`:

1. Forward kinematics with the root at its rest position gives every contact point (feet, hands)
   relative to the root.
2. Height: on the ground, the root height puts the lowest contact point exactly on y = 0
   (``h(t) = -min_k y_k(t)``); this needs no integration, so it is evaluated at any query time.
3. Horizontal: the lowest points are pinned. Between two grid times the root moves by minus the
   horizontal displacement of the contact points relative to the root, weighted by a soft-min of
   their heights (points within a few millimetres of the lowest share the weight), so a planted
   foot (or hand) does not slide, heading turns included. The displacements are summed over the
   grid; a query time interpolates that integrated track linearly (continuous at any timestamp).
4. Flight: where the action asks for it (running, skipping, jumps), the root follows a ballistic
   parabola between take-off and landing grid times (g = 9.81 m/s^2, fitted to the ground heights
   at both ends) and keeps its take-off horizontal velocity; the parabola never lets a contact
   point go below the floor (the height is ``max(parabola, h)``), and a step where the body
   touches the floor anyway is pinned as on the ground.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from benchmark.body.lbs import forward_kinematics
from benchmark.synthetic.rest import RestSkeleton

GRAVITY = 9.81  # m/s^2
SOFTMIN_TEMPERATURE = 0.001  # m: points within a few mm of the lowest share the pinning
_DTYPE = torch.float64


def contact_points(global_root_rot_local: torch.Tensor, skeleton: RestSkeleton) -> torch.Tensor:
    """Contact points (T, K, 3) for local rotations (T, 22, 3, 3) (root rotation global), with
    the root at its rest position and zero translation."""
    g_rot, joints = forward_kinematics(global_root_rot_local, skeleton.joints.to(global_root_rot_local))
    return skeleton.posed_points(g_rot, joints)


def ground_height(points: torch.Tensor) -> torch.Tensor:
    """(T, K, 3) contact points at zero translation -> (T,) root height that puts the lowest on y = 0."""
    return -points[..., 1].amin(dim=-1)


@dataclass
class RootTrack:
    """The integrated root track on the internal grid.

    times: (N,) uniform grid, seconds; xz: (N, 2) root translation x and z, metres;
    flights: (F, 4) rows (t_takeoff, t_landing, y_takeoff, vy_takeoff) in s, s, m, m/s.
    """

    times: torch.Tensor
    xz: torch.Tensor
    flights: torch.Tensor

    def horizontal(self, t: torch.Tensor) -> torch.Tensor:
        """(T,) times -> (T, 2) root x, z by linear interpolation of the grid track."""
        return interp_uniform(t, self.times, self.xz)

    def height(self, t: torch.Tensor, ground: torch.Tensor) -> torch.Tensor:
        """(T,) times and (T,) ground heights h(t) -> (T,) root height (ballistic inside flights)."""
        y = ground.clone()
        for t0, t1, y0, v0 in self.flights.tolist():
            inside = (t > t0) & (t < t1)
            if inside.any():
                tau = t[inside] - t0
                y[inside] = torch.maximum(y0 + v0 * tau - 0.5 * GRAVITY * tau * tau, ground[inside])
        return y


def interp_uniform(t: torch.Tensor, grid: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """Linear interpolation of values (N, ...) given on a uniform grid (N,) at times t (T,)."""
    dt = (grid[-1] - grid[0]) / (len(grid) - 1)
    u = (t - grid[0]) / dt
    i0 = u.floor().long().clamp(0, len(grid) - 2)
    w = (u - i0.to(u)).clamp(0.0, 1.0)
    w = w.reshape(-1, *([1] * (values.dim() - 1)))
    return values[i0] * (1 - w) + values[i0 + 1] * w


def _runs(mask: torch.Tensor) -> list[tuple[int, int]]:
    """Maximal runs [i, j] (inclusive) of True in a 1-D bool mask."""
    m = mask.to(torch.int8)
    d = torch.diff(torch.cat([m.new_zeros(1), m, m.new_zeros(1)]))
    starts = torch.nonzero(d == 1).flatten().tolist()
    ends = (torch.nonzero(d == -1).flatten() - 1).tolist()
    return list(zip(starts, ends))


def solve_root_track(times: torch.Tensor, points: torch.Tensor, airborne: torch.Tensor, origin_time: float = 0.0) -> RootTrack:
    """Integrate the root's horizontal track and find the flights.

    times: (N,) uniform grid (s); points: (N, K, 3) contact points at zero root translation
    (heading included); airborne: (N,) in [0, 1], > 0.5 where the action asks for flight.
    The track is shifted so that the root's horizontal translation is zero at ``origin_time``.
    """
    N = len(times)
    if points.shape[0] != N or airborne.shape != (N,):
        raise ValueError(
            f"solve_root_track: times ({N},), points {tuple(points.shape)} and airborne "
            f"{tuple(airborne.shape)} must share the grid length"
        )
    dt = float(times[1] - times[0])
    h = ground_height(points)  # (N,)
    y = points[..., 1] + h[:, None]  # heights above the floor when standing
    w = torch.softmax(-y / SOFTMIN_TEMPERATURE, dim=-1)  # (N, K)
    w_step = 0.5 * (w[1:] + w[:-1])
    rel = points[1:, :, [0, 2]] - points[:-1, :, [0, 2]]  # (N-1, K, 2)
    step = -(w_step[..., None] * rel).sum(1)  # (N-1, 2) pinned displacement

    # Flights: runs of airborne grid points strictly inside the grid.
    flights = []
    air = airborne > 0.5
    for i, j in _runs(air):
        a, b = i - 1, j + 1  # last grounded before, first grounded after
        if a < 1 or b > N - 1:
            continue  # touches the grid ends: no take-off to start from; treat as ground
        t0, t1 = float(times[a]), float(times[b])
        T = t1 - t0
        y0, y1 = float(h[a]), float(h[b])
        v0 = (y1 - y0) / T + 0.5 * GRAVITY * T
        flights.append((t0, t1, y0, v0))
        tau = times[a:b + 1] - t0
        par = y0 + v0 * tau - 0.5 * GRAVITY * tau * tau
        off_ground = par > h[a:b + 1] + 1e-6  # (b - a + 1,)
        # a step is ballistic if the body is off the ground at both of its ends (interior ones)
        flying = off_ground[1:] & off_ground[:-1]
        flying[0] = flying[0] | off_ground[1]
        flying[-1] = flying[-1] | off_ground[-2]
        v_takeoff = step[a - 1] / dt
        seg = torch.arange(a, b)
        step[seg[flying]] = v_takeoff * dt
    xz = torch.cat([step.new_zeros(1, 2), step.cumsum(0)])
    xz = xz - interp_uniform(torch.tensor([origin_time], dtype=_DTYPE), times, xz)
    fl = torch.tensor(flights, dtype=_DTYPE) if flights else torch.zeros(0, 4, dtype=_DTYPE)
    return RootTrack(times=times, xz=xz, flights=fl)
