"""HM-VAE's trajectory model (Li et al. 3DV 2021 §3.3; ``lijiaman/hm-vae: trajectory_pred_model.py``).

Input: joint positions (B, T, 24, 3) by forward kinematics of the (decoded) rotations on a fixed
skeleton, root orientation included, root at its rest position; standardised per dimension with
the training data's mean/std. Four blocks SkeletonConv(k, stride 1) -> SkeletonPool ->
LeakyReLU(0.2) with channels per edge ``(3, 6, 12, 24, 48)`` and edges 24 -> 14 -> 9 -> 7 -> 7,
then per frame ``fc_mapping = Linear(7 * 48 = 336 -> 3)``: the standardised root velocity
``V_t = trans_t - trans_{t-1}`` (world frame). De-standardised, the trajectory is
``G_t = sum_{1 <= i <= t} V_i`` (``G_0 = 0``: the official ``gen_motion_w_trajectory`` skips frame 0).

Paper size (``PAPER_TRAJECTORY_CONFIG``, ``configs/trajectory_model.yaml``): k = 31, channels
(3, 6, 12, 24, 48), trained on 128-frame windows with L2 on the velocity and on the integrated
trajectory; 3,233,811 learnable weights (2,636,751 non-zero under the masks; raw nn.Parameter
count 6,645,171 with the frozen masks and pooling matrices). State-dict keys as the official ``TrajectoryModel``: ``enc.layers.{i}.0.{weight,bias,
mask}``, ``enc.layers.{i}.1.weight``, ``fc_mapping.{weight,bias}``. The standardisation statistics
(official: ``all_amass_data_mean_std.npy`` dims 360:432 and 576:579) and the FK skeleton (official:
``skeleton_offsets.npy``) are plain attributes in the official code, not in its checkpoints; here
they are non-persistent buffers set by the loader.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from benchmark.body.lbs import forward_kinematics
from priors.hmvae.skeleton import NUM_JOINTS24, PARENTS24, SkeletonConv, SkeletonPool, neighbour_lists, topology_levels

NUM_LEVELS = 4


@dataclass(frozen=True)
class TrajectoryConfig:
    kernel_size: int = 31
    channels: tuple = (3, 6, 12, 24, 48)
    skeleton_dist: int = 2
    world_up: str = "z"

    def __post_init__(self):
        object.__setattr__(self, "channels", tuple(int(c) for c in self.channels))
        if len(self.channels) != NUM_LEVELS + 1 or self.channels[0] != 3:
            raise ValueError(f"TrajectoryConfig.channels must be 5 per-edge widths starting with 3 (positions), got {self.channels}")
        if self.kernel_size % 2 != 1:
            raise ValueError(f"TrajectoryConfig.kernel_size must be odd, got {self.kernel_size}")
        if self.world_up not in ("y", "z"):
            raise ValueError(f"TrajectoryConfig.world_up must be 'y' or 'z', got {self.world_up!r}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["channels"] = list(self.channels)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TrajectoryConfig":
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown trajectory config fields {sorted(unknown)}")
        return cls(**d)


PAPER_TRAJECTORY_CONFIG = TrajectoryConfig()


class TrajectoryEncoder(nn.Module):
    """``enc``: 4 blocks SkeletonConv (stride 1) -> SkeletonPool -> LeakyReLU(0.2)."""

    def __init__(self, cfg: TrajectoryConfig):
        super().__init__()
        levels, groups = topology_levels(NUM_LEVELS)
        C = cfg.channels
        self.layers = nn.ModuleList()
        for i in range(NUM_LEVELS):
            nb = neighbour_lists(levels[i], cfg.skeleton_dist)
            self.layers.append(nn.Sequential(
                SkeletonConv(nb, C[i], C[i + 1], cfg.kernel_size, stride=1, bias=True),
                SkeletonPool(groups[i], len(levels[i]), C[i + 1]),
                nn.LeakyReLU(0.2),
            ))
        self.out_edges = len(groups[-1])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for layer in self.layers:
            x = layer(x)
        return x


class TrajectoryModel(nn.Module):
    """Root velocity from joint positions (module docstring). Buffers (not in the state dict):
    ``pos_mean``/``pos_std`` (72,), ``vel_mean``/``vel_std`` (3,), ``rest_joints`` (24, 3)."""

    def __init__(self, config: TrajectoryConfig = PAPER_TRAJECTORY_CONFIG):
        super().__init__()
        self.config = config
        self.enc = TrajectoryEncoder(config)
        self.fc_mapping = nn.Linear(config.channels[-1] * self.enc.out_edges, 3)
        self.register_buffer("pos_mean", torch.zeros(NUM_JOINTS24 * 3), persistent=False)
        self.register_buffer("pos_std", torch.ones(NUM_JOINTS24 * 3), persistent=False)
        self.register_buffer("vel_mean", torch.zeros(3), persistent=False)
        self.register_buffer("vel_std", torch.ones(3), persistent=False)
        self.register_buffer("rest_joints", torch.zeros(NUM_JOINTS24, 3), persistent=False)
        for m in self.modules():  # official weights_init('kaiming') on nn.Linear
            if isinstance(m, nn.Linear):
                nn.init.kaiming_normal_(m.weight, a=0, mode="fan_in")
                nn.init.zeros_(m.bias)

    @torch.no_grad()
    def set_statistics(self, pos_mean, pos_std, vel_mean, vel_std, rest_joints) -> None:
        """Standardisation statistics and FK skeleton (std == 0 replaced by 1, as the official code)."""
        def t(x, shape, name):
            x = torch.as_tensor(x, dtype=torch.float32).reshape(-1)
            if x.numel() != int(torch.tensor(shape).prod()):
                raise ValueError(f"trajectory model: {name} must have {shape} values, got {x.numel()}")
            return x.reshape(shape)
        ps, vs = t(pos_std, (NUM_JOINTS24 * 3,), "pos_std"), t(vel_std, (3,), "vel_std")
        self.pos_mean.copy_(t(pos_mean, (NUM_JOINTS24 * 3,), "pos_mean"))
        self.pos_std.copy_(torch.where(ps == 0, torch.ones_like(ps), ps))
        self.vel_mean.copy_(t(vel_mean, (3,), "vel_mean"))
        self.vel_std.copy_(torch.where(vs == 0, torch.ones_like(vs), vs))
        self.rest_joints.copy_(t(rest_joints, (NUM_JOINTS24, 3), "rest_joints"))

    def statistics(self) -> dict:
        return {k: getattr(self, k).tolist() for k in ("pos_mean", "pos_std", "vel_mean", "vel_std", "rest_joints")}

    def joint_positions(self, rotations: torch.Tensor) -> torch.Tensor:
        """(B, T, 24, 3, 3) local rotations -> (B, T, 24, 3) FK positions on ``rest_joints``."""
        return forward_kinematics(rotations, self.rest_joints, parents=PARENTS24)[1]

    def forward(self, joints: torch.Tensor) -> torch.Tensor:
        """(B, T, 24, 3) joint positions -> (B, T, 3) standardised root velocity (the network output)."""
        B, T = joints.shape[:2]
        x = ((joints.reshape(B, T, -1) - self.pos_mean) / self.pos_std).transpose(1, 2)  # (B, 72, T)
        h = self.enc(x)  # (B, 7*C, T)
        h = h.reshape(B, self.enc.out_edges, -1, T).permute(0, 3, 1, 2).reshape(B, T, -1)
        return self.fc_mapping(h)

    def velocity(self, joints: torch.Tensor) -> torch.Tensor:
        """(B, T, 24, 3) -> (B, T, 3) root velocity in metres per frame (de-standardised)."""
        return self.forward(joints) * self.vel_std + self.vel_mean

    def trajectory(self, joints: torch.Tensor) -> torch.Tensor:
        """(B, T, 24, 3) -> (B, T, 3) integrated root trajectory, G_0 = 0."""
        return integrate_velocity(self.velocity(joints))


def integrate_velocity(v: torch.Tensor) -> torch.Tensor:
    """(B, T, 3) per-frame velocities -> (B, T, 3) ``G_t = sum_{1<=i<=t} v_i`` (frame 0's velocity unused)."""
    return torch.cat([torch.zeros_like(v[:, :1]), v[:, 1:]], dim=1).cumsum(dim=1)


def root_velocity(trans: torch.Tensor) -> torch.Tensor:
    """(B, T, 3) translations -> (B, T, 3) ``trans_t - trans_{t-1}``, 0 at frame 0."""
    return torch.cat([torch.zeros_like(trans[:, :1]), trans[:, 1:] - trans[:, :-1]], dim=1)


__all__ = [
    "TrajectoryConfig",
    "PAPER_TRAJECTORY_CONFIG",
    "TrajectoryEncoder",
    "TrajectoryModel",
    "integrate_velocity",
    "root_velocity",
]
