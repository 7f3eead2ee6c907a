"""Frequency-guided: the embedded training recipe (VPoser v1.0 stage, then the motion prior stage).

``python -m priors.frequency_guided.train --out priors/weights`` (or
``python -m benchmark train frequency-guided``) retrains the embedded weights.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import roma
import torch
from torch import nn

from benchmark.core.skeleton import NUM_JOINTS
from priors import training
from priors.vposer.model import NUM_BODY_JOINTS, VPoserV1
from priors.frequency_guided.model import EMBEDDED_CONFIG, FPS, FrequencyGuidedNetwork, pseudo_vertices
from priors.frequency_guided.checkpoint import DEFAULT_WEIGHTS

log = logging.getLogger(__name__)


# -- training the embedded weights -------------------------------------------------------------
VPOSER_KL = 1e-4  # official v1 kl_coef (vposer_smpl_defaults.ini)
MOTION_KL = 1e-2  # official kl_coef (motion_prior_defaults.ini)
VPOSE_COEF = 1e-3  # official vpose_coef
MM = 1000.0
DEFAULT_STEPS = 8000
DEFAULT_VPOSER_STEPS = 3000


def vposer_v1_loss(model: VPoserV1, pose_body: torch.Tensor, rest: torch.Tensor) -> dict:
    """(1 - kl) * mean|pv_rec - pv| (mm) + kl * KL for axis-angle poses (N, 21, 3), identity root."""
    target = roma.rotvec_to_rotmat(pose_body)
    out = model(pose_body)
    q = out["q_z"]
    kl = torch.distributions.kl_divergence(q, torch.distributions.Normal(torch.zeros_like(q.loc), torch.ones_like(q.scale))).sum(-1).mean()
    eye = torch.eye(3, dtype=target.dtype).expand(target.shape[0], 1, 3, 3)
    pv_t = pseudo_vertices(torch.cat([eye, target], 1), rest)
    pv_r = pseudo_vertices(torch.cat([eye, out["rotations"]], 1), rest)
    rec = (pv_r - pv_t).abs().mean() * MM
    loss = (1 - VPOSER_KL) * rec + VPOSER_KL * kl
    return {"loss": loss, "rec_mm": rec, "kl": kl}


PREPARED_CHANNELS = {"body_aa": 63, "root_aa": 3, "trans_norm": 3, "codes": 32, "p3ds_norm": 51}  # 152 per frame


@torch.no_grad()
def prepare_windows(net: FrequencyGuidedNetwork, windows: torch.Tensor, chunk: int = 256) -> torch.Tensor:
    """(N, F, 69) windows (``priors.training.motion_windows``) -> (N, F, 152) the yaw-independent
    training inputs [body aa 63, heading-normalised root aa 3, normalised translation 3, frozen
    VPoser v1 codes 32, normalised joints 51] (:data:`PREPARED_CHANNELS`), computed once."""
    from priors.training import unpack_windows

    net.vposer.eval()
    out = []
    for i in range(0, windows.shape[0], chunk):
        poses, trans = unpack_windows(windows[i : i + chunk])
        R = roma.rotvec_to_rotmat(poses)
        f = net.features(R, trans)
        n, Fr = R.shape[:2]
        codes = net.vposer.encode(f["body_aa"].reshape(-1, NUM_BODY_JOINTS, 3)).mean.reshape(n, Fr, -1)
        out.append(torch.cat([f["body_aa"], roma.rotmat_to_rotvec(f["root_norm"]), f["trans_norm"], codes, f["p3ds_norm"]], dim=-1))
    return torch.cat(out)


def motion_prior_loss(net: FrequencyGuidedNetwork, batch: torch.Tensor, loss_frames: int | None = None) -> dict:
    """Loss of the motion prior on prepared windows (N, F, 152) (:func:`prepare_windows`).

    Training mode: random yaw augmentation of the encoder input, z sampled, and the reconstruction
    term on ``loss_frames`` random frames of the windows (None = all; an unbiased estimate of the
    official mean over all frames, at a fraction of the FK / VPoser-decoding cost). Eval mode: yaw 0,
    z = posterior mean, all frames.
    """
    N, Fr = batch.shape[:2]
    parts = torch.split(batch, list(PREPARED_CHANNELS.values()), dim=-1)
    body_aa, root_aa, trans_norm, codes, p3ds = parts
    feats = {"root_norm": roma.rotvec_to_rotmat(root_aa), "trans_norm": trans_norm, "p3ds_norm": p3ds, "body_aa": body_aa}
    training = net.motion_prior.training
    yaw = (torch.rand(N) * 2 - 1) * math.pi if training else None
    inp = net.inputs(feats, codes, yaw=yaw)
    q = net.motion_prior.encode(inp["pin"], inp["frequency"], inp["frequency_block"])
    z = q.rsample() if training else q.loc
    codes_rec, root_rec = net.motion_prior.decode(z)
    if training and loss_frames is not None and loss_frames < Fr:
        idx = torch.randperm(Fr)[:loss_frames].sort().values
    else:
        idx = torch.arange(Fr)
    K = idx.numel()
    c_sel = codes_rec[:, idx]
    body_rec = net.vposer.decode(c_sel.reshape(-1, c_sel.shape[-1])).reshape(N, K, NUM_BODY_JOINTS, 3, 3)
    pv_r = pseudo_vertices(torch.cat([root_rec[:, idx, None], body_rec], 2), net.rest_joints)
    with torch.no_grad():
        body_t = roma.rotvec_to_rotmat(body_aa[:, idx].reshape(N, K, NUM_BODY_JOINTS, 3))
        pv_t = pseudo_vertices(torch.cat([feats["root_norm"][:, idx, None], body_t], 2), net.rest_joints)
    rec = (pv_r - pv_t).abs().mean() * MM
    prior = torch.distributions.Normal(torch.zeros_like(q.loc), torch.ones_like(q.scale))
    kl = torch.distributions.kl_divergence(q, prior).sum(-1).mean()
    vpose = codes_rec.square().mean()
    loss = (1 - MOTION_KL) * rec + MOTION_KL * kl + VPOSE_COEF * vpose
    return {"loss": loss, "rec_mm": rec, "kl": kl, "vpose_sq": vpose}


class _MotionStage(nn.Module):
    """Training wrapper: only the motion prior trains; VPoser v1 stays frozen in eval mode."""

    def __init__(self, net: FrequencyGuidedNetwork):
        super().__init__()
        self.net = net
        for p in net.vposer.parameters():
            p.requires_grad_(False)

    def train(self, mode: bool = True):
        super().train(mode)
        self.net.vposer.eval()
        return self


def train_frequency_guided(
    out_dir: str | Path | None = None,
    steps: int = DEFAULT_STEPS,
    seed: int = 0,
    *,
    vposer_steps: int = DEFAULT_VPOSER_STEPS,
    config: dict | None = None,
    windows: torch.Tensor | None = None,
    val_windows: torch.Tensor | None = None,
    batch_size: int = 32,
    vposer_batch_size: int = 256,
    lr: float = 5e-4,
    vposer_lr: float = 1e-3,
    stride: int = 32,
    loss_frames: int | None = 32,
    log_every: int = 200,
    rest_joints: torch.Tensor | None = None,
    dataset=None,
) -> tuple[FrequencyGuidedNetwork, dict]:
    """Train the embedded prior (VPoser v1, then the motion prior) and write
    ``frequency_guided.pt`` + ``frequency_guided.json`` into ``out_dir`` (None: write nothing).

    windows / val_windows: explicit (N, 128, 69) windows (``priors.training.motion_windows`` layout);
    by default 128-frame windows (stride ``stride``) of the train / val splits of ``dataset`` (the
    training data the caller hands over: :func:`priors.training.split_motions`) at 30 fps.
    The VPoser v1 stage trains on every 2nd frame of the split's motions (at most 200k poses), or on
    the frames of the explicit windows. rest_joints: the fixed (22, 3) skeleton of the losses and joint
    features (default ``priors.training.fixed_rest_skeleton()``); it is saved with the weights.
    """
    cfg = {**EMBEDDED_CONFIG, **(config or {})}
    Fr = int(cfg["frames"])
    data_info: dict = {}
    if windows is None:
        motions = training.split_motions(dataset, "train")
        windows = training.motion_windows(motions, Fr, stride, fps=FPS)
        vp_poses = training.pose_frames(motions, every=2, max_frames=200_000, seed=seed)
        data_info["train"] = {"source": dataset.source("train"), "motions": len(motions),
                              "windows": int(windows.shape[0]), "stride": stride, "fps": FPS,
                              "vposer_poses": int(vp_poses.shape[0]), "vposer_frame_every": 2}
        if val_windows is None:
            try:
                val_windows = training.motion_windows(training.split_motions(dataset, "val"), Fr, stride, fps=FPS)
                data_info["val"] = {"source": dataset.source("val"), "windows": int(val_windows.shape[0])}
            except Exception as exc:
                log.warning("no validation split (%s); training without a validation loss", exc)
                data_info["val"] = {"source": None, "error": f"{type(exc).__name__}: {exc}"}
    else:
        windows = torch.as_tensor(windows, dtype=torch.float32)
        vp_poses = training.unpack_windows(windows)[0].reshape(-1, NUM_JOINTS, 3)
        data_info["train"] = {"source": "windows given", "windows": int(windows.shape[0])}
        if val_windows is not None:
            data_info["val"] = {"source": "windows given", "windows": int(val_windows.shape[0])}
    if windows.dim() != 3 or windows.shape[1:] != (Fr, NUM_JOINTS * 3 + 3):
        raise ValueError(f"windows must be (N, {Fr}, {NUM_JOINTS * 3 + 3}) (priors.training.motion_windows), got {tuple(windows.shape)}")
    if rest_joints is None:
        rest, rest_source = training.fixed_rest_skeleton()
    else:
        rest, rest_source = torch.as_tensor(rest_joints, dtype=torch.float32), "rest_joints given"

    training.seed_everything(seed)
    net = FrequencyGuidedNetwork(cfg, rest_joints=rest)

    # stage 1: VPoser v1 on single poses
    vp_body = roma.rotmat_to_rotvec(roma.rotvec_to_rotmat(vp_poses[:, 1:].float()))  # canonical (angle <= pi), as at inference
    vp_res = training.train_loop(
        net.vposer, lambda m, b: vposer_v1_loss(m, b, net.rest_joints), vp_body, steps=vposer_steps,
        batch_size=vposer_batch_size, seed=seed, lr=vposer_lr, weight_decay=5e-4, final_lr_ratio=0.1, log_every=log_every,
        val_data=None if val_windows is None else training.unpack_windows(val_windows)[0][:, :, 1:].reshape(-1, NUM_BODY_JOINTS, 3)[::2].contiguous(),
    )
    net.vposer.eval()

    # stage 2: the motion prior on windows, VPoser v1 frozen (its codes and the joints precomputed)
    data = prepare_windows(net, windows)
    val_data = None if val_windows is None else prepare_windows(net, torch.as_tensor(val_windows, dtype=torch.float32))
    del windows
    stage = _MotionStage(net)
    mp_res = training.train_loop(
        stage, lambda m, b: motion_prior_loss(m.net, b, loss_frames), data, steps=steps, batch_size=batch_size, seed=seed + 1,
        lr=lr, weight_decay=1e-4, final_lr_ratio=0.1, log_every=log_every, val_data=val_data, val_batch=256,
    )
    net.eval()
    for p in net.vposer.parameters():
        p.requires_grad_(True)

    counts = net.parameter_counts()
    record = {
        "prior": "frequency-guided",
        "network": "Xu et al. 2021 MotionPrior + VPoser v1.0 (priors/frequency_guided/model.py, priors/vposer/model.py)",
        "config": net.config,
        "parameters": counts,
        "data": data_info,
        "rest_skeleton": rest_source,
        "loss": {
            "vposer_v1": f"(1-{VPOSER_KL})*mean|pseudo-vertices| (mm) + {VPOSER_KL}*KL(sum over dims)",
            "motion_prior": f"(1-{MOTION_KL})*mean|pseudo-vertices| (mm; heading-normalised root) + {MOTION_KL}*KL(sum over dims) "
                            f"+ {VPOSE_COEF}*mean(codes^2); random yaw on the encoder input",
            "pseudo_vertices": "22 FK joints + 2 markers per joint 0.1 m along local x and z (fixed rest skeleton)",
        },
        "optimiser": {
            "vposer_v1": {"name": "Adam", "lr": vposer_lr, "weight_decay": 5e-4, "schedule": "cosine to 0.1*lr",
                          "batch_size": vposer_batch_size, "steps": vposer_steps},
            "motion_prior": {"name": "Adam", "lr": lr, "weight_decay": 1e-4, "schedule": "cosine to 0.1*lr",
                             "batch_size": batch_size, "steps": steps},
        },
        "steps": steps,
        "vposer_steps": vposer_steps,
        "seed": seed,
        "torch_threads_training": 1,
        "train_wall_s": round(vp_res.wall_s + mp_res.wall_s, 2),
        "vposer_train_wall_s": round(vp_res.wall_s, 2),
        "motion_prior_train_wall_s": round(mp_res.wall_s, 2),
        "final_train": mp_res.final_train,
        "final_val": mp_res.final_val,
        "vposer_final_train": vp_res.final_train,
        "vposer_final_val": vp_res.final_val,
        "history": mp_res.history,
        "vposer_history": vp_res.history,
        **training.environment_record(),
    }
    if out_dir is not None:
        # Stored as float16 (halves the file: the paper's dense DCT gate alone is 4.2 M weights);
        # loading casts back to float32. Every number the harness reports uses these stored weights;
        # the losses above were measured before the cast.
        half = {k: v.half() if v.is_floating_point() else v for k, v in net.state_dict().items()}
        record["stored_dtype"] = "float16 (cast to float32 on load; losses above measured in float32 before the cast)"
        training.save_trained(out_dir, DEFAULT_WEIGHTS.name, half, net.config, record)
    return net, record


def main(argv: list[str] | None = None) -> None:
    """``python -m priors.frequency_guided.train --out priors/weights``: train the embedded weights."""
    from benchmark.core import argtypes as at
    from benchmark.synthetic.train_data import SyntheticTrainingData

    ap = training.recipe_parser("Train the embedded frequency-guided prior on the synthetic training split.",
                                DEFAULT_WEIGHTS, DEFAULT_STEPS)
    ap.add_argument("--vposer-steps", type=at.positive_int, default=DEFAULT_VPOSER_STEPS, help="VPoser v1 steps (default: %(default)s)")
    args = training.parse_recipe_args(ap, DEFAULT_WEIGHTS, argv)
    _, rec = train_frequency_guided(args.out, steps=args.steps, seed=args.seed, vposer_steps=args.vposer_steps,
                                    dataset=SyntheticTrainingData())
    print({k: rec[k] for k in ("train_wall_s", "final_train", "final_val", "checkpoint_bytes")})


if __name__ == "__main__":
    main()
