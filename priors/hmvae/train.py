"""Training the embedded HM-VAE and trajectory model on the synthetic training split (CPU, one thread).

Data: ``priors.training.motion_windows`` of the synthetic "train" split at 30 fps: 64-frame windows
every 16 frames for the VAE, 128-frame windows every 32 frames for the trajectory model; the "val"
split the same way for the validation losses. Rotations are SMPL-22 local rotations in the
project's y-up world (so the embedded models have ``world_up = "y"``), extended to the 24 HM-VAE
joints with identity rotations for the SMPL-H index joints 22/23.

Fixed skeleton (forward kinematics of both losses and of the trajectory model's input):
``priors.training.fixed_rest_skeleton()`` (22 joints, pelvis at the origin) extended by
:func:`rest_skeleton24`: left/right index1 placed 9 cm beyond the wrist along the elbow->wrist
direction (about the SMPL-H wrist -> index1 distance; the official ``skeleton_offsets.npy`` is not
shipped here). The 24-joint skeleton is stored in the trajectory checkpoint.

VAE loss (official ``TwoHierSAVAEModel.forward``, ``configs/len64_no_aug_hm_vae.yaml``)::

    1 * MSE(6D) + 1 * MSE(rotation matrices) + 10 * MSE(FK joint positions, metres)
    + 0.003 * KL(z_g) + 0.003 * KL(z_l)

with free bits on the deep code (``FREE_BITS_G`` nats per latent dimension, :func:`free_bits_kl`):
without them the embedded run's deep code collapsed (KL(z_g) 0.0015 nats) once the shallow code was on.

(MSE = mean over every element; KL = mean over batch x edges of the sum over latent dims.) For the
first 20 % of the steps (official: 50k of 250k iterations) the shallow code and its KL are
detached (deep-only phase). Training samples z with the reparameterisation; the validation loss
uses the posterior means.

Trajectory loss (official ``TrajectoryModel.forward``, ``configs/trajectory_model.yaml``)::

    1 * MSE(standardised root velocity) + 1 * MSE(integrated trajectory, metres)

with the input joint positions and the velocity standardised by the training windows' per-dim
mean/std (official: ``all_amass_data_mean_std.npy``), stored in the checkpoint.

Optimiser: Adam with weight decay 1e-4 (official); learning rate 1e-3 with a cosine decay to 1e-4
instead of the official 1e-4 with StepLR(100k, 0.3) over 250k iterations, because the embedded run
has ~60x fewer steps.

Embedded sizes (``EMBEDDED_VAE_CONFIG``, ``EMBEDDED_TRAJECTORY_CONFIG``), chosen so both train in
well under an hour on one CPU thread (the committed weights: 12,000 VAE steps in 24 min, then 4,800
trajectory steps; with 2,400 steps the validation loss was still falling: 0.070 against 0.052 now): the VAE keeps the paper's topology, strides, latent sizes
(z_g 7 x 24, z_l 14 x 12) and 64-frame window with kernel 7 and channels per edge
(6, 8, 16, 32, 64) instead of 15 and (6, 12, 24, 48, 96) (2,984,600 weights instead of 13.2 M);
the trajectory model kernel 15 and channels (3, 4, 8, 16, 32) instead of 31 and (3, 6, 12, 24, 48)
(730,851 weights instead of 3.2 M). Measured per-step cost on one thread (CPU time of the process,
on a shared 2-core machine): embedded VAE 0.19-0.23 s per step of 16 windows (3000 steps ~ 10-11
min), embedded trajectory model ~0.11 s per step of 8 x 128 frames (1200 steps ~ 2.2 min); for
comparison the paper-size VAE takes 0.42-0.53 s per step of 8 windows and the paper trajectory
model ~0.35 s per step of 8. See the JSON records for the wall times and losses of the real run.

Outputs: ``hmvae.pt`` + ``hmvae.json`` (VAE) and ``hmvae_trajectory.pt`` + ``hmvae_trajectory.json``
(trajectory model), two files so that ``hmvae`` needs only the first.
``python -m priors.hmvae.train --out priors/weights`` or ``python -m benchmark train hmvae``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import roma
import torch

from benchmark.body.lbs import forward_kinematics
from benchmark.core.frames import matrix_to_sixd_columns, sixd_columns_to_matrix
from benchmark.core.skeleton import JOINT_INDEX, NUM_JOINTS
from priors import training
from priors.hmvae.checkpoint import learnable_state_dict
from priors.hmvae.model import HMVAE, HMVAEConfig, kl_normal, parameter_summary
from priors.hmvae.skeleton import NUM_JOINTS24, PARENTS24
from priors.hmvae.trajectory import TrajectoryConfig, TrajectoryModel, integrate_velocity, root_velocity

log = logging.getLogger(__name__)

EMBEDDED_VAE_CONFIG = HMVAEConfig(kernel_size=7, channels=(6, 8, 16, 32, 64), world_up="y")
EMBEDDED_TRAJECTORY_CONFIG = TrajectoryConfig(kernel_size=15, channels=(3, 4, 8, 16, 32), world_up="y")
VAE_STEPS, VAE_BATCH, VAE_WINDOW, VAE_STRIDE = 12000, 16, 64, 16
TRAJ_STEPS, TRAJ_BATCH, TRAJ_WINDOW, TRAJ_STRIDE = 4800, 8, 128, 32
LR, FINAL_LR_RATIO, WEIGHT_DECAY = 1e-3, 0.1, 1e-4
DEEP_ONLY_FRACTION = 50_000 / 250_000
W_6D, W_ROT, W_POS, KL_G, KL_L = 1.0, 1.0, 10.0, 0.003, 0.003
W_VEL, W_TRAJ = 1.0, 1.0
# Free bits on the deep code (Kingma et al. 2016): the KL(z_g) term is sum over latent dims of
# max(lambda, batch-mean KL of that dim), mean over the 7 deep edges, so the first lambda nats per
# dimension are free. With the plain 0.003*KL(z_g) the deep code collapsed once the shallow code
# (a skip path into the last decoder block) was switched on: KL(z_g) 2.5 nats per edge at the end
# of the deep-only phase, 0.0015 at step 3000, everything carried by z_l.
FREE_BITS_G = 0.25
HAND_OFFSET_M = 0.09


# -- data ------------------------------------------------------------------------------------
def rest_skeleton24(rest22: torch.Tensor) -> torch.Tensor:
    """(22, 3) rest joints -> (24, 3) with left/right index1 ``HAND_OFFSET_M`` beyond each wrist along the forearm."""
    rest22 = torch.as_tensor(rest22, dtype=torch.float32)
    if rest22.shape == (NUM_JOINTS24, 3):
        return rest22.clone()
    if rest22.shape != (NUM_JOINTS, 3):
        raise ValueError(f"rest skeleton must be (22, 3) or (24, 3), got {tuple(rest22.shape)}")
    extra = []
    for side in ("left", "right"):
        w, e = rest22[JOINT_INDEX[f"{side}_wrist"]], rest22[JOINT_INDEX[f"{side}_elbow"]]
        d = w - e
        extra.append(w + HAND_OFFSET_M * d / d.norm().clamp_min(1e-6))
    return torch.cat([rest22, torch.stack(extra)], dim=0)


def windows_to_rotations(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, F, 69) training windows -> local rotations (N, F, 24, 3, 3) (hands identity), trans (N, F, 3)."""
    poses, trans = training.unpack_windows(x)
    rot = roma.rotvec_to_rotmat(torch.as_tensor(poses, dtype=torch.float32))
    N, F = rot.shape[:2]
    hands = torch.eye(3, dtype=rot.dtype).expand(N, F, NUM_JOINTS24 - NUM_JOINTS, 3, 3)
    return torch.cat([rot, hands], dim=2), trans


