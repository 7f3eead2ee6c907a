"""Skeleton-aware operators of HM-VAE (after Aberman et al., "Skeleton-aware networks", SIGGRAPH 2020).

HM-VAE (Li et al. 3DV 2021, ``lijiaman/hm-vae: skeleton.py``) works on *edges* of the 24-joint
skeleton, not on joints:

- joints: SMPL 0..21 plus SMPL-H ``left_index1`` (22, parent 20) and ``right_index1`` (23,
  parent 21), :data:`PARENTS24`;
- edges: a virtual root edge ``(0, 24)`` (24 = a virtual joint above the pelvis, put second so
  pooling keeps the edge) followed by the 23 bones ``(parent[j], j)`` for j = 1..23, so edge ``e``
  (e >= 1) carries the rotation of joint ``e`` and edge 0 the root orientation (:func:`edges24`);
- distance between two edges: 1 when they share a joint, graph distance otherwise
  (:func:`edge_distances`); a skeleton convolution lets output edge i see the input edges within
  distance ``d`` (2 in HM-VAE) (:func:`neighbour_lists`);
- pooling: the edge list is walked depth-first from the root; chains of edges through joints of
  degree 2 are cut at joints of degree > 2 and at end effectors, and each chain is averaged in
  consecutive pairs, an odd chain keeping its first edge alone (:func:`pooling_groups`). The
  merged edge of a pair ``(a, b)`` runs from a's parent joint to b's child joint. Applied four
  times this gives 24 -> 14 -> 9 -> 7 -> 7 edges; the fourth ("last") pooling keeps whole
  chains, which are single edges at that level, so it is the identity.

Tensors are laid out as in the official code: ``(batch, edges * channels, time)``, edge-major.
The masks and pooling/unpooling matrices are ``nn.Parameter(requires_grad=False)`` because the
official checkpoints store them under ``.mask`` / ``.weight``; they are fixed functions of the
topology and are rebuilt (and compared) when a checkpoint is loaded.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from benchmark.core.skeleton import PARENTS

PARENTS24 = tuple(PARENTS) + (20, 21)  # SMPL-22 + SMPL-H left_index1 (22), right_index1 (23)
NUM_JOINTS24 = len(PARENTS24)
VIRTUAL_JOINT = NUM_JOINTS24  # the child end of the virtual root edge (0, 24)
NUM_EDGES24 = NUM_JOINTS24  # virtual root edge + 23 bones
SKELETON_DIST = 2  # HM-VAE `skeleton_dist`


def edges24(parents: tuple[int, ...] = PARENTS24) -> list[tuple[int, int]]:
    """The level-0 edges: ``[(0, J), (parents[1], 1), ..., (parents[J-1], J-1)]`` with J joints."""
    J = len(parents)
    return [(0, J)] + [(parents[j], j) for j in range(1, J)]


def edge_distances(edges: list[tuple[int, int]]) -> list[list[int]]:
    """All-pairs edge distances: 0 on the diagonal, 1 for edges sharing a joint, shortest path else."""
    n = len(edges)
    inf = 10**6
    d = [[0 if i == j else (1 if set(edges[i]) & set(edges[j]) else inf) for j in range(n)] for i in range(n)]
    for k in range(n):
        dk = d[k]
        for i in range(n):
            dik = d[i][k]
            if dik >= inf:
                continue
            di = d[i]
            for j in range(n):
                if dik + dk[j] < di[j]:
                    di[j] = dik + dk[j]
    return d


def neighbour_lists(edges: list[tuple[int, int]], dist: int = SKELETON_DIST) -> list[list[int]]:
    """For each edge i, the sorted edges j with distance(i, j) <= ``dist`` (i itself included)."""
    d = edge_distances(edges)
    return [[j for j in range(len(edges)) if d[i][j] <= dist] for i in range(len(edges))]


def _chains(edges: list[tuple[int, int]]) -> list[list[int]]:
    """Edge chains in depth-first order from joint 0, cut at joints of degree > 2 and at end effectors."""
    degree: dict[int, int] = {}
    for a, b in edges:
        degree[a] = degree.get(a, 0) + 1
        degree[b] = degree.get(b, 0) + 1
    children: dict[int, list[int]] = {}
    for idx, (a, _) in enumerate(edges):
        children.setdefault(a, []).append(idx)  # in edge order, as the official DFS visits them
    chains: list[list[int]] = []

    def walk(joint: int, chain: list[int]) -> None:
        if degree[joint] > 2 and joint != 0:
            chains.append(chain)
            chain = []
        if degree[joint] == 1:
            chains.append(chain)
            return
        for idx in children.get(joint, []):
            walk(edges[idx][1], chain + [idx])

    walk(0, [])
    return chains


def pooling_groups(edges: list[tuple[int, int]], last: bool = False) -> tuple[list[list[int]], list[tuple[int, int]]]:
    """(groups of input edges merged into each output edge, output edges).

    ``last=True`` is the official ``last_pool``: every chain is one group (the identity on the
    7-edge level of the SMPL skeleton) and no output topology is defined (returns ``[]``).
    """
    groups: list[list[int]] = []
    new_edges: list[tuple[int, int]] = []
    for chain in _chains(edges):
        if last:
            groups.append(list(chain))
            continue
        if len(chain) % 2 == 1:
            groups.append([chain[0]])
            new_edges.append(tuple(edges[chain[0]]))
            chain = chain[1:]
        for i in range(0, len(chain), 2):
            a, b = chain[i], chain[i + 1]
            groups.append([a, b])
            new_edges.append((edges[a][0], edges[b][1]))
    return groups, new_edges


def topology_levels(num_levels: int = 4, parents: tuple[int, ...] = PARENTS24) -> tuple[list, list]:
    """Edges per level (``num_levels + 1`` entries; the last is ``[]`` after the last pooling, as in
    the official code) and the pooling groups of each level (``num_levels`` entries)."""
    levels = [edges24(parents)]
    groups = []
    for i in range(num_levels):
        g, new = pooling_groups(levels[-1], last=(i == num_levels - 1))
        groups.append(g)
        levels.append(new)
    return levels, groups


def conv_mask(neighbours: list[list[int]], c_in: int, c_out: int, kernel_size: int) -> torch.Tensor:
    """(E*c_out, E*c_in, k) 0/1 mask: output edge i's channels see input edges ``neighbours[i]``."""
    E = len(neighbours)
    m = torch.zeros(E * c_out, E * c_in, kernel_size)
    for i, nb in enumerate(neighbours):
        for j in nb:
            m[i * c_out : (i + 1) * c_out, j * c_in : (j + 1) * c_in] = 1.0
    return m


