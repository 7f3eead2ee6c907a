"""Sequential latent primitives: the embedded training recipe (data windows, point clouds, loss, loop).

``python -m priors.sequential_primitives.train --out priors/weights`` (or
``python -m benchmark train sequential-primitives``) retrains the embedded weights.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import fields as dc_fields
from pathlib import Path

import roma
import torch

from benchmark.body.lbs import forward_kinematics
from benchmark.core.frames import yaw_matrix
from benchmark.core.rotations import matrix_to_sixd, slerp_matrices
from benchmark.core.skeleton import NUM_JOINTS
from priors import training
from priors.sequential_primitives.model import (
    EMBEDDED_CONFIG,
    MODEL_JOINTS,
    SMPL_VERTICES,
    SequentialPrimitives,
    TRAIN_FPS,
    canonicalise,
    insert_feet,
)
from priors.sequential_primitives.checkpoint import DEFAULT_WEIGHTS

log = logging.getLogger(__name__)


LAMBDA_KL, LAMBDA_REG, LAMBDA_3D = 1e-4, 0.01, 1.0
JOINT_WEIGHT = SMPL_VERTICES / NUM_JOINTS

WINDOW_FRAMES = (60, 150)  # 2-5 s at 30 fps: the reconstruction table's 2 s windows and table1's 4 s ones
TRAIN_SAMPLES = 100  # n timestamps per training window
OBS_STRIDES = (3, 4, 5, 6)  # 10, 7.5, 6, 5 fps from 30 fps
OBS_POINTS = (100, 1000)
POINT_NOISE_M = 0.005
DEFAULT_STEPS = 8000  # motion VAE (1500: 160 mm reconstruction MPJPE, still falling; 3200: 109 mm; 8000: 34 mm)
DEFAULT_POINT_STEPS = 1500  # initialisation encoder (the adapter's train_embedded keeps this ratio to DEFAULT_STEPS)
TRANS_SCALE_MIN_M = 0.1  # floor of the per-axis translation scale (the vertical axis barely moves)


# -- the loss -----------------------------------------------------------------------------------
def primitives_loss(net: SequentialPrimitives, R: torch.Tensor, trans: torch.Tensor, tau: torch.Tensor,
                    shape: torch.Tensor, rest_joints: torch.Tensor, lambda_3d: float,
                    sample: bool = True) -> dict:
    """Eqs. 3-8 for canonical-frame windows: R (B, n, 22, 3, 3) (feet identity), trans (B, n, 3) m,
    tau (B, n), shape (B, S). Returns {"loss", "global", "segment", "kl", "reg", "pose", "trans",
    "joints" (unweighted mean over frames of the summed squared joint errors, m^2)}."""
    mu, logvar = net.encode(R, trans, tau)
    z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar) if sample else mu
    out = net.decoder(z, shape, tau, with_segments=True)
    m = z.shape[1]
    gt_six = matrix_to_sixd(R[:, :, list(MODEL_JOINTS)], "columns")  # (B, n, 20, 6)
    gt_g = (trans - net.decoder.trans_center) / net.decoder.trans_scale
    pose = (out["sixd"] - gt_six).square().sum((-1, -2)).mean()
    tr = (out["gamma"] - gt_g).square().sum(-1).mean()
    _, j_pred = forward_kinematics(out["rotations"], rest_joints)
    _, j_gt = forward_kinematics(R, rest_joints)
    joints = ((j_pred + out["trans"][..., None, :]) - (j_gt + trans[..., None, :])).square().sum((-1, -2)).mean()
    L_global = pose + tr + lambda_3d * JOINT_WEIGHT * joints
    G = out["masks"]  # (B, m, n)
    seg_pose = (out["seg_sixd"] - gt_six[:, None]).square().sum((-1, -2))
    seg_tr = (out["seg_gamma"] - gt_g[:, None]).square().sum(-1)
    L_segment = (G * (seg_pose + seg_tr)).sum(1).mean() / m
    kl = (0.5 * (mu.square() + logvar.exp() - 1.0 - logvar)).sum(-1).mean()  # (1/m) sum_j, mean over batch
    reg = (out["delta"] - 1.0 / m).square().sum(-1).mean()
    loss = L_global + L_segment + LAMBDA_KL * kl + LAMBDA_REG * reg
    return {"loss": loss, "global": L_global, "segment": L_segment, "kl": kl, "reg": reg, "pose": pose,
            "trans": tr, "joints": joints}


# -- training data ------------------------------------------------------------------------------
class WindowBank:
    """Frames of many motions in one tensor, and the starts of the windows that fit in them.

    frames (M, 69 + S): [axis-angle 22 x 3, trans 3, shape S] per 30 fps frame; starts (N,) long:
    frame indices where a window of ``max_frames`` frames lies inside one motion.
    """

    def __init__(self, frames: torch.Tensor, starts: torch.Tensor, max_frames: int, min_frames: int):
        self.frames, self.starts = frames, starts.long()
        self.max_frames, self.min_frames = int(max_frames), int(min_frames)
        if self.starts.numel() < 2:
            raise ValueError(f"need at least 2 training windows of {max_frames} frames, got {self.starts.numel()}")

    @classmethod
    def from_motions(cls, motions, shape_dim: int, stride: int = 10, frames=WINDOW_FRAMES, fps=TRAIN_FPS):
        lo, hi = frames
        chunks, starts, pos = [], [], 0
        for i, m in enumerate(motions):
            if abs(m.fps - fps) > 1e-6:
                m = m.resample_fps(fps)
            T = m.poses.shape[0]
            s = getattr(m, "shape", None)
            if s is None or torch.as_tensor(s).numel() == 0:
                s = torch.full((shape_dim,), 0.5)
            s = torch.as_tensor(s, dtype=torch.float32).reshape(-1)
            if s.numel() != shape_dim:
                raise ValueError(f"motion {i} ({getattr(m, 'name', '?')}): shape vector of size {s.numel()}, the "
                                 f"network takes shape_dim = {shape_dim}")
            x = torch.cat([torch.as_tensor(m.poses, dtype=torch.float32).reshape(T, -1),
                           torch.as_tensor(m.trans, dtype=torch.float32), s.expand(T, -1)], dim=1)
            chunks.append(x)
            if T >= hi:
                starts.append(pos + torch.arange(0, T - hi + 1, stride))
            pos += T
        if not starts:
            raise ValueError(f"no motion has {hi} frames at {fps} fps")
        return cls(torch.cat(chunks), torch.cat(starts), hi, lo)

    @classmethod
    def from_windows(cls, windows: torch.Tensor, shapes: torch.Tensor | None, shape_dim: int, frames=WINDOW_FRAMES):
        """windows (N, F, 69) as :func:`priors.training.motion_windows` gives; shapes (N, S) or None (0.5)."""
        windows = torch.as_tensor(windows, dtype=torch.float32)
        if windows.dim() != 3 or windows.shape[-1] != NUM_JOINTS * 3 + 3:
            raise ValueError(f"windows must be (N, F, 69) [axis-angle 66, trans 3], got {tuple(windows.shape)}")
        N, Fw = windows.shape[:2]
        if shapes is None:
            shapes = torch.full((N, shape_dim), 0.5)
        shapes = torch.as_tensor(shapes, dtype=torch.float32)
        if shapes.shape != (N, shape_dim):
            raise ValueError(f"window shapes must be (N, {shape_dim}) = ({N}, {shape_dim}), got {tuple(shapes.shape)}")
        hi = min(frames[1], Fw)
        lo = min(frames[0], hi)
        x = torch.cat([windows, shapes[:, None].expand(-1, Fw, -1)], dim=-1).reshape(N * Fw, -1)
        return cls(x, torch.arange(N) * Fw, hi, lo)

    def crop(self, starts: torch.Tensor, lengths: torch.Tensor, g: torch.Generator):
        """Random crops: (R (B, L, 22, 3, 3) feet identity, trans (B, L, 3), mask (B, L), shape (B, S)),
        L = max_frames, frames past each crop's length repeat its last frame; canonicalised."""
        B, L = starts.shape[0], self.max_frames
        off = (torch.rand(B, generator=g) * (L - lengths + 1).float()).long().clamp(max=L - 1)
        k = torch.arange(L)
        idx = starts[:, None] + off[:, None] + torch.minimum(k[None], lengths[:, None] - 1)
        x = self.frames[idx]  # (B, L, 69 + S)
        aa = x[..., : NUM_JOINTS * 3].unflatten(-1, (NUM_JOINTS, 3))
        R = roma.rotvec_to_rotmat(aa)
        R = insert_feet(R[:, :, list(MODEL_JOINTS)])
        mask = k[None] < lengths[:, None]
        Rc, tc, _, _ = canonicalise(R, x[..., NUM_JOINTS * 3: NUM_JOINTS * 3 + 3], mask)
        return Rc, tc, mask, x[:, 0, NUM_JOINTS * 3 + 3:]

    def random_lengths(self, B: int, g: torch.Generator) -> torch.Tensor:
        return torch.randint(self.min_frames, self.max_frames + 1, (B,), generator=g)

    def sample(self, starts: torch.Tensor, g: torch.Generator, n: int = TRAIN_SAMPLES):
        """Training samples: n sorted random timestamps per random 3-5 s crop, SLERP/LERP between frames.
        Returns R (B, n, 22, 3, 3), trans (B, n, 3), tau (B, n) in [0, 1), shape (B, S)."""
        lengths = self.random_lengths(starts.shape[0], g)
        R, tr, _, shape = self.crop(starts, lengths, g)
        t = torch.rand(starts.shape[0], n, generator=g).sort(-1).values * (lengths[:, None] - 1).float()
        k0 = t.floor().long().clamp(max=(lengths[:, None] - 2).clamp_min(0))
        w = (t - k0.float()).clamp(0, 1)
        k1 = torch.minimum(k0 + 1, lengths[:, None] - 1)
        b = torch.arange(starts.shape[0])[:, None]
        Rt = slerp_matrices(R[b, k0], R[b, k1], w[..., None])
        trt = tr[b, k0] + w[..., None] * (tr[b, k1] - tr[b, k0])
        return Rt, trt, t / lengths[:, None].float(), shape

    def trans_stats(self, stride: int = 5):
        """Per-axis (mean, standard deviation) of canonical translation over full-length windows.

        The scale is the standard deviation (floored at TRANS_SCALE_MIN_M), not the half-range: the
        half-range is set by the few fastest windows (6.3 / 0.5 / 8.5 m on the synthetic split), which
        made a 1 m translation error cost ~0.02 in the normalised loss against ~1 for the 6D pose, so
        the decoder's root path was left metres off."""
        n, s1, s2 = 0, torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
        starts = self.starts[::stride]
        for i in range(0, starts.numel(), 512):
            s = starts[i: i + 512]
            _, tc, _, _ = self.crop(s, torch.full_like(s, self.max_frames), torch.Generator().manual_seed(0))
            tc = tc.reshape(-1, 3).double()
            n, s1, s2 = n + tc.shape[0], s1 + tc.sum(0), s2 + tc.square().sum(0)
        mean = s1 / n
        std = (s2 / n - mean.square()).clamp_min(0).sqrt()
        return mean.float(), std.float().clamp_min(TRANS_SCALE_MIN_M)

    def shape_mean(self) -> torch.Tensor:
        return self.frames[self.starts][:, NUM_JOINTS * 3 + 3:].mean(0)