def _check_windows(x: torch.Tensor, frames: int, what: str) -> torch.Tensor:
    x = torch.as_tensor(x, dtype=torch.float32)
    if x.dim() != 3 or x.shape[1] != frames or x.shape[2] != NUM_JOINTS * 3 + 3:
        raise ValueError(f"{what}: windows must be (N, {frames}, 69) [axis-angle 22x3, trans 3] "
                         f"(priors.training.motion_windows), got {tuple(x.shape)}")
    return x.contiguous()


def _split_windows(dataset, split: str, frames: int, stride: int) -> tuple[torch.Tensor, dict]:
    motions = training.split_motions(dataset, split)
    w = training.motion_windows(motions, frames, stride, fps=30.0)
    return w, {"source": dataset.source(split), "motions": len(motions),
               "window_frames": frames, "stride": stride, "fps": 30.0, "windows": int(w.shape[0])}


def _default_data(dataset, frames: int, stride: int) -> tuple[torch.Tensor, torch.Tensor | None, dict]:
    train, info = _split_windows(dataset, "train", frames, stride)
    data = {"train": info}
    try:
        val, vinfo = _split_windows(dataset, "val", frames, stride)
        data["val"] = vinfo
    except Exception as exc:  # recorded; training goes on without a validation loss
        log.warning("no validation split (%s); training without a validation loss", exc)
        val, data["val"] = None, {"source": None, "error": f"{type(exc).__name__}: {exc}"}
    return train, val, data


