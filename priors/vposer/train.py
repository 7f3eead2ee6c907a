"""VPoser V02_05: the embedded training recipe (loss and loop).

``python -m priors.vposer.train --out priors/weights`` retrains the embedded weights.
"""

from __future__ import annotations

import logging
from pathlib import Path

import roma
import torch

from benchmark.body.lbs import forward_kinematics
from benchmark.core.skeleton import NUM_JOINTS
from priors import training
from priors.vposer.model import EMBEDDED_CONFIG, NUM_BODY_JOINTS, VPoser
from priors.vposer.checkpoint import DEFAULT_WEIGHTS

log = logging.getLogger(__name__)


# -- training the embedded weights -----------------------------------------------------------
KL_WEIGHT, GEODESIC_WEIGHT, JOINT_WEIGHT = 0.005, 2.0, 6.0


def vposer_loss(model: VPoser, pose_body: torch.Tensor, rest_joints: torch.Tensor) -> dict[str, torch.Tensor]:
    """Training loss of the embedded VPoser (module docstring) for axis-angle poses (N, 21, 3).

    Returns {"loss", "kl" (nats, summed over dims), "geodesic" (rad), "joints_l1" (m)}.
    """
    target = roma.rotvec_to_rotmat(pose_body)  # (N, 21, 3, 3)
    out = model(pose_body)
    q = out["q_z"]
    prior = torch.distributions.Normal(torch.zeros_like(q.loc), torch.ones_like(q.scale))
    kl = torch.distributions.kl_divergence(q, prior).sum(-1).mean()
    rec = out["rotations"]
    geodesic = roma.rotmat_geodesic_distance(rec, target, clamping=1.0 - 1e-6).mean()
    eye = torch.eye(3, dtype=rec.dtype).expand(rec.shape[0], 1, 3, 3)
    _, j_rec = forward_kinematics(torch.cat([eye, rec], 1), rest_joints)
    _, j_tgt = forward_kinematics(torch.cat([eye, target], 1), rest_joints)
    joints_l1 = (j_rec - j_tgt).abs().mean()
    loss = KL_WEIGHT * kl + GEODESIC_WEIGHT * geodesic + JOINT_WEIGHT * joints_l1
    return {"loss": loss, "kl": kl, "geodesic": geodesic, "joints_l1": joints_l1}