def _vertex_areas(body) -> torch.Tensor:
    """(V,) rest-mesh (default shape) area per vertex (1/3 of the incident triangles' area)."""
    with torch.no_grad():
        rest = body.prepare(body.default_shape(1))
        eye = torch.eye(3).expand(1, 1, NUM_JOINTS, 3, 3)
        v = body.skin(rest, eye, torch.zeros(1, 1, 3)).vertices[0, 0]
        f = body.faces.long()
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        area = torch.linalg.cross(b - a, c - a).norm(dim=-1) / 2
        out = torch.zeros(v.shape[0])
        for k in range(3):
            out.index_add_(0, f[:, k], area / 3)
    return out


class PointCloudMaker:
    """Point clouds of canonical windows on the body (the documented cheap stand-in for surface sampling)."""

    def __init__(self, body, bank: WindowBank):
        self.body = body
        self.areas = _vertex_areas(body)
        shapes = bank.frames[bank.starts][:, NUM_JOINTS * 3 + 3:]
        self.unique, self.inverse = torch.unique(shapes, dim=0, return_inverse=True)
        self.shape_of_start = dict(zip(bank.starts.tolist(), self.inverse.tolist()))
        with torch.no_grad():
            self.rests = [body.prepare(s[None]) for s in self.unique]

    def _rest(self, ids: torch.Tensor):
        first = self.rests[0]
        out = {}
        for f in dc_fields(first):
            vals = [getattr(self.rests[i], f.name) for i in ids.tolist()]
            if torch.is_tensor(vals[0]):
                out[f.name] = torch.cat(vals)
            elif isinstance(vals[0], dict):
                out[f.name] = {k: (torch.cat([v[k] for v in vals]) if torch.is_tensor(vals[0][k]) else vals[0][k]) for k in vals[0]}
            else:
                out[f.name] = vals[0]
        return type(first)(**out)

    @torch.no_grad()
    def make(self, starts, R, trans, points: int, g: torch.Generator):
        """R (B, T, 22, 3, 3), trans (B, T, 3) canonical -> points (B, T, P, 3) under a random yaw."""
        B, T = R.shape[:2]
        ids = torch.tensor([self.shape_of_start.get(int(s), 0) for s in starts])
        yaw = torch.rand(B, generator=g) * 2 * math.pi
        Y = yaw_matrix(yaw)[:, None]
        R = torch.cat([Y[:, :, None] @ R[:, :, :1], R[:, :, 1:]], dim=2)
        trans = (Y @ trans[..., None])[..., 0]
        pool = torch.multinomial(self.areas, min(2 * points, self.areas.numel()), replacement=False, generator=g)
        verts = self.body.skin(self._rest(ids), R, trans, vertex_indices=pool).vertices  # (B, T, K, 3)
        pick = torch.rand(B, T, pool.numel(), generator=g).argsort(-1)[..., :points]
        pts = verts.gather(2, pick[..., None].expand(-1, -1, -1, 3))
        return pts + POINT_NOISE_M * torch.randn(pts.shape, generator=g)