# -- losses ----------------------------------------------------------------------------------
def free_bits_kl(mu: torch.Tensor, logvar: torch.Tensor, free_bits: float) -> torch.Tensor:
    """KL(N(mu, e^logvar) || N(0, I)) with ``free_bits`` nats per latent dimension free: the batch-mean KL
    of each (edge, dim), clamped below at ``free_bits``, summed over dims, mean over edges (the scale of
    :func:`kl_normal`; equal to it when every dim is above the threshold)."""
    kl = -0.5 * (1 + logvar - mu.square() - logvar.exp())  # (B, E, D)
    return kl.mean(0).clamp_min(free_bits).sum(-1).mean()


def hmvae_loss(model: HMVAE, batch: torch.Tensor, rest24: torch.Tensor, deep_only: bool = False,
               free_bits_g: float = FREE_BITS_G) -> dict:
    """The official HM-VAE loss (module docstring) for windows (N, T, 69), with ``free_bits_g`` nats per
    dimension of the deep code free (:func:`free_bits_kl`; 0 is the official loss). In eval mode the
    posterior means are decoded and the shallow code is never detached. ``kl_g`` / ``kl_l`` are the
    plain KLs; ``kl_g_term`` is the deep KL as penalised."""
    rot, _ = windows_to_rotations(batch)
    sixd = matrix_to_sixd_columns(rot)
    with torch.no_grad():
        _, pos = forward_kinematics(rot, rest24, parents=PARENTS24)
    out = model(sixd, sample=model.training, detach_local=deep_only and model.training)
    rec_sixd = out["sixd"]
    rec_rot = sixd_columns_to_matrix(rec_sixd)
    _, rec_pos = forward_kinematics(rec_rot, rest24, parents=PARENTS24)
    l6d = (rec_sixd - sixd).square().mean()
    lrot = (rec_rot - rot).square().mean()
    lpos = (rec_pos - pos).square().mean()
    kl_g = kl_normal(out["mu_g"], out["logvar_g"])
    kl_g_term = free_bits_kl(out["mu_g"], out["logvar_g"], free_bits_g) if free_bits_g > 0 else kl_g
    kl_l = kl_normal(out["mu_l"], out["logvar_l"])
    if deep_only and model.training:
        kl_l = kl_l.detach()
    loss = W_6D * l6d + W_ROT * lrot + W_POS * lpos + KL_G * kl_g_term + KL_L * kl_l
    return {"loss": loss, "mse_6d": l6d, "mse_rotmat": lrot, "mse_joints_m2": lpos, "kl_g": kl_g, "kl_l": kl_l,
            "kl_g_term": kl_g_term.detach()}