def train_vposer(
    out_dir: str | Path | None = None,
    steps: int = 15000,
    seed: int = 0,
    *,
    hidden: int = EMBEDDED_CONFIG["hidden"],
    latent: int = EMBEDDED_CONFIG["latent"],
    batch_size: int = 256,
    lr: float = 1e-3,
    poses: torch.Tensor | None = None,
    val_poses: torch.Tensor | None = None,
    frame_every: int = 2,
    max_frames: int = 200_000,
    log_every: int = 200,
    dataset=None,
) -> tuple[VPoser, dict]:
    """Train a VPoser on body poses and write ``vposer.pt`` + ``vposer.json`` into ``out_dir``.

    poses / val_poses: (N, 22, 3) or (N, 21, 3) axis-angle; by default every ``frame_every``-th
    frame of the "train" split of ``dataset`` (at most ``max_frames``) and of its "val" split (if it
    builds); ``dataset``: the training data the caller hands over (:func:`priors.training.split_motions`). ``out_dir=None`` writes nothing (tests). Returns (trained model in eval mode, record).
    """
    data_info: dict = {}
    if poses is None:
        motions = training.split_motions(dataset, "train")
        poses = training.pose_frames(motions, every=frame_every, max_frames=max_frames, seed=seed)
        data_info["train"] = {"source": dataset.source("train"), "motions": len(motions),
                              "frame_every": frame_every, "frames": int(poses.shape[0])}
        if val_poses is None:
            try:
                val_motions = training.split_motions(dataset, "val")
                val_poses = training.pose_frames(val_motions, every=frame_every, max_frames=max_frames // 10, seed=seed)
                data_info["val"] = {"source": dataset.source("val"), "motions": len(val_motions),
                                    "frame_every": frame_every, "frames": int(val_poses.shape[0])}
            except Exception as exc:
                log.warning("no validation split (%s); training without a validation loss", exc)
                data_info["val"] = {"source": None, "error": f"{type(exc).__name__}: {exc}"}
    else:
        data_info["train"] = {"source": "poses given", "frames": int(poses.shape[0])}
        if val_poses is not None:
            data_info["val"] = {"source": "poses given", "frames": int(val_poses.shape[0])}

    def body_only(p: torch.Tensor) -> torch.Tensor:
        p = torch.as_tensor(p, dtype=torch.float32)
        if p.shape[1:] == (NUM_JOINTS, 3):
            p = p[:, 1:]
        if p.shape[1:] != (NUM_BODY_JOINTS, 3):
            raise ValueError(f"poses must be (N, 22, 3) or (N, 21, 3) axis-angle, got {tuple(p.shape)}")
        return p.contiguous()

    poses = body_only(poses)
    val_poses = body_only(val_poses) if val_poses is not None else None
    rest, rest_source = training.fixed_rest_skeleton()

    training.seed_everything(seed)
    model = VPoser(hidden=hidden, latent=latent)

    def loss_fn(m, batch):
        return vposer_loss(m, batch, rest)

    result = training.train_loop(
        model, loss_fn, poses, steps=steps, batch_size=batch_size, seed=seed, lr=lr, weight_decay=1e-5,
        final_lr_ratio=0.1, log_every=log_every, val_data=val_poses,
    )
    model.eval()
    record = {
        "prior": "vposer-slerp",
        "network": "VPoser V02_05 architecture (priors/vposer/model.py VPoser)",
        "config": model.config,
        "parameters": sum(p.numel() for p in model.parameters()),
        "data": data_info,
        "rest_skeleton": rest_source,
        "loss": f"{KL_WEIGHT}*KL + {GEODESIC_WEIGHT}*geodesic(rad) + {JOINT_WEIGHT}*L1(FK joints, m)",
        "optimiser": {"name": "Adam", "lr": lr, "weight_decay": 1e-5, "schedule": "cosine to 0.1*lr", "batch_size": batch_size},
        "steps": steps,
        "seed": seed,
        "torch_threads_training": 1,
        "train_wall_s": round(result.wall_s, 2),
        "final_train": result.final_train,
        "final_val": result.final_val,
        "history": result.history,
        **training.environment_record(),
    }
    if out_dir is not None:
        training.save_trained(out_dir, "vposer.pt", model.state_dict(), model.config, record)
    return model, record


def main(argv: list[str] | None = None) -> None:
    """``python -m priors.vposer.train --out priors/weights --steps 15000 --seed 0``: train the embedded weights."""
    from benchmark.core import argtypes as at
    from benchmark.synthetic.train_data import SyntheticTrainingData

    ap = training.recipe_parser("Train the embedded VPoser on the synthetic training split.", DEFAULT_WEIGHTS, 15000)
    ap.add_argument("--hidden", type=at.positive_int, default=EMBEDDED_CONFIG["hidden"])
    ap.add_argument("--latent", type=at.positive_int, default=EMBEDDED_CONFIG["latent"])
    ap.add_argument("--batch-size", type=at.positive_int, default=256)
    ap.add_argument("--frame-every", type=at.positive_int, default=2)
    args = training.parse_recipe_args(ap, DEFAULT_WEIGHTS, argv)
    _, rec = train_vposer(args.out, steps=args.steps, seed=args.seed, hidden=args.hidden, latent=args.latent,
                          batch_size=args.batch_size, frame_every=args.frame_every, dataset=SyntheticTrainingData())
    print({k: rec[k] for k in ("train_wall_s", "final_train", "final_val", "checkpoint_bytes")})


if __name__ == "__main__":
    main()
