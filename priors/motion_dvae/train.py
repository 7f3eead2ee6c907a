"""Motion-DVAE: the embedded training recipe (statistics, DVAE phase, denoising phase).

``python -m priors.motion_dvae.train --out priors/weights`` (or ``python -m benchmark train motion-dvae``)
retrains the embedded weights.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import time
from pathlib import Path

import torch

from benchmark.core.skeleton import NUM_JOINTS
from priors import training, training_state
from priors.motion_dvae.model import (
    EMBEDDED_CONFIG,
    KL_ANNEAL_FRACTION,
    MotionDVAE,
    NOISE_PRIOR_SCALE_M,
    NOISE_PRIOR_SHAPE,
    PAPER_CONFIG,
    POINT_WEIGHT,
    STATE_STD_FLOOR,
)
from priors.motion_dvae.states import (
    DENOISE_SIGMA_RANGE,
    FPS,
    STATE_DIM,
    body_points,
    canonical_poses,
    noisy_poses,
    pose_to_state,
    state_to_motion,
)
from priors.motion_dvae.checkpoint import DEFAULT_WEIGHTS

log = logging.getLogger(__name__)


# -- training --------------------------------------------------------------------------------
def compute_statistics(poses: torch.Tensor, max_windows: int = 20000, seed: int = 0) -> dict:
    """Standardisation statistics of the states of canonical pose windows (N, F, 69), and the mean
    first-frame state (a seeded subset of ``max_windows`` windows)."""
    if poses.shape[0] > max_windows:
        g = torch.Generator().manual_seed(seed)
        poses = poses[torch.randperm(poses.shape[0], generator=g)[:max_windows]]
    states = pose_to_state(poses)
    flat = states.reshape(-1, STATE_DIM)
    return {"state_mean": flat.mean(0), "state_std": flat.std(0).clamp_min(STATE_STD_FLOOR), "x0_mean": states[:, 0].mean(0)}


def _check_windows(w: torch.Tensor, what: str) -> torch.Tensor:
    w = torch.as_tensor(w, dtype=torch.float32)
    if w.dim() != 3 or w.shape[-1] != NUM_JOINTS * 3 + 3 or w.shape[1] < 2:
        raise ValueError(f"{what} must be (N, F >= 2, 69) windows (priors.training.motion_windows), got {tuple(w.shape)}")
    return w.contiguous()


# Training windows are 4 s (120 frames) and each training batch is cut to its first L frames, L drawn
# from CROP_FRAMES with CROP_PROBS (torch's global RNG, restored on --resume). Trained on 1 s windows
# only, the recurrent decoder (x_t = x_0 + sum of increments) was accurate for 1 s (reconstruction
# MPJPE 31 mm on the test split) and drifted beyond it (170 mm at 2 s, 860 mm at 4 s: the root
# overshoots by metres on running motions), while the tables use 2 s windows and completion 4 s.
CROP_FRAMES = (30, 60, 120)
CROP_PROBS = (0.2, 0.4, 0.4)


def _crop(batch: torch.Tensor, lengths, probs) -> torch.Tensor:
    """The first L frames of a batch of canonical pose windows (N, F, 69), L ~ ``lengths`` (capped at F)."""
    i = int(torch.multinomial(torch.tensor(probs, dtype=torch.float32), 1))
    return batch[:, : max(2, min(int(lengths[i]), batch.shape[1]))]


def train_motion_dvae(
    out_dir: str | Path | None = None,
    steps: int = 1800,
    denoise_steps: int = 720,
    seed: int = 0,
    *,
    config: dict | None = None,
    batch_size: int = 32,
    lr: float = 1e-3,
    denoise_lr: float = 1e-3,
    windows: torch.Tensor | None = None,
    val_windows: torch.Tensor | None = None,
    rest_joints: torch.Tensor | None = None,
    frames: int = 120,
    stride: int = 20,
    crop_frames: tuple = CROP_FRAMES,
    crop_probs: tuple = CROP_PROBS,
    log_every: int = 200,
    val_max_windows: int = 512,
    init_weights: str | Path | None = None,
    init_denoise: bool = False,
    init_denoise_weights: str | Path | None = None,
    train_generative: bool = True,
    encoder_point_weight: float | None = None,
    encoder_root_marker_m: float = 0.0,
    encoder_input_noise: tuple[float, float] | None = None,
    kl_anneal_fraction: float | None = None,
    dataset=None,
) -> tuple[MotionDVAE, dict]:
    """Train the embedded Motion-DVAE (phase 1: DVAE on clean windows; phase 2: denoising networks on
    noisy copies, prior and decoder frozen) and write ``motion_dvae.pt`` + ``motion_dvae.json``.

    windows / val_windows: (N, F, 69) raw windows (default: ``priors.training.motion_windows`` of the
    train / val splits of ``dataset``, the training data the caller hands over
    (:func:`priors.training.split_motions`), ``frames`` frames every ``stride`` at 30 fps). rest_joints: the
    skeleton of the point losses (default ``priors.training.fixed_rest_skeleton``). The shared loop
    ``priors.training.train_loop`` is used (Adam, cosine decay to 0.1 lr, one thread); the paper
    (HuMoR settings) uses Adamax lr 1e-4 for 200 epochs, too slow for the embedded CPU budget.
    ``out_dir=None`` writes nothing. Returns (model in eval mode, record).

    init_weights: a project checkpoint (``motion_dvae.pt``) whose DVAE (generative model, clean
    encoder) and statistics buffers start phase 1 (a warm start; the denoising networks start fresh);
    then the KL weight is 1 from the first step unless ``kl_anneal_fraction`` says otherwise.
    init_denoise: the denoising networks of ``init_weights`` start phase 2 too (a continued denoising
    phase); init_denoise_weights: take them from this other checkpoint instead (it implies
    init_denoise). train_generative=False: phase 1 trains the clean encoder only (prior, decoder and
    their variance frozen: the completion tables, which use only the generative model, do not move).
    encoder_point_weight: with train_generative=False, the weight of the squared point errors in
    the clean encoder's loss (default POINT_WEIGHT, the DVAE's own). The clean encoder serves only
    ``encode_motion`` (the reconstruction table, completion's encoded start); a larger weight fits it
    to reconstruct more closely at the cost of more nats of KL, like a beta < 1 for the inference
    network alone, while the generative model and its loss stay the DVAE's.
    encoder_input_noise: (lo, hi) rad, with train_generative=False: in training the clean encoder
    reads a noisy copy of each window (every body joint's rotation vector plus N(0, sigma^2) per
    axis and frame, sigma ~ U(lo, hi) per window; root and translation clean, so the copy keeps
    the window's canonical frame), its first frame (held within the data's range,
    ``MotionDVAE.dvae_loss``) the decoder's x_0, and is scored on
    reconstructing the clean window: an encoder for the motions it meets as a completion start
    (an optimiser's estimate, off by a few degrees per joint), not only for clean data.
    Validation stays clean.
    steps=0 / denoise_steps=0 skip a phase (the loaded networks are kept as they are).
    """
    if init_denoise_weights is not None:
        if init_weights is None:
            raise ValueError("init_denoise_weights needs init_weights (the DVAE the denoising networks belong to)")
        init_denoise = True
    if not train_generative and init_weights is None:
        raise ValueError("train_generative=False (encoder only) needs init_weights (a trained generative model)")
    if (encoder_point_weight is not None or encoder_root_marker_m or encoder_input_noise is not None) and train_generative:
        raise ValueError("encoder_point_weight, encoder_root_marker_m and encoder_input_noise apply to encoder-only "
                         "training (train_generative=False)")
    if encoder_input_noise is not None:
        lo_hi = tuple(float(v) for v in encoder_input_noise)
        if len(lo_hi) != 2 or not 0.0 <= lo_hi[0] <= lo_hi[1]:
            raise ValueError(f"encoder_input_noise must be (lo, hi) rad with 0 <= lo <= hi, got {encoder_input_noise!r}")
        encoder_input_noise = lo_hi
    pw = float(POINT_WEIGHT if encoder_point_weight is None else encoder_point_weight)  # phase 1's point weight
    cfg = dict(EMBEDDED_CONFIG, **(config or {}))
    data_info: dict = {}
    if windows is None:
        motions = training.split_motions(dataset, "train")
        windows = training.motion_windows(motions, frames, stride, fps=FPS)
        data_info["train"] = {"source": dataset.source("train"), "motions": len(motions),
                              "frames": frames, "stride": stride, "windows": int(windows.shape[0])}
        if val_windows is None:
            try:
                vm = training.split_motions(dataset, "val")
                val_windows = training.motion_windows(vm, frames, frames, fps=FPS, max_windows=val_max_windows, seed=seed)
                data_info["val"] = {"source": dataset.source("val"), "motions": len(vm),
                                    "frames": frames, "stride": frames, "windows": int(val_windows.shape[0])}
            except Exception as exc:
                log.warning("no validation split (%s); training without a validation loss", exc)
                data_info["val"] = {"source": None, "error": f"{type(exc).__name__}: {exc}"}
    else:
        data_info["train"] = {"source": "windows given", "windows": int(windows.shape[0])}
        if val_windows is not None:
            data_info["val"] = {"source": "windows given", "windows": int(val_windows.shape[0])}
    windows = _check_windows(windows, "windows")
    val_windows = _check_windows(val_windows, "val_windows") if val_windows is not None else None
    if rest_joints is None:
        rest_joints, rest_source = training.fixed_rest_skeleton()
    else:
        rest_source = "given"

    training.seed_everything(seed)
    model = MotionDVAE(**cfg)
    t_prep = time.perf_counter()
    poses = canonical_poses(windows)  # the training data: canonical, unwrapped pose sequences
    del windows
    val_poses = canonical_poses(val_windows) if val_windows is not None else None
    stats = compute_statistics(poses, seed=seed)
    prep_wall = time.perf_counter() - t_prep
    with torch.no_grad():
        for k, v in stats.items():
            getattr(model, k).copy_(v)
        model.rest_joints.copy_(torch.as_tensor(rest_joints, dtype=torch.float32))
    init_info = None
    if init_weights is not None:
        import hashlib

        from priors.motion_dvae import checkpoint

        init_net, init_report = checkpoint.load(Path(init_weights))
        sd, init_cfg = init_net.state_dict(), init_report.config
        if {k: init_cfg[k] for k in ("z_dim", "hidden", "mlp_hidden")} != {k: cfg[k] for k in ("z_dim", "hidden", "mlp_hidden")}:
            raise ValueError(f"init_weights {init_weights}: config {init_cfg} does not match {cfg}")
        keep = ("gen_rnn.", "prior_mean.", "prior_logvar.", "decoder.", "dec_logvar", "encoder.", "state_mean", "state_std", "x0_mean")
        if init_denoise:  # also the denoising networks (a continued denoising phase)
            keep = keep + ("denoise_encoder.", "init_state.", "noise.")
        part = {k: v.float() for k, v in sd.items() if k.startswith(keep)}
        if init_denoise_weights is not None:
            denoise_net, denoise_report = checkpoint.load(Path(init_denoise_weights))
            dsd, dcfg = denoise_net.state_dict(), denoise_report.config
            if {k: dcfg[k] for k in ("z_dim", "hidden", "mlp_hidden")} != {k: cfg[k] for k in ("z_dim", "hidden", "mlp_hidden")}:
                raise ValueError(f"init_denoise_weights {init_denoise_weights}: config {dcfg} does not match {cfg}")
            dkeep = ("denoise_encoder.", "init_state.", "noise.")
            part.update({k: v.float() for k, v in dsd.items() if k.startswith(dkeep)})
        missing = [k for k in model.state_dict() if k.startswith(keep) and k not in part
                   and not (k.startswith("encoder.res_") and not init_cfg.get("encoder_residual"))]  # they start at zero
        if missing:
            raise ValueError(f"init_weights {init_weights}: missing {missing[:5]}")
        unexpected = [k for k in part if k not in model.state_dict()]
        if unexpected:  # e.g. a residual encoder loaded into a config without it: its weights would be dropped
            raise ValueError(f"init_weights {init_weights}: keys {unexpected[:5]} have no place in config {cfg} "
                             f"(the checkpoint's config is {init_cfg}); train with the checkpoint's config")
        model.load_state_dict(part, strict=False)
        init_info = {"path": str(init_weights), "sha256": hashlib.sha256(Path(init_weights).read_bytes()).hexdigest(),
                     "loaded": "generative model, clean encoder, state statistics (its own, not recomputed)"
                               + (", denoising networks (continued)" if init_denoise and init_denoise_weights is None else "")}
        if init_denoise_weights is not None:
            init_info["denoise_networks"] = {
                "path": str(init_denoise_weights),
                "sha256": hashlib.sha256(Path(init_denoise_weights).read_bytes()).hexdigest(),
                "loaded": "denoise_encoder, init_state, noise"}
    if kl_anneal_fraction is None:
        kl_anneal_fraction = 0.0 if init_weights is not None else KL_ANNEAL_FRACTION

    # phase 1: the DVAE on clean canonical windows, KL annealing
    anneal = max(1, int(kl_anneal_fraction * steps))
    counter = {"dvae": 0, "denoise": 0}

    def dvae_loss(m: MotionDVAE, batch: torch.Tensor) -> dict:
        if m.training:
            batch = _crop(batch, crop_frames, crop_probs)
            counter["dvae"] += 1
            beta = min(1.0, counter["dvae"] / anneal) if kl_anneal_fraction > 0 else 1.0
        else:
            beta = 1.0
        with torch.no_grad():
            states = pose_to_state(batch)
            pts = body_points(*state_to_motion(states), m.rest_joints)
        if not m.training:
            return m.dvae_loss(states, pts, beta, point_weight=POINT_WEIGHT)
        enc_states = None
        if encoder_input_noise is not None:
            with torch.no_grad():
                enc_states = pose_to_state(noisy_poses(batch, None, encoder_input_noise, body_only=True)[0])
        return m.dvae_loss(states, pts, beta, point_weight=pw, root_marker_m=encoder_root_marker_m,
                           encoder_states=enc_states)

    for p in model.parameters():
        p.requires_grad_(False)
    gen_modules = [model.gen_rnn, model.prior_mean, model.prior_logvar, model.decoder] if train_generative else []
    for mod in gen_modules + [model.encoder]:
        for p in mod.parameters():
            p.requires_grad_(True)
    model.dec_logvar.requires_grad_(bool(train_generative))
    t0 = time.perf_counter()
    if steps > 0:
        r1 = training.train_loop(model, dvae_loss, poses, steps=steps, batch_size=batch_size, seed=seed, lr=lr,
                                 log_every=log_every, val_data=val_poses, val_batch=256)
    else:  # the DVAE of init_weights as it is (only the denoising phase is trained)
        if init_weights is None:
            raise ValueError("steps=0 (no DVAE phase) needs init_weights")
        model.eval()
        r1 = training.TrainResult(steps=0, wall_s=0.0, final_train=None,
                                  final_val=training.evaluate(model, dvae_loss, val_poses, 256) if val_poses is not None else None)
    phase1_wall = time.perf_counter() - t0

    # phase 2: denoising networks on noisy copies; prior, decoder and clean encoder frozen
    if not (init_weights is not None and init_denoise) and denoise_steps > 0:
        with torch.no_grad():
            # the denoising encoder has no residual input (Encoder docstring): every other weight is copied
            model.denoise_encoder.load_state_dict({k: v for k, v in model.encoder.state_dict().items()
                                                   if not k.startswith("res_")})
    for p in model.parameters():
        p.requires_grad_(False)
    for mod in (model.denoise_encoder, model.init_state, model.noise):
        for p in mod.parameters():
            p.requires_grad_(True)
    anneal2 = max(1, int(KL_ANNEAL_FRACTION * denoise_steps))
    continued = init_weights is not None and init_denoise  # a continued denoising phase: no KL annealing

    def denoise_loss(m: MotionDVAE, batch: torch.Tensor) -> dict:
        if m.training:
            batch = _crop(batch, crop_frames, crop_probs)
            counter["denoise"] += 1
            beta, g = (1.0 if continued else min(1.0, counter["denoise"] / anneal2)), None
        else:
            beta, g = 1.0, torch.Generator().manual_seed(seed + 1)
        with torch.no_grad():
            noisy, _ = noisy_poses(batch, g)
            states = pose_to_state(noisy)
            obs = body_points(*state_to_motion(states), m.rest_joints)
        return m.denoise_loss(states, obs, beta, generator=g)

    t0 = time.perf_counter()
    if denoise_steps > 0:
        r2 = training.train_loop(model, denoise_loss, poses, steps=denoise_steps, batch_size=batch_size, seed=seed + 1,
                                 lr=denoise_lr, log_every=log_every, val_data=val_poses, val_batch=256)
    else:  # the denoising networks as loaded
        model.eval()
        r2 = training.TrainResult(steps=0, wall_s=0.0, final_train=None,
                                  final_val=training.evaluate(model, denoise_loss, val_poses, 256) if val_poses is not None else None)
    phase2_wall = time.perf_counter() - t0
    for p in model.parameters():
        p.requires_grad_(False)
    model.eval()

    record = {
        "prior": "motion-dvae",
        "network": "Motion-DVAE (priors/motion_dvae/model.py MotionDVAE), embedded size",
        "config": model.config,
        "parameters": model.parameter_counts(),
        "paper_parameters": MotionDVAE(**PAPER_CONFIG).parameter_counts(),
        "data": data_info,
        "rest_skeleton": rest_source,
        "init_weights": init_info,
        "windows": {"frames": frames, "stride": stride, "train_crops": {"frames": list(crop_frames), "probs": list(crop_probs)},
                    "note": "each training batch is cut to its first L frames (L drawn per step); validation on whole windows"},
        "state": "138-D: trans, root aa, 21 body aa, finite-difference velocities x30; canonical first frame (HuMoR)",
        "phase_dvae": {
            "loss": f"Gaussian NLL of the standardised state (learned per-dim variance) + beta*KL(q||p) + {pw}*sum squared point errors (m^2; "
                    "22 FK joints + 44 virtual markers), per frame; beta 0->1 over the first "
                    f"{kl_anneal_fraction:.0%} of steps",
            "optimiser": {"name": "Adam (shared train_loop)", "lr": lr, "schedule": "cosine to 0.1*lr", "batch_size": batch_size},
            "trained": (["gen_rnn", "prior_mean", "prior_logvar", "decoder", "dec_logvar"] if train_generative else []) + ["encoder"]
                       if steps > 0 else [],
            "point_weight": pw, "validation_point_weight": POINT_WEIGHT, "root_marker_m": encoder_root_marker_m,
            "encoder_input_noise_rad": list(encoder_input_noise) if encoder_input_noise is not None else None,
            "steps": steps, "train_wall_s": round(phase1_wall, 2), "s_per_step": round(r1.wall_s / max(steps, 1), 4),
            "final_train": r1.final_train, "final_val": r1.final_val, "history": r1.history,
        },
        "phase_denoise": {
            "loss": "Student-t (Inverse-Gamma per-frame variance) data term on body points + beta*KL_z + KL_noise, per frame",
            "noise": f"axis-angle sigma ~ U{DENOISE_SIGMA_RANGE} rad on all 22 joints; noise prior InvGamma(a0={NOISE_PRIOR_SHAPE}, "
                     f"mean precision 1/{NOISE_PRIOR_SCALE_M}^2)",
            "trained": ["denoise_encoder (initialised from encoder)", "init_state", "noise"] if denoise_steps > 0 else [],
            "optimiser": {"name": "Adam (shared train_loop)", "lr": denoise_lr, "schedule": "cosine to 0.1*lr", "batch_size": batch_size},
            "steps": denoise_steps, "train_wall_s": round(phase2_wall, 2), "s_per_step": round(r2.wall_s / max(denoise_steps, 1), 4),
            "final_train": r2.final_train, "final_val": r2.final_val, "history": r2.history,
        },
        "paper_settings_not_used": "Adamax lr 1e-4 (HuMoR), batch 64, 200 epochs, KL annealing over 50 epochs",
        "data_preparation_wall_s": round(prep_wall, 2),
        "seed": seed,
        "torch_threads_training": 1,
        "train_wall_s": round(phase1_wall + phase2_wall, 2),
        **training.environment_record(),
    }
    if out_dir is not None:
        training.save_trained(out_dir, DEFAULT_WEIGHTS.name, model.state_dict(), model.config, record)
    return model, record


def main(argv: list[str] | None = None) -> None:
    """``python -m priors.motion_dvae.train --out priors/weights``: train the embedded weights."""
    from benchmark.core import argtypes as at
    from benchmark.synthetic.train_data import SyntheticTrainingData

    # steps / denoise steps 0: skip that phase (needs --init)
    ap = training.recipe_parser("Train the embedded Motion-DVAE on the synthetic training split.", DEFAULT_WEIGHTS, 1800,
                                min_steps=0)
    ap.add_argument("--denoise-steps", type=at.non_negative_int, default=720)
    ap.add_argument("--init", default=None, help="warm start phase 1 from this motion_dvae.pt (DVAE and statistics)")
    ap.add_argument("--lr", type=at.positive_float, default=1e-3, help="phase-1 learning rate")
    ap.add_argument("--denoise-lr", type=at.positive_float, default=1e-3, help="phase-2 learning rate")
    ap.add_argument("--encoder-only", action="store_true",
                    help="phase 1 trains the clean encoder only (the generative model of --init stays as it is)")
    ap.add_argument("--encoder-point-weight", type=at.non_negative_float, default=None,
                    help="with --encoder-only: the point-error weight of the clean encoder's loss (default: the DVAE's)")
    ap.add_argument("--encoder-root-marker", type=at.non_negative_float, default=0.0, metavar="M",
                    help="with --encoder-only: two extra markers M metres along the root's x and z axes in the clean "
                         "encoder's point loss (weighs the root heading like a lever of M metres)")
    ap.add_argument("--encoder-input-noise", type=at.non_negative_float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="with --encoder-only: the clean encoder reads windows whose body joints are turned by "
                         "N(0, sigma^2) rad per axis and frame, sigma ~ U(LO, HI) per window, and learns to "
                         "reconstruct the clean window")
    ap.add_argument("--encoder-residual", action=argparse.BooleanOptionalAction, default=None,
                    help="whether the clean encoder also reads target minus decoded pose (config encoder_residual; "
                         "default: on, as the embedded weights; from an --init without it, its weights start at zero)")
    ap.add_argument("--init-denoise", action="store_true", help="phase 2 continues the denoising networks of --init")
    ap.add_argument("--denoise-from", default=None, help="phase 2 starts from the denoising networks of this motion_dvae.pt")
    ap.add_argument("--checkpoint-dir", default=None,
                    help="save the resumable training state here every --checkpoint-every steps (--resume continues it)")
    ap.add_argument("--checkpoint-every", type=at.positive_int, default=200)
    ap.add_argument("--resume", action="store_true")
    args = training.parse_recipe_args(ap, DEFAULT_WEIGHTS, argv)
    if args.resume and not (args.checkpoint_dir and Path(args.checkpoint_dir).exists()):
        raise SystemExit(f"--resume: no training state in --checkpoint-dir {args.checkpoint_dir!r}; start the training "
                         f"with --checkpoint-dir DIR (and without --resume) first")
    ctx = (training_state.training_session(args.checkpoint_dir, resume=args.resume,
                                           checkpoint_every=args.checkpoint_every, val_every=500) if args.checkpoint_dir else contextlib.nullcontext())
    with ctx:
        _, rec = train_motion_dvae(args.out, steps=args.steps, denoise_steps=args.denoise_steps, seed=args.seed,
                                   init_weights=args.init, lr=args.lr, denoise_lr=args.denoise_lr,
                                   init_denoise=args.init_denoise, init_denoise_weights=args.denoise_from,
                                   train_generative=not args.encoder_only,
                                   encoder_point_weight=args.encoder_point_weight,
                                   encoder_root_marker_m=args.encoder_root_marker,
                                   encoder_input_noise=args.encoder_input_noise,
                                   config=None if args.encoder_residual is None else {"encoder_residual": args.encoder_residual},
                                   dataset=SyntheticTrainingData())
    print({k: rec[k] for k in ("train_wall_s", "checkpoint_bytes")})


if __name__ == "__main__":
    main()