# -- training -----------------------------------------------------------------------------------
LAMBDA_3D_RAMP = 0.05  # fraction of the steps over which lambda_3D rises from 0 to 1 after the first half


def lambda_3d_schedule(step: int, steps: int) -> float:
    """0 for steps 1..steps//2 (paper: lambda_3D = 0 for the first phase), then a linear rise to 1
    over LAMBDA_3D_RAMP * steps steps (ours: the joint term is ~1000x the first-phase loss, and a
    jump would make Adam's first updates ~10x too large while its second moment catches up)."""
    half = steps // 2
    if step <= half:
        return 0.0
    ramp = max(1.0, LAMBDA_3D_RAMP * steps)
    return min(1.0, (step - half) / ramp)


def train_sequential_primitives(
    out_dir: str | Path | None = None,
    steps: int = DEFAULT_STEPS,
    point_steps: int = DEFAULT_POINT_STEPS,
    seed: int = 0,
    *,
    config: dict | None = None,
    motions: list | None = None,
    val_motions: list | None = None,
    windows: torch.Tensor | None = None,
    window_shapes: torch.Tensor | None = None,
    val_windows: torch.Tensor | None = None,
    val_window_shapes: torch.Tensor | None = None,
    body=None,
    rest_joints: torch.Tensor | None = None,
    batch_size: int = 16,
    point_batch_size: int = 8,
    lr: float = 1e-3,
    log_every: int = 100,
    max_val_windows: int = 256,
    dataset=None,
) -> tuple[SequentialPrimitives, dict]:
    """Train the motion VAE (``steps``) then the initialisation encoder (``point_steps``); write
    ``sequential_primitives.pt`` + ``.json`` into ``out_dir`` (None writes nothing).

    Data: by default the train / val splits of ``dataset`` (the training data the caller hands over:
    :func:`priors.training.split_motions`); or ``motions`` / ``val_motions`` (Motion
    lists); or ``windows`` (N, F, 69) (+ ``window_shapes`` (N, S)) for tests (crops of
    min(90, F)..min(150, F) frames). ``body``: the body that poses the initialisation encoder's point
    clouds (default: the embedded Anny body; only built when point_steps > 0). ``rest_joints``
    (22, 3): the FK skeleton of the 3D term (default :func:`priors.training.fixed_rest_skeleton`).
    Returns (network in eval mode, training record).
    """
    cfg = dict(EMBEDDED_CONFIG if config is None else config)
    S = int(cfg["shape_dim"])
    data_info: dict = {}
    if windows is not None:
        bank = WindowBank.from_windows(windows, window_shapes, S)
        data_info["train"] = {"source": "windows given", "windows": int(bank.starts.numel())}
        val_bank = WindowBank.from_windows(val_windows, val_window_shapes, S) if val_windows is not None else None
    else:
        if motions is None:
            motions = training.split_motions(dataset, "train")
            data_info["train"] = {"source": dataset.source("train")}
            if val_motions is None:
                try:
                    val_motions = training.split_motions(dataset, "val")
                    data_info["val"] = {"source": dataset.source("val")}
                except Exception as exc:
                    log.warning("no validation split (%s); training without a validation loss", exc)
                    data_info["val"] = {"source": None, "error": f"{type(exc).__name__}: {exc}"}
        bank = WindowBank.from_motions(motions, S)
        data_info.setdefault("train", {"source": "motions given"})
        data_info["train"].update(motions=len(motions), windows=int(bank.starts.numel()), window_stride_frames=10)
        val_bank = WindowBank.from_motions(val_motions, S, stride=30) if val_motions else None
        if val_bank is not None:
            data_info.setdefault("val", {"source": "motions given"})
            data_info["val"].update(motions=len(val_motions), windows=int(val_bank.starts.numel()))
    if rest_joints is None:
        rest_joints, rest_source = training.fixed_rest_skeleton()
    else:
        rest_source = "given"
    rest_joints = torch.as_tensor(rest_joints, dtype=torch.float32)

    training.seed_everything(seed)
    net = SequentialPrimitives(**cfg)
    center, scale = bank.trans_stats()
    net.set_normalisation(center, scale, bank.shape_mean())
    val_starts = None
    if val_bank is not None:
        gv = torch.Generator().manual_seed(seed + 7)
        val_starts = val_bank.starts[torch.randperm(val_bank.starts.numel(), generator=gv)[:max_val_windows]]

    # phase 1: the motion VAE --------------------------------------------------------------
    for p in net.point_encoder.parameters():
        p.requires_grad_(False)
    gen = torch.Generator().manual_seed(seed + 1)
    counter = {"step": 0}
    half = steps // 2

    def vae_loss(model, starts):
        if model.training and torch.is_grad_enabled():
            counter["step"] += 1
            src, g = bank, gen
        else:  # validation: fixed crops and timestamps, posterior means, lambda_3D on
            src, g = val_bank, torch.Generator().manual_seed(seed + 11)
        R, tr, tau, shape = src.sample(starts, g)
        lam = LAMBDA_3D * lambda_3d_schedule(counter["step"], steps) if model.training else LAMBDA_3D
        return primitives_loss(model, R, tr, tau, shape, rest_joints, lam, sample=model.training)

    t0 = time.perf_counter()
    res1 = training.train_loop(net, vae_loss, bank.starts, steps=steps, batch_size=batch_size, seed=seed, lr=lr,
                               final_lr_ratio=0.1, log_every=log_every, val_data=val_starts, val_batch=64)

    # phase 2: the initialisation encoder ---------------------------------------------------
    for p in net.parameters():
        p.requires_grad_(False)
    for p in net.point_encoder.parameters():
        p.requires_grad_(True)
    res2 = None
    if point_steps > 0:
        if body is None:
            from benchmark.body.anny_body import load_anny_body

            body = load_anny_body("cpu")
        if body.shape_dim != S:
            raise ValueError(f"body {body.name!r} takes {body.shape_dim} shape numbers, the network shape_dim is {S}")
        maker = PointCloudMaker(body, bank)
        val_maker = PointCloudMaker(body, val_bank) if val_bank is not None else None
        gen2 = torch.Generator().manual_seed(seed + 2)
        lo, hi = math.log(OBS_POINTS[0]), math.log(OBS_POINTS[1])

        def point_loss(model, starts):
            if model.training and torch.is_grad_enabled():
                src, mk, g = bank, maker, gen2
            else:
                src, mk, g = val_bank, val_maker, torch.Generator().manual_seed(seed + 12)
            B = starts.shape[0]
            L = int(torch.randint(src.min_frames, src.max_frames + 1, (1,), generator=g))
            stride = OBS_STRIDES[int(torch.randint(len(OBS_STRIDES), (1,), generator=g))]
            P = int(round(math.exp(lo + (hi - lo) * float(torch.rand(1, generator=g)))))
            R, tr, _, shape = src.crop(starts, torch.full((B,), L), g)
            R, tr = R[:, :L], tr[:, :L]
            tau_all = (torch.arange(L, dtype=torch.float32) / L).expand(B, L)
            with torch.no_grad():
                target, _ = model.encode(R, tr, tau_all)
            obs = torch.arange(0, L, stride)
            pts = mk.make(starts, R[:, obs], tr[:, obs], P, g)
            lengths = torch.full(pts.shape[:2], P, dtype=torch.long)
            pred = model.point_encoder(pts, lengths, tau_all[:, obs])
            mse = (pred - target).square().sum(-1).mean()
            return {"loss": mse, "latent_mse": mse, "target_norm2": target.square().sum(-1).mean()}

        res2 = training.train_loop(net, point_loss, bank.starts, steps=point_steps, batch_size=point_batch_size,
                                   seed=seed + 1, lr=lr, final_lr_ratio=0.1, log_every=log_every,
                                   val_data=val_starts[:64] if val_starts is not None else None, val_batch=16)
    wall = time.perf_counter() - t0
    for p in net.parameters():
        p.requires_grad_(False)
    net.eval()

    n_params = {k: sum(p.numel() for p in getattr(net, k).parameters())
                for k in ("motion_encoder", "decoder", "point_encoder")}
    record = {
        "prior": "sequential-primitives",
        "network": "priors/sequential_primitives/model.py SequentialPrimitives",
        "config": net.config,
        "parameters": sum(n_params.values()),
        "parameters_by_part": n_params,
        "data": data_info,
        "rest_skeleton": rest_source,
        "loss": (f"L_global (6D pose + normalised translation + lambda_3D*{JOINT_WEIGHT:.1f}*sum of squared FK joint "
                 f"errors, m^2) + L_segment + {LAMBDA_KL}*KL + {LAMBDA_REG}*sum(delta-1/m)^2; lambda_3D 0 for the "
                 f"first {half} steps, then a linear rise to {LAMBDA_3D} over {max(1, round(LAMBDA_3D_RAMP * steps))} steps"),
        "point_loss": "L2 between the initialisation encoder's output and the frozen motion encoder's mu",
        "optimiser": {"name": "Adam", "lr": lr, "schedule": "cosine to 0.1*lr", "batch_size": batch_size,
                      "point_batch_size": point_batch_size},
        "steps": steps,
        "point_steps": point_steps,
        "seed": seed,
        "torch_threads_training": 1,
        "train_wall_s": round(wall, 2),
        "vae_wall_s": round(res1.wall_s, 2),
        "point_wall_s": round(res2.wall_s, 2) if res2 else 0.0,
        "final_train": res1.final_train,
        "final_val": res1.final_val,
        "point_final_train": res2.final_train if res2 else None,
        "point_final_val": res2.final_val if res2 else None,
        "history": res1.history,
        "point_history": res2.history if res2 else [],
        **training.environment_record(),
    }
    if out_dir is not None:
        training.save_trained(out_dir, DEFAULT_WEIGHTS.name, net.state_dict(), net.config, record)
    return net, record


def main(argv: list[str] | None = None) -> None:
    """``python -m priors.sequential_primitives.train --out priors/weights``: train the embedded weights."""
    from benchmark.core import argtypes as at
    from benchmark.synthetic.train_data import SyntheticTrainingData

    ap = training.recipe_parser("Train the embedded sequential-primitives prior on the synthetic split.",
                                DEFAULT_WEIGHTS, DEFAULT_STEPS)
    ap.add_argument("--point-steps", type=at.positive_int, default=DEFAULT_POINT_STEPS)
    args = training.parse_recipe_args(ap, DEFAULT_WEIGHTS, argv)
    _, rec = train_sequential_primitives(args.out, steps=args.steps, point_steps=args.point_steps, seed=args.seed,
                                         dataset=SyntheticTrainingData())
    print({k: rec[k] for k in ("train_wall_s", "final_train", "final_val", "point_final_val", "checkpoint_bytes")})


if __name__ == "__main__":
    main()
