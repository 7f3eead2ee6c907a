"""The HM-VAE network (Li et al. 3DV 2021, ``lijiaman/hm-vae: seq_two_hier_sa_vae.py`` Encoder/Decoder).

Input/output: a window of ``seq_len`` frames of 24 joint rotations in 6D "columns" layout
([R[:, 0], R[:, 1]] concatenated; root orientation = joint 0), laid out ``(B, 24*6, T)``
edge-major (edge e carries joint e; edge 0 is the virtual root edge carrying the root).

Encoder (4 blocks, each SkeletonConv -> SkeletonPool -> LeakyReLU(0.2)); with channels per edge
``C = (C0..C4)``, level edges ``E = (24, 14, 9, 7, 7)`` and frame counts ``T_i``:

    block i: SkeletonConv(E_i edges, C_i -> C_{i+1}, k, stride s_i) ; pool E_i -> E_{i+1}
    head i:  Linear(C_{i+1} * T_{i+1} -> 2 d_i) per pooled edge (d_0 = shallow_latent_d, else latent_d)

Only head 0 (shallow/local ``z_l``, E_1 = 14 edges) and head 3 (deep/global ``z_g``, 7 edges) are
used; heads 1 and 2 exist (their weights are in the official checkpoints) but their latents are
ignored by the decoder and carry no KL term.

Decoder (block k = 0..3 mirrors encoder level l = 3 - k):

    z_g -> Linear(latent_d -> C4 * T4) per edge -> (B, 7*C4, T4)
    block k: [Upsample x2 (linear) if s_l == 2] -> SkeletonUnpool(E_{l+1} -> E_l)
             -> SkeletonConv(E_l edges, c_in -> C_l, k, stride 1, bias only in blocks 0 and 3)
             -> LeakyReLU(0.2) except after block 3
    with c_in = C_{l+1}, except before block 3 where z_l -> Linear(shallow_latent_d -> C1 * T1) per
    edge is concatenated per edge with block 2's output (14 edges x (C1 + C1)), so c_in = 2 C1.

Sizes (``PAPER_CONFIG``, len-64 model of ``configs/len_64_test_interpolation.yaml``): k = 15,
C = (6, 12, 24, 48, 96), strides (2, 2, 2, 2), T = 64, 32, 16, 8, 4; latent_d = 24 (z_g: 7 x 24),
shallow_latent_d = 12 (z_l: 14 x 12); 13,233,480 stored weights (the masked conv weights counted in
full, = the "13.2 M" dense-equivalent of docs/priors.md), of which 10,457,880 can be non-zero under the
distance-2 masks; the frozen masks and pooling/unpooling matrices add 14,713,344 stored numbers, so
the raw ``nn.Parameter`` count is 27,946,824 (see :func:`parameter_summary`). Embedded size: see
:mod:`priors.hmvae.train` (kernel 7, channels (6, 8, 16, 32, 64): 2,984,600 weights).
Note: the released *training* config ``configs/len64_no_aug_hm_vae.yaml`` says
``shallow_latent_d: 24``, while the test/interpolation config (the one the completion code loads
the trained model with) says 12; we follow the test config (12).
``LEN8_CONFIG``: the video-refinement model (k = 3, latents 6/6, strides 1, 2, 2, 1, T = 8, 8, 4,
2, 2; no upsampling in decoder blocks 0 and 3, so those blocks' module indices shift by one).

Module and attribute names reproduce the official state-dict keys (``enc.layers.{i}.0.{weight,
bias,mask}``, ``enc.layers.{i}.1.weight``, ``enc.latent_enc_layers.{i}.*``, ``dec.layers.{k}.{j}.*``,
``dec.unpools.{k}.weight``, ``dec.latent_dec_layers.{k}.*``), except that the decoder here does not
hold the encoder, so the official duplicate ``dec.enc.*`` keys are not part of this model; the
loader (:mod:`priors.hmvae.checkpoint`) checks they equal ``enc.*`` and drops them, and
:func:`official_state_dict` adds them back when writing the official layout.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from priors.hmvae.skeleton import (
    NUM_JOINTS24,
    SkeletonConv,
    SkeletonPool,
    SkeletonUnpool,
    frozen_parameter_names,
    neighbour_lists,
    topology_levels,
)

NUM_LEVELS = 4


@dataclass(frozen=True)
class HMVAEConfig:
    """Architecture of an HM-VAE window model (see the module docstring).

    world_up: the up axis of the world the model was trained in: "z" for the AMASS world of the
    official code, "y" for this project's data; the adapter converts the root orientation.
    """

    seq_len: int = 64
    kernel_size: int = 15
    channels: tuple = (6, 12, 24, 48, 96)
    strides: tuple = (2, 2, 2, 2)
    latent_d: int = 24
    shallow_latent_d: int = 12
    skeleton_dist: int = 2
    world_up: str = "z"

    def __post_init__(self):
        object.__setattr__(self, "channels", tuple(int(c) for c in self.channels))
        object.__setattr__(self, "strides", tuple(int(s) for s in self.strides))
        if len(self.channels) != NUM_LEVELS + 1 or self.channels[0] != 6:
            raise ValueError(f"HMVAEConfig.channels must be 5 per-edge widths starting with 6 (6D input), got {self.channels}")
        if len(self.strides) != NUM_LEVELS or any(s not in (1, 2) for s in self.strides):
            raise ValueError(f"HMVAEConfig.strides must be 4 values in {{1, 2}}, got {self.strides}")
        if self.kernel_size % 2 != 1 or self.kernel_size < 1:
            raise ValueError(f"HMVAEConfig.kernel_size must be odd (symmetric reflection padding), got {self.kernel_size}")
        if self.world_up not in ("y", "z"):
            raise ValueError(f"HMVAEConfig.world_up must be 'y' or 'z', got {self.world_up!r}")
        t = self.seq_len
        for s in self.strides:
            if t % s:
                raise ValueError(f"HMVAEConfig: seq_len {self.seq_len} is not divisible through strides {self.strides}")
            t //= s
        if (self.kernel_size - 1) // 2 >= min(self.timesteps[:-1]):
            raise ValueError(f"HMVAEConfig: kernel {self.kernel_size} too large for reflection padding at {self.timesteps} frames")

    @property
    def timesteps(self) -> tuple:
        """Frames after each encoder block: (T0, T1, T2, T3, T4)."""
        t = [self.seq_len]
        for s in self.strides:
            t.append(t[-1] // s)
        return tuple(t)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["channels"], d["strides"] = list(self.channels), list(self.strides)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "HMVAEConfig":
        known = set(cls.__dataclass_fields__)
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown HM-VAE config fields {sorted(unknown)}; expected a subset of {sorted(known)}")
        return cls(**d)


PAPER_CONFIG = HMVAEConfig()  # len-64, official world (z up)
LEN8_CONFIG = HMVAEConfig(seq_len=8, kernel_size=3, latent_d=6, shallow_latent_d=6, strides=(1, 2, 2, 1))


class Encoder(nn.Module):
    """``enc``: 4 skeleton blocks and 4 latent heads (``layers``, ``latent_enc_layers``)."""

    def __init__(self, cfg: HMVAEConfig):
        super().__init__()
        levels, groups = topology_levels(NUM_LEVELS)
        C, T = cfg.channels, cfg.timesteps
        self.edge_counts = [len(levels[0])] + [len(g) for g in groups]  # 24, 14, 9, 7, 7
        self.layers = nn.ModuleList()
        self.latent_enc_layers = nn.ModuleList()
        for i in range(NUM_LEVELS):
            nb = neighbour_lists(levels[i], cfg.skeleton_dist)
            conv = SkeletonConv(nb, C[i], C[i + 1], cfg.kernel_size, stride=cfg.strides[i], bias=True)
            pool = SkeletonPool(groups[i], len(levels[i]), C[i + 1])
            self.layers.append(nn.Sequential(conv, pool, nn.LeakyReLU(0.2)))
            d = cfg.shallow_latent_d if i == 0 else cfg.latent_d
            self.latent_enc_layers.append(nn.Linear(C[i + 1] * T[i + 1], 2 * d))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 24*6, T) -> (shallow head output (B, 14, 2 d_l), deep head output (B, 7, 2 d_g))."""
        B = x.shape[0]
        h = self.layers[0](x)
        shallow = self.latent_enc_layers[0](h.reshape(B, self.edge_counts[1], -1))
        for i in range(1, NUM_LEVELS):
            h = self.layers[i](h)
        deep = self.latent_enc_layers[NUM_LEVELS - 1](h.reshape(B, self.edge_counts[NUM_LEVELS], -1))
        return shallow, deep


