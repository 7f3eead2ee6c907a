"""The frequency-guided motion prior (Xu et al. 2021): DCT features, Xu's joints, the networks at any size
(pure torch, no I/O).

See the package docstring (:mod:`priors.frequency_guided`) for the method and the sizes.
"""

from __future__ import annotations

import math
import warnings

import roma
import torch
import torch.nn.functional as F
from torch import nn

from benchmark.body.lbs import forward_kinematics
from benchmark.core.frames import heading as heading_angle, yaw_matrix
from benchmark.core.skeleton import NUM_JOINTS, SMPL_LIKE_REST_JOINTS
from priors.vposer.model import NUM_BODY_JOINTS, VPoserV1, sixd_interleaved_to_matrix


FRAMES = 128
FPS = 30.0
INPUT_CHANNELS = 158
NUM_XU_JOINTS = 17
NUM_FREQ = 20
HEAD_TOP_OFFSET = 0.116  # m along the head joint's local +y (Xu's nose-head target bone length)

# Xu's 17 joints from the SMPL 22 (index into 0..21; -1 = head-top end site), official order.
XU17_NAMES = ("hip", "right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle", "chest",
              "neck", "nose", "head", "left_shoulder", "left_elbow", "left_wrist", "right_shoulder", "right_elbow",
              "right_wrist")
XU17_FROM_SMPL22 = (0, 2, 5, 8, 1, 4, 7, 9, 12, 15, -1, 16, 18, 20, 17, 19, 21)

PAPER_CONFIG = {
    "num_neurons": 512, "latent": 256, "latent_t": 8, "frames": FRAMES, "dense_freq": True,
    "channels": [64, 64, 128], "dct_hidden": 512, "pose_code": 32, "unused_layers": True,
    "vposer": {"hidden": 512, "latent": 32},
}
EMBEDDED_CONFIG = {
    "num_neurons": 256, "latent": 128, "latent_t": 8, "frames": FRAMES, "dense_freq": True,
    "channels": [32, 32, 64], "dct_hidden": 256, "pose_code": 32, "unused_layers": False,
    "vposer": {"hidden": 256, "latent": 32},
}


# -- pure functions: DCT bases, headings, joints, encoder inputs --------------------------------
def dct_matrix(n: int, dtype=torch.float32) -> torch.Tensor:
    """(n, n) orthonormal DCT-II matrix C (row k = frequency k), C @ x = scipy ``dct(x, norm='ortho', axis=0)``.

    Same as the official ``dct(np.eye(n), norm='ortho', axis=0)``.
    """
    k = torch.arange(n, dtype=torch.float64)[:, None]
    i = torch.arange(n, dtype=torch.float64)[None, :]
    C = torch.cos(math.pi * (2 * i + 1) * k / (2 * n)) * math.sqrt(2.0 / n)
    C[0] = C[0] / math.sqrt(2.0)
    return C.to(dtype)