def trajectory_statistics(windows: torch.Tensor, rest24: torch.Tensor, chunk: int = 512) -> dict:
    """Per-dim mean/std of the FK joint positions (72) and root velocities (3) of training windows."""
    s1 = torch.zeros(NUM_JOINTS24 * 3, dtype=torch.float64)
    s2 = torch.zeros_like(s1)
    v1 = torch.zeros(3, dtype=torch.float64)
    v2 = torch.zeros_like(v1)
    n = 0
    for i in range(0, windows.shape[0], chunk):
        rot, trans = windows_to_rotations(windows[i : i + chunk])
        pos = forward_kinematics(rot, rest24, parents=PARENTS24)[1].flatten(2).flatten(0, 1).double()
        vel = root_velocity(trans)[:, 1:].flatten(0, 1).double()
        s1 += pos.sum(0)
        s2 += pos.square().sum(0)
        n += pos.shape[0]
        v1 += vel.sum(0)
        v2 += vel.square().sum(0)
    nv = n - windows.shape[0]
    pm, vm = s1 / n, v1 / max(nv, 1)
    ps = (s2 / n - pm.square()).clamp_min(0).sqrt()
    vs = (v2 / max(nv, 1) - vm.square()).clamp_min(0).sqrt()
    return {"pos_mean": pm.float(), "pos_std": ps.float(), "vel_mean": vm.float(), "vel_std": vs.float(), "rest_joints": rest24}


def trajectory_loss(model: TrajectoryModel, batch: torch.Tensor) -> dict:
    """The official trajectory loss (module docstring) for windows (N, T, 69)."""
    rot, trans = windows_to_rotations(batch)
    with torch.no_grad():
        joints = model.joint_positions(rot)
        v = root_velocity(trans)
        v_std = (v - model.vel_mean) / model.vel_std
    pred_std = model(joints)
    pred_traj = integrate_velocity(pred_std * model.vel_std + model.vel_mean)
    gt_traj = integrate_velocity(v)
    l_vel = (pred_std - v_std).square().mean()
    l_traj = (pred_traj - gt_traj).square().mean()
    return {"loss": W_VEL * l_vel + W_TRAJ * l_traj, "mse_velocity_std": l_vel, "mse_trajectory_m2": l_traj}


# -- training --------------------------------------------------------------------------------
def _rest(rest) -> tuple[torch.Tensor, str]:
    if rest is None:
        r, src = training.fixed_rest_skeleton()
    else:
        r, src = torch.as_tensor(rest, dtype=torch.float32), "given"
    return rest_skeleton24(r), f"{src}; + index1 joints {HAND_OFFSET_M} m beyond the wrists along the forearm"