def pool_matrix(groups: list[list[int]], num_in_edges: int, channels: int) -> torch.Tensor:
    """(G*C, E*C) averaging matrix: output edge g is the mean of its group's input edges."""
    W = torch.zeros(len(groups) * channels, num_in_edges * channels)
    eye = torch.eye(channels)
    for g, group in enumerate(groups):
        for e in group:
            W[g * channels : (g + 1) * channels, e * channels : (e + 1) * channels] = eye / len(group)
    return W


def unpool_matrix(groups: list[list[int]], channels: int) -> torch.Tensor:
    """(E*C, G*C) copy matrix: every input edge of group g receives g's features."""
    num_out = sum(len(g) for g in groups)
    W = torch.zeros(num_out * channels, len(groups) * channels)
    eye = torch.eye(channels)
    for g, group in enumerate(groups):
        for e in group:
            W[e * channels : (e + 1) * channels, g * channels : (g + 1) * channels] = eye
    return W


class SkeletonConv(nn.Module):
    """Temporal Conv1d over ``edges * c_in`` channels with a fixed neighbourhood mask.

    ``weight`` (E*c_out, E*c_in, k), ``bias`` (E*c_out) or None, ``mask`` (same as weight, frozen).
    Reflection padding of (k-1)//2 on both sides, then the strided convolution with
    ``weight * mask`` (so masked-out weights never act, whatever their stored value).
    Initialisation as the official code: each output edge's unmasked block gets
    ``kaiming_uniform_(a=sqrt(5))`` and its bias ``U(-1/sqrt(fan_in), 1/sqrt(fan_in))`` with the
    block's fan-in; masked entries are 0.
    """

    def __init__(self, neighbours: list[list[int]], c_in: int, c_out: int, kernel_size: int, stride: int = 1,
                 bias: bool = True):
        super().__init__()
        E = len(neighbours)
        self.num_edges, self.c_in, self.c_out = E, int(c_in), int(c_out)
        self.kernel_size, self.stride = int(kernel_size), int(stride)
        self.padding = (self.kernel_size - 1) // 2
        self.weight = nn.Parameter(torch.zeros(E * c_out, E * c_in, kernel_size))
        self.bias = nn.Parameter(torch.zeros(E * c_out)) if bias else None
        self.mask = nn.Parameter(conv_mask(neighbours, c_in, c_out, kernel_size), requires_grad=False)
        self.neighbours = [list(n) for n in neighbours]
        self.reset_parameters()

    @torch.no_grad()
    def reset_parameters(self) -> None:
        self.weight.zero_()
        for i, nb in enumerate(self.neighbours):
            cols = torch.cat([torch.arange(j * self.c_in, (j + 1) * self.c_in) for j in nb])
            block = torch.empty(self.c_out, len(cols), self.kernel_size)
            nn.init.kaiming_uniform_(block, a=math.sqrt(5))
            self.weight[i * self.c_out : (i + 1) * self.c_out, cols] = block
            if self.bias is not None:
                bound = 1.0 / math.sqrt(len(cols) * self.kernel_size)
                self.bias[i * self.c_out : (i + 1) * self.c_out].uniform_(-bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.padding:
            x = F.pad(x, (self.padding, self.padding), mode="reflect")
        return F.conv1d(x, self.weight * self.mask, self.bias, stride=self.stride)

    def extra_repr(self) -> str:
        return (f"edges={self.num_edges}, channels/edge {self.c_in}->{self.c_out}, kernel={self.kernel_size}, "
                f"stride={self.stride}, bias={self.bias is not None}")


class SkeletonPool(nn.Module):
    """Mean pooling of edge groups: ``(B, E*C, T) -> (B, G*C, T)``.

    ``weight`` (G*C, E*C) is the official frozen averaging matrix (stored in checkpoints); the
    forward pass computes the same means with index gathers over the edge axis (non-persistent
    buffers derived from the groups), ~C times cheaper than the dense product. Loaders check a
    checkpoint's ``weight`` equals the one rebuilt here, so the two always agree.
    """

    def __init__(self, groups: list[list[int]], num_in_edges: int, channels: int):
        super().__init__()
        self.groups = [list(g) for g in groups]
        self.channels = int(channels)
        self.weight = nn.Parameter(pool_matrix(groups, num_in_edges, channels), requires_grad=False)
        K = max(len(g) for g in groups)
        idx = torch.tensor([[g[k] if k < len(g) else g[0] for g in groups] for k in range(K)], dtype=torch.long)
        w = torch.tensor([[1.0 / len(g) if k < len(g) else 0.0 for g in groups] for k in range(K)])
        self.register_buffer("gather_index", idx, persistent=False)  # (K, G)
        self.register_buffer("gather_weight", w[..., None], persistent=False)  # (K, G, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, _, T = x.shape
        x = x.reshape(B, -1, self.channels * T)
        out = x.index_select(1, self.gather_index[0]) * self.gather_weight[0]
        for k in range(1, self.gather_index.shape[0]):
            out = out + x.index_select(1, self.gather_index[k]) * self.gather_weight[k]
        return out.reshape(B, -1, T)

    def extra_repr(self) -> str:
        return f"edges {self.weight.shape[1] // self.channels}->{len(self.groups)}, channels/edge={self.channels}"


class SkeletonUnpool(nn.Module):
    """Copy unpooling: ``(B, G*C, T) -> (B, E*C, T)``, every edge of group g receives g's features.

    ``weight`` (E*C, G*C) is the official frozen copy matrix (stored); the forward pass is the
    equivalent gather over the edge axis.
    """

    def __init__(self, groups: list[list[int]], channels: int):
        super().__init__()
        self.groups = [list(g) for g in groups]
        self.channels = int(channels)
        self.weight = nn.Parameter(unpool_matrix(groups, channels), requires_grad=False)
        owner = {e: g for g, group in enumerate(groups) for e in group}
        self.register_buffer("gather_index", torch.tensor([owner[e] for e in range(len(owner))], dtype=torch.long),
                             persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, _, T = x.shape
        return x.reshape(B, -1, self.channels * T).index_select(1, self.gather_index).reshape(B, -1, T)

    def extra_repr(self) -> str:
        return f"edges {len(self.groups)}->{self.weight.shape[0] // self.channels}, channels/edge={self.channels}"


def frozen_parameter_names(module: nn.Module) -> set[str]:
    """Names (as in ``module.state_dict()``) of the topology-derived frozen tensors: conv masks and
    pooling / unpooling matrices."""
    names = set()
    for prefix, m in module.named_modules(remove_duplicate=False):
        p = f"{prefix}." if prefix else ""
        if isinstance(m, SkeletonConv):
            names.add(p + "mask")
        elif isinstance(m, (SkeletonPool, SkeletonUnpool)):
            names.add(p + "weight")
    return names


__all__ = [
    "PARENTS24",
    "NUM_JOINTS24",
    "NUM_EDGES24",
    "SKELETON_DIST",
    "edges24",
    "edge_distances",
    "neighbour_lists",
    "pooling_groups",
    "topology_levels",
    "conv_mask",
    "pool_matrix",
    "unpool_matrix",
    "SkeletonConv",
    "SkeletonPool",
    "SkeletonUnpool",
    "frozen_parameter_names",
]