class Decoder(nn.Module):
    """``dec``: latent heads (``latent_dec_layers``), 4 blocks (``layers``) and their ``unpools``."""

    def __init__(self, cfg: HMVAEConfig):
        super().__init__()
        levels, groups = topology_levels(NUM_LEVELS)
        C, T = cfg.channels, cfg.timesteps
        self.edge_counts = [len(levels[0])] + [len(g) for g in groups]
        self.timesteps = T
        self.layers = nn.ModuleList()
        self.unpools = nn.ModuleList()
        self.latent_dec_layers = nn.ModuleList()
        for k in range(NUM_LEVELS):
            lvl = NUM_LEVELS - 1 - k
            last = k == NUM_LEVELS - 1
            c_in = 2 * C[1] if last else C[lvl + 1]
            if last:
                self.latent_dec_layers.append(nn.Linear(cfg.shallow_latent_d, C[1] * T[1]))
            else:
                self.latent_dec_layers.append(nn.Linear(cfg.latent_d, C[NUM_LEVELS - k] * T[NUM_LEVELS - k]))
            unpool = SkeletonUnpool(groups[lvl], c_in)
            self.unpools.append(unpool)
            nb = neighbour_lists(levels[lvl], cfg.skeleton_dist)
            seq = []
            if cfg.strides[lvl] == 2:
                seq.append(nn.Upsample(scale_factor=2, mode="linear", align_corners=False))
            seq += [unpool, SkeletonConv(nb, c_in, C[lvl], cfg.kernel_size, stride=1, bias=(k == 0 or last))]
            if not last:
                seq.append(nn.LeakyReLU(0.2))
            self.layers.append(nn.Sequential(*seq))

    def forward(self, z_g: torch.Tensor, z_l: torch.Tensor) -> torch.Tensor:
        """z_g (B, 7, latent_d), z_l (B, 14, shallow_latent_d) -> (B, 24*6, T0)."""
        B = z_g.shape[0]
        T = self.timesteps
        h = self.latent_dec_layers[0](z_g).reshape(B, -1, T[NUM_LEVELS])
        for k in range(NUM_LEVELS - 1):
            h = self.layers[k](h)
        E1 = self.edge_counts[1]
        local = self.latent_dec_layers[NUM_LEVELS - 1](z_l).reshape(B, E1, -1, T[1])
        h = torch.cat([h.reshape(B, E1, -1, T[1]), local], dim=2).reshape(B, -1, T[1])
        return self.layers[NUM_LEVELS - 1](h)