def train_hmvae(out_dir=None, steps: int = VAE_STEPS, seed: int = 0, *, config: HMVAEConfig = EMBEDDED_VAE_CONFIG,
                windows: torch.Tensor | None = None, val_windows: torch.Tensor | None = None, rest=None,
                batch_size: int = VAE_BATCH, lr: float = LR, log_every: int = 200,
                deep_only_fraction: float = DEEP_ONLY_FRACTION, dataset=None) -> tuple[HMVAE, dict]:
    """Train an HM-VAE on 64-frame windows; writes hmvae.pt + hmvae.json into ``out_dir`` (None: nothing).

    windows / val_windows: (N, seq_len, 69) (``priors.training.motion_windows``); default: the
    train / val splits of ``dataset`` (the training data the caller hands over:
    :func:`priors.training.split_motions`). rest: (22, 3) or (24, 3) FK skeleton (default: the fixed one).
    """
    if windows is None:
        windows, val_windows, data_info = _default_data(dataset, config.seq_len, VAE_STRIDE)
    else:
        data_info = {"train": {"source": "windows given", "windows": int(windows.shape[0])}}
        if val_windows is not None:
            data_info["val"] = {"source": "windows given", "windows": int(val_windows.shape[0])}
    windows = _check_windows(windows, config.seq_len, "train_hmvae")
    val_windows = _check_windows(val_windows, config.seq_len, "train_hmvae (val)") if val_windows is not None else None
    rest24, rest_source = _rest(rest)
    training.seed_everything(seed)
    model = HMVAE(config)
    deep_steps = int(round(deep_only_fraction * steps))
    counter = {"step": 0}

    def loss_fn(m, batch):
        if m.training:
            counter["step"] += 1
        return hmvae_loss(m, batch, rest24, deep_only=counter["step"] <= deep_steps)

    result = training.train_loop(model, loss_fn, windows, steps=steps, batch_size=batch_size, seed=seed, lr=lr,
                                 weight_decay=WEIGHT_DECAY, final_lr_ratio=FINAL_LR_RATIO, log_every=log_every,
                                 val_data=val_windows, val_batch=256)
    model.eval()
    record = {
        "prior": "hmvae",
        "network": "HM-VAE len-64 window model (priors/hmvae/model.py HMVAE), official topology and key names",
        "config": config.to_dict(),
        "parameters": parameter_summary(model),
        "data": data_info,
        "rest_skeleton": rest_source,
        "loss": f"{W_6D}*MSE(6D) + {W_ROT}*MSE(rotmat) + {W_POS}*MSE(FK joints, m) + {KL_G}*KL_fb(z_g) + {KL_L}*KL(z_l)",
        "free_bits_g": {"nats_per_dim": FREE_BITS_G,
                        "kl_fb": "sum over the 24 dims of max(free_bits, batch-mean KL of the dim), mean over the 7 deep edges "
                                 "(kl_g_term in the history; kl_g is the plain KL)"},
        "deep_only_steps": deep_steps,
        **training.loop_record(result, steps=steps, seed=seed, lr=lr, weight_decay=WEIGHT_DECAY,
                               final_lr_ratio=FINAL_LR_RATIO, batch_size=batch_size),
    }
    if out_dir is not None:
        cfg = {"kind": "hmvae", "model": config.to_dict(), "rest_skeleton": rest24.tolist()}
        training.save_trained(out_dir, "hmvae.pt", learnable_state_dict(model), cfg, record)
    return model, record


def train_trajectory(out_dir=None, steps: int = TRAJ_STEPS, seed: int = 0, *,
                     config: TrajectoryConfig = EMBEDDED_TRAJECTORY_CONFIG, windows: torch.Tensor | None = None,
                     val_windows: torch.Tensor | None = None, rest=None, frames: int = TRAJ_WINDOW,
                     batch_size: int = TRAJ_BATCH, lr: float = LR, log_every: int = 100,
                     dataset=None) -> tuple[TrajectoryModel, dict]:
    """Train the trajectory model on ``frames``-frame windows (default: of the splits of ``dataset``, as
    :func:`train_hmvae`); writes hmvae_trajectory.pt/.json into ``out_dir``."""
    if windows is None:
        windows, val_windows, data_info = _default_data(dataset, frames, TRAJ_STRIDE)
    else:
        data_info = {"train": {"source": "windows given", "windows": int(windows.shape[0])}}
        if val_windows is not None:
            data_info["val"] = {"source": "windows given", "windows": int(val_windows.shape[0])}
    windows = _check_windows(windows, frames, "train_trajectory")
    val_windows = _check_windows(val_windows, frames, "train_trajectory (val)") if val_windows is not None else None
    rest24, rest_source = _rest(rest)
    training.seed_everything(seed)
    model = TrajectoryModel(config)
    st = trajectory_statistics(windows, rest24)
    model.set_statistics(st["pos_mean"], st["pos_std"], st["vel_mean"], st["vel_std"], st["rest_joints"])
    result = training.train_loop(model, trajectory_loss, windows, steps=steps, batch_size=batch_size, seed=seed, lr=lr,
                                 weight_decay=WEIGHT_DECAY, final_lr_ratio=FINAL_LR_RATIO, log_every=log_every,
                                 val_data=val_windows, val_batch=128)
    model.eval()
    record = {
        "prior": "hmvae-trajectory",
        "network": "HM-VAE trajectory model (priors/hmvae/trajectory.py TrajectoryModel), official key names",
        "config": config.to_dict(),
        "parameters": parameter_summary(model),
        "data": data_info,
        "window_frames": frames,
        "rest_skeleton": rest_source,
        "loss": f"{W_VEL}*MSE(standardised root velocity) + {W_TRAJ}*MSE(integrated trajectory, m)",
        **training.loop_record(result, steps=steps, seed=seed, lr=lr, weight_decay=WEIGHT_DECAY,
                               final_lr_ratio=FINAL_LR_RATIO, batch_size=batch_size),
    }
    if out_dir is not None:
        cfg = {"kind": "hmvae-trajectory", "model": config.to_dict(), "statistics": model.statistics()}
        training.save_trained(out_dir, "hmvae_trajectory.pt", learnable_state_dict(model), cfg, record)
    return model, record