def xu17_joints(global_rot: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
    """(..., 22, 3, 3) global rotations, (..., 22, 3) joints -> (..., 17, 3) Xu's joint set (module docstring)."""
    head = 15
    top = joints[..., head, :] + HEAD_TOP_OFFSET * global_rot[..., head, :, 1]
    idx = [j if j >= 0 else 0 for j in XU17_FROM_SMPL22]
    out = joints[..., idx, :]
    site = XU17_FROM_SMPL22.index(-1)
    return torch.cat([out[..., :site, :], top[..., None, :], out[..., site + 1 :, :]], dim=-2)


def pseudo_vertices(rotations: torch.Tensor, rest_joints: torch.Tensor, marker: float = 0.1) -> torch.Tensor:
    """(..., 22, 3, 3) local rotations -> (..., 66, 3): FK joints + markers ``marker`` m along each joint's
    local x and z axes (the training loss's stand-in for mesh vertices)."""
    g, j = forward_kinematics(rotations, rest_joints)
    mx = j + marker * g[..., :, 0]
    mz = j + marker * g[..., :, 2]
    return torch.cat([j, mx, mz], dim=-2)


def frequency_features(p3ds: torch.Tensor, basis: torch.Tensor, basis_block: torch.Tensor, dense: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Xu's frequency guidance from joint trajectories p3ds (B, F, 51).

    Returns (frequency (B, n_freq*51): the first n_freq DCT coefficients of every channel,
    coefficient-major; frequency_block: dense (B, F*5*51): per frame, the 5-point DCT of frames
    t-2..t+2 (edges repeated), ordered frame, coefficient, channel; non-dense (B, F*51): the
    8-point DCT of consecutive non-overlapping 8-frame blocks).
    """
    B, Fr, C = p3ds.shape
    freq = torch.einsum("kf,bfc->bkc", basis, p3ds).reshape(B, -1)
    b = basis_block.shape[0]
    if dense:
        h = b // 2
        pad = torch.cat([p3ds[:, :1].expand(B, h, C), p3ds, p3ds[:, -1:].expand(B, h, C)], dim=1)
        blocks = pad.unfold(1, b, 1).permute(0, 1, 3, 2)  # (B, F, b, C)
    else:
        blocks = p3ds.reshape(B, Fr // b, b, C)
    fb = torch.einsum("kb,znbc->znkc", basis_block, blocks)
    return freq, fb.reshape(B, -1)


def window_features(rotations: torch.Tensor, trans: torch.Tensor, rest_joints: torch.Tensor) -> dict:
    """The yaw-independent part of Xu's encoder input (official ``data_prepare``, with our joints).

    rotations (B, F, 22, 3, 3) local rotations (root = world orientation, y up), trans (B, F, 3) m.
    Heading normalisation at the first frame: H = Ry(-heading(R_0)). Returns
    {"root_norm" (B, F, 3, 3) = H R_t (the decoder's target), "trans_norm" (B, F, 3) = H (x_t - x_0),
    "p3ds_norm" (B, F, 51) the 17 joints relative to the hip for the normalised root,
    "body_aa" (B, F, 63) axis-angle of joints 1..21 (angle <= pi)}.
    """
    B, Fr = rotations.shape[:2]
    root = rotations[:, :, 0]
    H = yaw_matrix(-heading_angle(root[:, 0]))[:, None]  # (B, 1, 3, 3)
    root_norm = H @ root
    trans_norm = (H @ (trans - trans[:, :1])[..., None])[..., 0]
    body = rotations[:, :, 1:]
    g, j = forward_kinematics(torch.cat([root_norm[:, :, None], body], dim=2), rest_joints)
    p3 = xu17_joints(g, j)
    p3ds = (p3 - p3[..., :1, :]).reshape(B, Fr, NUM_XU_JOINTS * 3)
    body_aa = roma.rotmat_to_rotvec(body).reshape(B, Fr, NUM_BODY_JOINTS * 3)
    return {"root_norm": root_norm, "trans_norm": trans_norm, "p3ds_norm": p3ds, "body_aa": body_aa}


def encoder_inputs(feats: dict, codes: torch.Tensor, basis: torch.Tensor, basis_block: torch.Tensor, dense: bool,
                   yaw: torch.Tensor | None = None) -> dict:
    """Xu's encoder inputs from :func:`window_features` and the VPoser v1 codes (B, F, 32).

    yaw (B,) rad: the augmentation yaw Y = Ry(yaw) applied to root, translation and joints (None = 0).
    Returns {"pin" (B, F, 158), "frequency" (B, 1020), "frequency_block" (B, F*5*51)}; channel order
    [body aa 63, codes 32, root aa 3, translation 3, velocity 3, angular velocity aa 3, joints 51].
    """
    root, tr, p3ds = feats["root_norm"], feats["trans_norm"], feats["p3ds_norm"]
    B, Fr = root.shape[:2]
    if yaw is not None:
        Y = yaw_matrix(yaw.to(root))[:, None]  # (B, 1, 3, 3)
        root = Y @ root
        tr = (Y @ tr[..., None])[..., 0]
        p3ds = (Y[:, :, None] @ p3ds.reshape(B, Fr, NUM_XU_JOINTS, 3, 1)).reshape(B, Fr, NUM_XU_JOINTS * 3)
    vel = torch.cat([torch.zeros_like(tr[:, :1]), tr[:, 1:] - tr[:, :-1]], dim=1)
    rvel = torch.cat([root[:, :1], root[:, 1:] @ root[:, :-1].transpose(-1, -2)], dim=1)
    pin = torch.cat([feats["body_aa"], codes, roma.rotmat_to_rotvec(root), tr, vel, roma.rotmat_to_rotvec(rvel), p3ds], dim=-1)
    freq, fblock = frequency_features(p3ds, basis, basis_block, dense)
    return {"pin": pin, "frequency": freq, "frequency_block": fblock}


# -- the networks ------------------------------------------------------------------------------
def _weight_norm(module: nn.Module) -> nn.Module:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # deprecated alias; keeps the official weight_g/weight_v keys
        return torch.nn.utils.weight_norm(module)


class MotionPrior(nn.Module):
    """Xu et al.'s ``MotionPrior`` (module docstring), sizes from its config."""

    def __init__(self, num_neurons: int = 512, latent: int = 256, latent_t: int = 8, frames: int = FRAMES,
                 dense_freq: bool = True, channels=(64, 64, 128), dct_hidden: int = 512, pose_code: int = 32,
                 unused_layers: bool = True):
        super().__init__()
        c0, c1, c2 = (int(c) for c in channels)
        self.cfg = {"num_neurons": int(num_neurons), "latent": int(latent), "latent_t": int(latent_t),
                    "frames": int(frames), "dense_freq": bool(dense_freq), "channels": [c0, c1, c2],
                    "dct_hidden": int(dct_hidden), "pose_code": int(pose_code), "unused_layers": bool(unused_layers)}
        if frames % 8:
            raise ValueError(f"MotionPrior: frames must be a multiple of 8 (three stride-2 stages), got {frames}")
        self.frames, self.latent, self.pose_code, self.dense_freq = int(frames), int(latent), int(pose_code), bool(dense_freq)
        self.block_size = 5 if dense_freq else 8
        J3 = NUM_XU_JOINTS * 3
        N = int(num_neurons)
        conv = lambda i, o, s: _weight_norm(nn.Conv1d(i, o, kernel_size=3, stride=s, padding=1))  # noqa: E731
        if dense_freq:
            self.dct_att = nn.Linear(frames * self.block_size * J3, frames)
        else:
            self.dct_att = nn.Linear(frames * J3, frames // self.block_size)
        self.bodyprior_enc_fc0_1 = conv(INPUT_CHANNELS, c0, 2)
        self.bodyprior_enc_fc0_2 = conv(c0, c0, 1)
        self.bodyprior_enc_fc0_3 = conv(c0, c0, 1)
        self.pool1_1 = conv(c0, c1, 2)
        self.bodyprior_enc_fc1_1 = conv(c1, c1, 1)
        self.bodyprior_enc_fc1_2 = conv(c1, c1, 1)
        self.pool2_1 = conv(c1, c2, 2)
        self.bodyprior_enc_fc2_1 = conv(c2, c2, 1)
        self.bodyprior_enc_fc2_2 = conv(c2, c2, 1)
        L0 = frames // 2
        conv_flat = c0 * L0 + c1 * L0 // 2 + c2 * L0 // 4
        self.bodyprior_enc_dct = _weight_norm(nn.Linear(NUM_FREQ * J3, dct_hidden))
        self.bodyprior_enc_mu_local = nn.Linear(conv_flat + dct_hidden, latent)
        self.bodyprior_enc_logvar_local = nn.Linear(conv_flat + dct_hidden, latent)
        self.dropout = nn.Dropout(p=0.1)
        self.bodyprior_dec_fc0 = nn.Linear(latent, N)
        self.bodyprior_dec_fc1 = nn.Linear(N, N)
        self.bodyprior_dec_fc2 = nn.Linear(N, N)
        self.bodyprior_dec_pose = nn.Linear(N + latent, frames * pose_code)
        self.bodyprior_dec_orient = nn.Linear(N + latent, frames * 6)
        if unused_layers:  # in the official state dict, never used by its forward pass
            for name, c in (("0_1", c0), ("0_2", c0), ("0_3", c0), ("1_1", c1), ("1_2", c1), ("2_1", c2), ("2_2", c2)):
                setattr(self, f"bodyprior_enc_bn{name}", nn.BatchNorm1d(c))
            self.bodyprior_enc_mu_global = nn.Linear(conv_flat, latent_t)
            self.bodyprior_enc_logvar_global = nn.Linear(conv_flat, latent_t)
            self.bodyprior_dec_trans = nn.Linear(N + latent_t, frames * 3)

    def encode(self, pin: torch.Tensor, frequency: torch.Tensor, frequency_block: torch.Tensor) -> torch.distributions.Normal:
        """pin (B, F, 158), frequency (B, 1020), frequency_block (B, F*5*51) -> q(z) with loc/scale (B, L)."""
        B = pin.shape[0]
        x = pin.transpose(1, 2)  # (B, 158, F)
        att = self.dct_att(frequency_block)
        if not self.dense_freq:
            att = att.repeat_interleave(self.block_size, dim=1)
        x = x * att[:, None, :]
        x = F.silu(self.bodyprior_enc_fc0_1(x))
        x = x + F.silu(self.bodyprior_enc_fc0_3(F.silu(self.bodyprior_enc_fc0_2(x))))
        local = x.reshape(B, -1)
        x = F.silu(self.pool1_1(x))
        x = x + F.silu(self.bodyprior_enc_fc1_2(F.silu(self.bodyprior_enc_fc1_1(x))))
        mid = x.reshape(B, -1)
        x = F.silu(self.pool2_1(x))
        x = x + F.silu(self.bodyprior_enc_fc2_2(F.silu(self.bodyprior_enc_fc2_1(x))))
        h = torch.cat([x.reshape(B, -1), local, mid, F.silu(self.bodyprior_enc_dct(frequency))], dim=-1)
        h = self.dropout(h)
        return torch.distributions.Normal(self.bodyprior_enc_mu_local(h), F.softplus(self.bodyprior_enc_logvar_local(h)))

    def decode(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """z (B, L) -> (codes (B, F, 32) VPoser v1 codes, root (B, F, 3, 3)); traceable with a dynamic B."""
        x = F.silu(self.bodyprior_dec_fc0(z))
        x = x + F.silu(self.bodyprior_dec_fc1(x))
        x = x + F.silu(self.bodyprior_dec_fc2(x))
        x = self.dropout(x)
        h = torch.cat([x, z], dim=-1)
        codes = self.bodyprior_dec_pose(h).reshape(-1, self.frames, self.pose_code)
        root = sixd_interleaved_to_matrix(self.bodyprior_dec_orient(h).reshape(-1, 6)).reshape(-1, self.frames, 3, 3)
        return codes, root

    def decoder_parameter_count(self) -> int:
        """Parameters of the decode path (``bodyprior_dec_*`` except the unused ``dec_trans``)."""
        return sum(p.numel() for n, p in self.named_parameters()
                   if n.startswith("bodyprior_dec_") and not n.startswith("bodyprior_dec_trans"))


class FrequencyGuidedDecoder(nn.Module):
    """z (B, L) -> rotations (B, F, 22, 3, 3): root from the 6D head, joints 1..21 from VPoser v1."""

    def __init__(self, motion_prior: MotionPrior, vposer: VPoserV1):
        super().__init__()
        self.motion_prior = motion_prior
        self.vposer = vposer

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        codes, root = self.motion_prior.decode(z)
        Fr, P = self.motion_prior.frames, self.motion_prior.pose_code
        body = self.vposer.decode(codes.reshape(-1, P)).reshape(-1, Fr, NUM_BODY_JOINTS, 3, 3)
        return torch.cat([root[:, :, None], body], dim=2)


class ExportModule(nn.Module):
    def __init__(self, decoder: FrequencyGuidedDecoder):
        super().__init__()
        self.decoder = decoder

    def forward(self, z: torch.Tensor):
        return (self.decoder(z),)


class FrequencyGuidedNetwork(nn.Module):
    """Everything the prior holds: the motion prior, VPoser v1, the rest skeleton and the DCT bases."""

    def __init__(self, config: dict, rest_joints: torch.Tensor | None = None):
        super().__init__()
        cfg = dict(config)
        self.config = {**cfg, "vposer": dict(cfg["vposer"])}
        if int(cfg["vposer"]["latent"]) != int(cfg.get("pose_code", 32)):
            raise ValueError(f"config: pose_code {cfg.get('pose_code')} must equal the VPoser v1 latent {cfg['vposer']['latent']}")
        self.motion_prior = MotionPrior(**{k: v for k, v in cfg.items() if k != "vposer"})
        self.vposer = VPoserV1(**cfg["vposer"])
        if rest_joints is None:
            rest_joints = torch.tensor(SMPL_LIKE_REST_JOINTS, dtype=torch.float32)
        self.register_buffer("rest_joints", torch.as_tensor(rest_joints, dtype=torch.float32).reshape(NUM_JOINTS, 3).clone())
        Fr = self.motion_prior.frames
        self.register_buffer("basis", dct_matrix(Fr)[:NUM_FREQ], persistent=False)
        self.register_buffer("basis_block", dct_matrix(self.motion_prior.block_size), persistent=False)
        # the decode path over the same two modules, not registered (its weights are saved once)
        object.__setattr__(self, "decoder", FrequencyGuidedDecoder(self.motion_prior, self.vposer))

    def features(self, rotations: torch.Tensor, trans: torch.Tensor) -> dict:
        """:func:`window_features` on this network's rest skeleton."""
        return window_features(rotations, trans, self.rest_joints)

    def inputs(self, feats: dict, codes: torch.Tensor, yaw: torch.Tensor | None = None) -> dict:
        """:func:`encoder_inputs` with this network's DCT bases."""
        return encoder_inputs(feats, codes, self.basis, self.basis_block, self.motion_prior.dense_freq, yaw)

    def vposer_codes(self, body_rotations: torch.Tensor) -> torch.Tensor:
        """(..., 21, 3, 3) -> (..., 32) VPoser v1 encoder means (the network must be in eval mode)."""
        lead = body_rotations.shape[:-3]
        aa = roma.rotmat_to_rotvec(body_rotations.reshape(-1, NUM_BODY_JOINTS, 3, 3))
        return self.vposer.encode(aa).mean.reshape(*lead, self.vposer.latent)

    def parameter_counts(self) -> dict:
        mp = sum(p.numel() for p in self.motion_prior.parameters())
        vp = sum(p.numel() for p in self.vposer.parameters())
        vp_dec = sum(p.numel() for n, p in self.vposer.named_parameters() if n.startswith("bodyprior_dec_"))
        dec = self.motion_prior.decoder_parameter_count()
        return {"total": mp + vp, "motion_prior": mp, "vposer_v1": vp, "motion_prior_decoder": dec,
                "decode_path": dec + vp_dec}