class HMVAE(nn.Module):
    """The HM-VAE window model (``TwoHierSAVAEModel`` without its data, FK and optimisation code).

    ``encode`` and ``decode`` take/return 6D rotations (B, T, 24, 6) in the model's world
    (``config.world_up``); ``forward`` is the training pass (reparameterised latents).
    """

    def __init__(self, config: HMVAEConfig = PAPER_CONFIG):
        super().__init__()
        self.config = config
        self.enc = Encoder(config)
        self.dec = Decoder(config)
        self.init_linear_kaiming()

    @torch.no_grad()
    def init_linear_kaiming(self) -> None:
        """The official ``weights_init('kaiming')``: ``nn.Linear`` weights kaiming-normal (fan-in), biases 0
        (it matches class names starting with Conv/Linear, so SkeletonConv keeps its own init)."""
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.kaiming_normal_(m.weight, a=0, mode="fan_in")
                nn.init.zeros_(m.bias)

    @property
    def num_local_edges(self) -> int:
        return self.enc.edge_counts[1]

    @property
    def num_global_edges(self) -> int:
        return self.enc.edge_counts[NUM_LEVELS]

    def _check_sixd(self, sixd: torch.Tensor) -> None:
        T = self.config.seq_len
        if sixd.dim() != 4 or tuple(sixd.shape[1:]) != (T, NUM_JOINTS24, 6):
            raise ValueError(f"HM-VAE input must be (B, {T}, {NUM_JOINTS24}, 6) 6D rotations, got {tuple(sixd.shape)}")

    def encode(self, sixd: torch.Tensor) -> dict[str, torch.Tensor]:
        """(B, T, 24, 6) -> {"mu_g", "logvar_g"} (B, 7, latent_d) and {"mu_l", "logvar_l"} (B, 14, shallow_d)."""
        self._check_sixd(sixd)
        x = sixd.flatten(2).transpose(1, 2)
        shallow, deep = self.enc(x)
        dl, dg = self.config.shallow_latent_d, self.config.latent_d
        return {"mu_l": shallow[..., :dl], "logvar_l": shallow[..., dl:], "mu_g": deep[..., :dg], "logvar_g": deep[..., dg:]}

    def decode(self, z_g: torch.Tensor, z_l: torch.Tensor) -> torch.Tensor:
        """z_g (B, 7, latent_d), z_l (B, 14, shallow_d) -> raw 6D (B, T, 24, 6) (not orthonormalised)."""
        out = self.dec(z_g, z_l)  # (B, 144, T)
        return out.transpose(1, 2).reshape(z_g.shape[0], self.config.seq_len, NUM_JOINTS24, 6)

    def forward(self, sixd: torch.Tensor, sample: bool = True, detach_local: bool = False) -> dict[str, torch.Tensor]:
        """Training pass. ``detach_local``: the official deep-only phase (the shallow code and its KL
        are detached). Returns the posterior parameters, the latents used and the decoded 6D."""
        q = self.encode(sixd)
        if sample:
            z_g = q["mu_g"] + torch.randn_like(q["mu_g"]) * torch.exp(0.5 * q["logvar_g"])
            z_l = q["mu_l"] + torch.randn_like(q["mu_l"]) * torch.exp(0.5 * q["logvar_l"])
        else:
            z_g, z_l = q["mu_g"], q["mu_l"]
        if detach_local:
            z_l = z_l.detach()
        return {**q, "z_g": z_g, "z_l": z_l, "sixd": self.decode(z_g, z_l)}