def train_embedded(out_dir=None, steps: int | None = None, seed: int = 0, overwrite: bool = False,
                   dataset=None) -> dict:
    """Train both embedded models into ``out_dir`` (default priors/weights) on ``dataset`` (the training
    data the caller hands over: :func:`priors.training.split_motions`). ``steps`` sets the VAE's
    steps; the trajectory model's scale with it (default 12000 and 4800: the committed weights). Refuses to overwrite
    existing files unless ``overwrite``."""
    out = Path(out_dir) if out_dir is not None else training.WEIGHTS_DIR
    training.refuse_overwrite(out, ["hmvae.pt", "hmvae_trajectory.pt"], overwrite)
    vae_steps = VAE_STEPS if steps is None else int(steps)
    traj_steps = max(1, round(vae_steps * TRAJ_STEPS / VAE_STEPS))
    rest = training.fixed_rest_skeleton()[0]
    _, rec_vae = train_hmvae(out, steps=vae_steps, seed=seed, rest=rest, dataset=dataset)
    _, rec_traj = train_trajectory(out, steps=traj_steps, seed=seed, rest=rest, dataset=dataset)
    return {"hmvae": rec_vae, "hmvae_trajectory": rec_traj}


def main(argv: list[str] | None = None) -> None:
    """``python -m priors.hmvae.train --out priors/weights [--steps N] [--seed S] [--force]``."""
    import argparse

    from benchmark.core import argtypes as at
    from benchmark.synthetic.train_data import SyntheticTrainingData

    ap = argparse.ArgumentParser(description="Train the embedded HM-VAE and trajectory model on the synthetic split.")
    ap.add_argument("--out", default=str(training.WEIGHTS_DIR))
    ap.add_argument("--steps", type=at.positive_int, default=None, help=f"VAE steps (default {VAE_STEPS}; trajectory scaled)")
    ap.add_argument("--seed", type=at.seed, default=0)
    ap.add_argument("--force", action="store_true", help="overwrite existing weights")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    training.check_recipe_out(args.out, ["hmvae.pt", "hmvae_trajectory.pt"], args.force)
    rec = train_embedded(args.out, steps=args.steps, seed=args.seed, overwrite=args.force, dataset=SyntheticTrainingData())
    for k, r in rec.items():
        print(k, {x: r[x] for x in ("train_wall_s", "seconds_per_step", "final_train", "final_val", "checkpoint_bytes")})


__all__ = [
    "EMBEDDED_VAE_CONFIG",
    "EMBEDDED_TRAJECTORY_CONFIG",
    "rest_skeleton24",
    "windows_to_rotations",
    "hmvae_loss",
    "trajectory_loss",
    "trajectory_statistics",
    "train_hmvae",
    "train_trajectory",
    "train_embedded",
]


if __name__ == "__main__":
    main()