def kl_normal(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """The official ``kl_loss``: KL(N(mu, exp(logvar)) || N(0, I)) summed over the last dim, mean over the rest."""
    return (-0.5 * (1 + logvar - mu.square() - logvar.exp()).sum(-1)).mean()


def official_state_dict(model: HMVAE) -> dict[str, torch.Tensor]:
    """``model.state_dict()`` in the official layout: plus the duplicate ``dec.enc.*`` entries that the
    official ``Decoder`` holds because it keeps a reference to the encoder."""
    sd = dict(model.state_dict())
    sd.update({f"dec.enc.{k[len('enc.'):]}": v for k, v in model.state_dict().items() if k.startswith("enc.")})
    return sd


def parameter_summary(module: nn.Module) -> dict[str, int]:
    """Parameter counts of an HM-VAE (or trajectory) network, all as integers:

    - ``parameters_total``: every ``nn.Parameter`` (each shared tensor once), frozen ones included;
    - ``frozen_fixed``: the frozen conv masks and pooling/unpooling matrices among them (fixed
      functions of the skeleton, stored in the official checkpoints);
    - ``weights``: the learnable tensors (= total - frozen), masked conv weights counted in full: the
      "dense-equivalent" size (13.2 M for the paper len-64 model);
    - ``weights_effective``: the learnable numbers that can be non-zero (conv weights under the mask).
    """
    frozen_names = frozen_parameter_names(module)
    named = dict(module.named_parameters())  # shared tensors once
    total = sum(p.numel() for p in named.values())
    frozen = sum(p.numel() for n, p in named.items() if n in frozen_names)
    effective = 0
    for n, p in named.items():
        if n in frozen_names:
            continue
        if n.endswith(".weight") and n[: -len("weight")] + "mask" in named:
            effective += int(named[n[: -len("weight")] + "mask"].sum().item())
        else:
            effective += p.numel()
    return {"parameters_total": total, "frozen_fixed": frozen, "weights": total - frozen, "weights_effective": effective}


__all__ = [
    "HMVAEConfig",
    "PAPER_CONFIG",
    "LEN8_CONFIG",
    "Encoder",
    "Decoder",
    "HMVAE",
    "kl_normal",
    "official_state_dict",
    "parameter_summary",
]
