"""VPoser V02_05 (Pavlakos et al. 2019, ``nghorbani/human_body_prior``) and the VPoser+SLERP prior.

Three parts (see /work/shared/priors.md section 1):

1. :class:`VPoser`: the V02_05 network, layer for layer (so the official keys map one to one).
   Paper size ``hidden=512, latent=32`` has 936,252 parameters.
2. :func:`load_vposer_checkpoint`: a strict loader for the official Lightning checkpoint
   (``V02_05/snapshots/*.ckpt``) and for the project's own ``priors/weights/vposer.pt``.
3. :class:`VPoserSlerp`: the prior adapter of paper 000 section 5.5 ("VPoser+SLERP"): one latent per
   observed frame, decoded at the observed timestamps; the protocol SLERPs the rotations to the
   output timestamps and owns root orientation and translation.

The embedded weights (``size="embedded"``) are a smaller VPoser (``EMBEDDED_CONFIG``: hidden 256,
latent 32, 271,676 parameters, ~1.1 MB) trained by :func:`train_vposer` on the synthetic training
split. Training loss (the official one needs SMPL-X vertices, which this project does not ship):

    0.005 * KL(q(z|x) || N(0, I))   (sum over latent dims, mean over the batch; official weight)
  + 2     * geodesic angle between decoded and input rotations (rad, mean over joints; official weight)
  + 6     * L1 of joint positions by forward kinematics on a fixed rest skeleton (metres, mean)

The official recipe has 4 * L1(vertices) + 2 * L1(joints); with no mesh, the joint term takes both
weights (6). Joint positions are the cheap stand-in for vertices: they weigh errors by the lever
arm of each joint, which the geodesic term alone does not. Adam, lr 1e-3 with a cosine decay to
1e-4, weight decay 1e-5 (official), batch 256, 15,000 steps on every 2nd frame of the train split
(135k poses), one torch thread: about 3.5 min on one CPU core
(``python -m priors.vposer --out priors/weights``; record in ``priors/weights/vposer.json``;
its train losses are measured with dropout on, its validation losses in eval mode).

Beyond the fitting API the adapter provides ``encode_motion`` (per-frame posterior means, for the
reconstruction table), ``export_decoder`` (ONNX: ``z`` (B, 32) -> ``rotations`` (B, 22, 3, 3),
identity root; ``python -m benchmark export-onnx vposer-slerp``) and ``paper_network`` (the paper
size with random weights, for ``python -m benchmark describe vposer-slerp --size paper``).
"""

from __future__ import annotations

import logging
import pickle
import re
import types
from dataclasses import dataclass, field
from pathlib import Path

import roma
import torch
import torch.nn.functional as F
from torch import nn

from benchmark.body.lbs import forward_kinematics
from benchmark.rotations import sixd_to_matrix
from benchmark.skeleton import NUM_JOINTS
from priors.base import Decoded, FitBatch, PriorAdapter, WindowSpec
from priors.base import ExportSpec

log = logging.getLogger(__name__)

NUM_BODY_JOINTS = 21  # SMPL joints 1..21
PAPER_CONFIG = {"hidden": 512, "latent": 32}
EMBEDDED_CONFIG = {"hidden": 256, "latent": 32}
DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "vposer.pt"
OFFICIAL_PREFIX = "vp_model."
WHERE_TO_GET = (
    "VPoser V02_05 is distributed (registration required) as V02_05.zip on the SMPL-X download page "
    "https://smpl-x.is.tue.mpg.de/download.php; unzip it and pass the folder (or its "
    "snapshots/*.ckpt file), e.g. `--weights vposer-slerp=/path/V02_05`"
)


# -- the network -----------------------------------------------------------------------------
class NormalDistDecoder(nn.Module):
    """Encoder head: ``Normal(mu(x), softplus(logvar(x)))``; the "logvar" head is a softplus scale."""

    def __init__(self, num_feat_in: int, latent: int):
        super().__init__()
        self.mu = nn.Linear(num_feat_in, latent)
        self.logvar = nn.Linear(num_feat_in, latent)

    def forward(self, x: torch.Tensor) -> torch.distributions.Normal:
        return torch.distributions.Normal(self.mu(x), F.softplus(self.logvar(x)))


class ContinousRotReprDecoder(nn.Module):
    """(B, 21*6) -> (B*21, 3, 3): VPoser's 6D decoder, "interleaved" layout (row-major 3x2)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return sixd_to_matrix(x.reshape(-1, 6), layout="interleaved")


class VPoser(nn.Module):
    """The VPoser V02_05 network; module indices match the official state-dict keys.

    ``encoder_net``: 0 flatten, 1 BatchNorm1d(63), 2 Linear(63, H), 3 LeakyReLU(0.01),
    4 BatchNorm1d(H), 5 Dropout(0.1), 6 Linear(H, H), 7 Linear(H, H) (no activation between 6 and
    7, as in the official code), 8 NormalDistDecoder(H, L).
    ``decoder_net``: 0 Linear(L, H), 1 LeakyReLU(0.01), 2 Dropout(0.1), 3 Linear(H, H),
    4 LeakyReLU(0.01), 5 Linear(H, 126), 6 ContinousRotReprDecoder.
    """

    def __init__(self, hidden: int = 512, latent: int = 32):
        super().__init__()
        self.hidden, self.latent = int(hidden), int(latent)
        n_in = NUM_BODY_JOINTS * 3
        H, L = self.hidden, self.latent
        self.encoder_net = nn.Sequential(
            nn.Flatten(),
            nn.BatchNorm1d(n_in),
            nn.Linear(n_in, H),
            nn.LeakyReLU(0.01),
            nn.BatchNorm1d(H),
            nn.Dropout(0.1),
            nn.Linear(H, H),
            nn.Linear(H, H),
            NormalDistDecoder(H, L),
        )
        self.decoder_net = nn.Sequential(
            nn.Linear(L, H),
            nn.LeakyReLU(0.01),
            nn.Dropout(0.1),
            nn.Linear(H, H),
            nn.LeakyReLU(0.01),
            nn.Linear(H, NUM_BODY_JOINTS * 6),
            ContinousRotReprDecoder(),
        )

    @property
    def config(self) -> dict:
        return {"hidden": self.hidden, "latent": self.latent}

    def encode(self, pose_body: torch.Tensor) -> torch.distributions.Normal:
        """(B, 21, 3) or (B, 63) axis-angle body pose (radians) -> Normal over z, loc/scale (B, L)."""
        return self.encoder_net(pose_body)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """(B, L) latents -> (B, 21, 3, 3) local rotations of SMPL joints 1..21."""
        return self.decoder_net(z).reshape(z.shape[0], NUM_BODY_JOINTS, 3, 3)

    def forward(self, pose_body: torch.Tensor) -> dict:
        q = self.encode(pose_body)
        z = q.rsample()
        return {"q_z": q, "z": z, "rotations": self.decode(z)}


# -- strict checkpoint loading ---------------------------------------------------------------
def expected_keys(model: VPoser) -> dict[str, tuple[int, ...]]:
    """The state-dict entries a VPoser checkpoint must hold, with their shapes (26 entries)."""
    return {k: tuple(v.shape) for k, v in model.state_dict().items()}


def optional_keys(model: VPoser) -> set[str]:
    """Entries loaded when present but not required: BatchNorm's ``num_batches_tracked`` counters
    (unused in eval mode; absent from checkpoints written by older torch versions)."""
    return {k for k in model.state_dict() if k.endswith("num_batches_tracked")}


@dataclass
class CheckpointReport:
    """What :func:`load_vposer_checkpoint` did."""

    file: Path
    format: str  # "official-lightning" or "project"
    chosen_because: str
    loaded: list[str] = field(default_factory=list)
    ignored: list[str] = field(default_factory=list)
    config: dict = field(default_factory=dict)


def resolve_checkpoint(path: str | Path) -> tuple[Path, str]:
    """A checkpoint file from a file path or a ``V02_05`` folder; returns (file, why this file).

    A folder is searched for ``snapshots/*.ckpt`` (or ``*.ckpt`` directly inside it) and the file
    with the highest ``epoch=NN`` in its name is taken (the official loader takes the newest by
    modification time, which depends on how the zip was extracted).
    """
    p = Path(path).expanduser()
    if p.is_file():
        return p, "file given"
    if not p.exists():
        raise FileNotFoundError(f"VPoser weights not found: {p} does not exist. {WHERE_TO_GET}")
    candidates = sorted((p / "snapshots").glob("*.ckpt")) or sorted(p.glob("*.ckpt"))
    if not candidates:
        raise FileNotFoundError(
            f"no VPoser checkpoint in folder {p}: expected {p}/snapshots/*.ckpt (layout V02_05/V02_05.yaml, "
            f"V02_05/snapshots/V02_05_epoch=13_val_loss=0.03.ckpt). {WHERE_TO_GET}"
        )
    epochs = {}
    for c in candidates:
        m = re.search(r"epoch=(\d+)", c.name)
        if m is None:
            raise ValueError(
                f"cannot choose a VPoser checkpoint in {c.parent}: {c.name} has no 'epoch=NN' in its name "
                f"(found {[x.name for x in candidates]}); pass the .ckpt file itself"
            )
        epochs[c] = int(m.group(1))
    best = max(candidates, key=lambda c: (epochs[c], c.name))
    why = f"highest epoch ({epochs[best]}) among {[c.name for c in candidates]} in {best.parent}"
    return best, why


class _Stub:
    """Stands in for a pickled class that cannot be imported (e.g. OmegaConf in Lightning's hparams)."""

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state):
        self.__dict__["_state"] = state


class _TolerantUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        try:
            return super().find_class(module, name)
        except (ImportError, AttributeError):
            return type(name, (_Stub,), {"__module__": module})


_tolerant_pickle = types.SimpleNamespace(
    Unpickler=_TolerantUnpickler,
    load=lambda f, **kw: _TolerantUnpickler(f, **kw).load(),
    __name__="tolerant_pickle",
)


def _torch_load(file: Path) -> object:
    """torch.load on CPU: weights_only first; a Lightning checkpoint that pickles other objects
    (hyper-parameters) is then read with a full unpickler that stubs classes it cannot import."""
    try:
        return torch.load(file, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        log.warning(
            "%s: not loadable with weights_only=True (%s); reading it with the full unpickler "
            "(only its state_dict tensors are used)", file, str(exc).splitlines()[0]
        )
        return torch.load(file, map_location="cpu", weights_only=False, pickle_module=_tolerant_pickle)


def read_state_dict(file: Path, model: VPoser) -> tuple[dict[str, torch.Tensor], list[str], str]:
    """Map a checkpoint's tensors onto ``model``'s keys, strictly.

    Accepts the official Lightning checkpoint (``ckpt["state_dict"]``, keys ``vp_model.*``) and the
    project's file (``{"state_dict": {...unprefixed...}, "config": {...}}``). Returns
    (mapped state dict, sorted ignored keys, format). Every required key must be present with the
    model's shape; anything else is ignored and listed.
    """
    ckpt = _torch_load(file)
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt or not isinstance(ckpt["state_dict"], dict):
        top = sorted(ckpt)[:20] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(
            f"{file}: not a VPoser checkpoint: expected a dict with a 'state_dict' entry (Lightning .ckpt or "
            f"priors/weights/vposer.pt), found {top}"
        )
    raw = ckpt["state_dict"]
    official = any(k.startswith(OFFICIAL_PREFIX) for k in raw)
    prefix = OFFICIAL_PREFIX if official else ""
    fmt = "official-lightning" if official else "project"
    expected = expected_keys(model)
    optional = optional_keys(model)
    mapped, used = {}, set()
    for key, shape in expected.items():
        src = prefix + key
        if src not in raw:
            if key in optional:
                continue
            raise KeyError(
                f"{file}: missing key {src!r} (expected shape {shape}); the VPoser V02_05 checkpoint must hold all of "
                f"{sorted(prefix + k for k in expected if k not in optional)}"
            )
        t = raw[src]
        if not torch.is_tensor(t) or tuple(t.shape) != shape:
            found = tuple(t.shape) if torch.is_tensor(t) else type(t).__name__
            raise ValueError(
                f"{file}: key {src!r} has shape {found}, expected {shape} for VPoser(hidden={model.hidden}, "
                f"latent={model.latent}); is this the right size (paper: hidden 512, latent 32)?"
            )
        mapped[key] = t
        used.add(src)
    ignored = sorted(k for k in raw if k not in used)
    ignored += sorted(f"<top level>/{k}" for k in ckpt if k != "state_dict" and not (fmt == "project" and k == "config"))
    return mapped, ignored, fmt


def load_vposer_checkpoint(path: str | Path, model: VPoser) -> CheckpointReport:
    """Load a VPoser checkpoint (file, or ``V02_05`` folder) into ``model`` strictly; see
    :func:`read_state_dict`. Logs and returns which file was chosen and what was ignored."""
    file, why = resolve_checkpoint(path)
    mapped, ignored, fmt = read_state_dict(file, model)
    model.load_state_dict(mapped, strict=False)  # every required key is checked above
    log.info("VPoser weights: %s (%s, %s); %d tensors loaded, ignored: %s", file, fmt, why, len(mapped), ignored or "nothing")
    return CheckpointReport(file=file, format=fmt, chosen_because=why, loaded=sorted(mapped), ignored=ignored, config=model.config)


def read_project_config(file: str | Path) -> dict:
    """The ``config`` entry ({"hidden", "latent"}) of a project checkpoint (priors/weights/vposer.pt)."""
    if Path(file).is_dir() or Path(file).suffix == ".ckpt":
        raise ValueError(
            f"{file} looks like the official VPoser release (a V02_05 folder or a .ckpt): load it with "
            "size='paper'; size 'embedded' reads priors/weights/vposer.pt"
        )
    ckpt = torch.load(file, map_location="cpu", weights_only=True)
    cfg = ckpt.get("config") if isinstance(ckpt, dict) else None
    if not isinstance(cfg, dict) or not {"hidden", "latent"} <= set(cfg):
        raise ValueError(f"{file}: field 'config' with 'hidden' and 'latent' is missing; retrain with priors.vposer.train_vposer")
    return {"hidden": int(cfg["hidden"]), "latent": int(cfg["latent"])}


# -- the adapter -----------------------------------------------------------------------------
class VPoserSlerp(PriorAdapter):
    """VPoser+SLERP: one VPoser latent per observed frame; the protocol SLERPs between them.

    Latents: ``{"z": (B, n_observed, L)}``, initialised by a random sample of N(0, I) (paper 000
    section 5.5). ``decode`` gives joints 1..21 from the VPoser decoder and an identity root (the
    protocol owns root orientation and translation). Prior term: mean over the sequence's codes of
    ``|z|^2``. The network is frozen and always in eval mode.
    """

    name = "vposer-slerp"
    paper = "Pavlakos et al. 2019 (VPoser V02_05) + SLERP, as in Marsot et al. 2022 §5.5"
    window = WindowSpec(kind="per-frame")
    encodes_translation = False
    encodes_root_orientation = False
    joints = tuple(range(1, NUM_JOINTS))
    sixd_layout = "interleaved"
    has_encoder = True

    def __init__(self, size: str = "embedded", weights: str | None = None, device: str | torch.device = "cpu"):
        super().__init__(size=size, weights=weights, device=device)
        if size == "paper":
            if weights is None:
                raise ValueError(f"vposer-slerp size 'paper' needs the official weights. {WHERE_TO_GET}")
            self.vposer = VPoser(**PAPER_CONFIG)
            self.checkpoint = load_vposer_checkpoint(weights, self.vposer)
        elif size == "embedded":
            path = Path(weights) if weights is not None else DEFAULT_WEIGHTS
            if not path.exists():
                raise FileNotFoundError(
                    f"embedded VPoser weights not found: {path}. Train them with "
                    "`python -c \"from priors.vposer import train_vposer; train_vposer('priors/weights')\"` "
                    "(or `python -m benchmark train vposer-slerp`), or use size='paper' with the official V02_05."
                )
            self.vposer = VPoser(**read_project_config(path))
            self.checkpoint = load_vposer_checkpoint(path, self.vposer)
        else:
            raise ValueError(f"vposer-slerp: unknown size {size!r}; expected 'embedded' or 'paper'")
        self.weights_path = str(self.checkpoint.file)
        for p in self.vposer.parameters():
            p.requires_grad_(False)
        self.to(device)
        self.vposer.eval()

    @property
    def latent_dim(self) -> int:
        return self.vposer.latent

    @property
    def device(self) -> torch.device:
        return next(self.vposer.parameters()).device

    def train(self, mode: bool = True):
        """The prior is frozen: its network stays in eval mode (no dropout, BatchNorm running stats)."""
        super().train(mode)
        self.vposer.eval()
        return self

    def init_latents(self, batch: FitBatch, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """``{"z": (B, n_observed, L)}`` drawn from N(0, I) with ``generator`` (on its device)."""
        shape = (batch.batch_size, batch.num_observed, self.latent_dim)
        z = torch.randn(shape, generator=generator, device=generator.device, dtype=torch.float32)
        return {"z": z.to(self.device)}

    def decode(self, latents: dict[str, torch.Tensor], timestamps: torch.Tensor, shape: torch.Tensor | None = None) -> Decoded:
        """z (B, n, L) at their own timestamps (B, n) -> rotations (B, n, 22, 3, 3), root identity."""
        z = latents["z"]
        if z.dim() != 3 or z.shape[-1] != self.latent_dim:
            raise ValueError(f"vposer-slerp: latents['z'] must be (B, n, {self.latent_dim}), got {tuple(z.shape)}")
        if tuple(timestamps.shape) != tuple(z.shape[:2]):
            raise ValueError(
                f"vposer-slerp is a per-frame prior: decode at the latents' own timestamps, shape {tuple(z.shape[:2])}, "
                f"got timestamps {tuple(timestamps.shape)}; the protocol interpolates to other timestamps"
            )
        B, n, L = z.shape
        body = self.vposer.decode(z.reshape(B * n, L)).reshape(B, n, NUM_BODY_JOINTS, 3, 3)
        root = torch.eye(3, dtype=body.dtype, device=body.device).expand(B, n, 1, 3, 3)
        return Decoded(rotations=torch.cat([root, body], dim=2))

    @classmethod
    def train_embedded(cls, out_dir=None, steps=None, seed: int = 0, overwrite: bool = False) -> dict:
        """``python -m benchmark train vposer-slerp``: retrain the embedded weights (see train_vposer)."""
        out = Path(out_dir) if out_dir is not None else DEFAULT_WEIGHTS.parent
        target = out / DEFAULT_WEIGHTS.name
        if target.exists() and not overwrite:
            raise FileExistsError(f"{target} exists: pass --force to overwrite it, or --out DIR to write elsewhere")
        _, record = train_vposer(out, seed=seed, **({"steps": int(steps)} if steps else {}))
        return record

    def prior_term(self, latents: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B,) mean over the sequence's latent codes of |z|^2 (sum over the L dims)."""
        return latents["z"].square().sum(-1).mean(-1)

    @classmethod
    def paper_network(cls) -> VPoser:
        """The paper-size VPoser V02_05 (hidden 512, latent 32: 936,252 parameters) with random
        weights, in eval mode: ``python -m benchmark describe vposer-slerp --size paper`` prints its
        architecture and parameter counts without the (gated) official checkpoint."""
        return VPoser(**PAPER_CONFIG).eval()

    def encode_motion(self, rotations: torch.Tensor, trans: torch.Tensor, timestamps: torch.Tensor) -> dict[str, torch.Tensor]:
        """Posterior means of every frame: rotations (B, T, 22, 3, 3) -> ``{"z": (B, T, L)}``.

        VPoser encodes one pose at a time, so the latents are per frame and ``decode(latents,
        timestamps)`` at the same timestamps gives the per-frame reconstruction (joints 1..21; the
        root comes back as identity). Only joints 1..21 are encoded: the root orientation (joint
        0) and ``trans`` are not part of this prior (``encodes_root_orientation`` and
        ``encodes_translation`` are False), so the protocol supplies them. ``trans`` and
        ``timestamps`` are only checked for shape. Deterministic (the encoder mean, eval mode), no
        gradient.
        """
        if rotations.dim() != 5 or rotations.shape[-3:] != (NUM_JOINTS, 3, 3):
            raise ValueError(
                f"vposer-slerp.encode_motion: rotations must be (B, T, {NUM_JOINTS}, 3, 3) local rotations, "
                f"got {tuple(rotations.shape)}"
            )
        B, T = rotations.shape[:2]
        if tuple(timestamps.shape) != (B, T):
            raise ValueError(f"vposer-slerp.encode_motion: timestamps must be (B, T) = {(B, T)}, got {tuple(timestamps.shape)}")
        if trans is not None and tuple(trans.shape) != (B, T, 3):
            raise ValueError(f"vposer-slerp.encode_motion: trans must be (B, T, 3) = {(B, T, 3)}, got {tuple(trans.shape)}")
        return {"z": self.encode_poses(rotations[:, :, 1:])}

    def export_decoder(self) -> ExportSpec:
        """ONNX export of the decoder: input ``z`` (B, L) -> output ``rotations`` (B, 22, 3, 3).

        One latent per pose (the prior is per-frame; a (B, T, L) sequence is flattened to B*T
        poses). The output has all 22 SMPL joints, in the same convention as ``decode``: joint 0 is
        the identity (the protocol owns the root orientation), joints 1..21 are the VPoser decoder's
        local rotations. Example batch: 2 latents drawn from N(0, I) with seed 0.
        """
        module = _VPoserDecoderExport(self.vposer).eval()
        g = torch.Generator().manual_seed(0)
        z = torch.randn(2, self.latent_dim, generator=g).to(self.device)
        return ExportSpec(module=module, example_inputs=(z,), input_names=["z"], output_names=["rotations"])

    @torch.no_grad()
    def encode_poses(self, rotmats: torch.Tensor) -> torch.Tensor:
        """(..., 21, 3, 3) local rotations of joints 1..21 -> (..., L) the encoder's mean."""
        if rotmats.shape[-3:] != (NUM_BODY_JOINTS, 3, 3):
            raise ValueError(f"encode_poses expects (..., 21, 3, 3) rotations of joints 1..21, got {tuple(rotmats.shape)}")
        lead = rotmats.shape[:-3]
        aa = roma.rotmat_to_rotvec(rotmats.reshape(-1, NUM_BODY_JOINTS, 3, 3).to(self.device, torch.float32))
        return self.vposer.encode(aa).mean.reshape(*lead, self.latent_dim)


class _VPoserDecoderExport(nn.Module):
    """The traceable decode path of :meth:`VPoserSlerp.export_decoder`: z (B, L) -> (B, 22, 3, 3)
    with an identity root.

    Same numbers as ``VPoserSlerp.decode``, written so that the batch dimension stays symbolic in a
    trace: the 6D -> matrix step is the Gram-Schmidt of ``roma.special_gramschmidt`` (interleaved
    layout, epsilon 0) restated with ``reshape(-1, ...)``, because roma's own batch flattening
    records the example's batch size as a constant (an export at batch 2 then fails at batch 5).
    """

    def __init__(self, vposer: VPoser):
        super().__init__()
        self.mlp = vposer.decoder_net[:-1]  # every layer but ContinousRotReprDecoder (shared weights)
        self.register_buffer("eye", torch.eye(3), persistent=False)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        m = self.mlp(z).reshape(-1, NUM_BODY_JOINTS, 3, 2)  # interleaved: row-major 3x2, columns a1, a2
        a1, a2 = m[..., 0], m[..., 1]
        b1 = a1 / torch.linalg.vector_norm(a1, dim=-1, keepdim=True)
        a2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
        b2 = a2 / torch.linalg.vector_norm(a2, dim=-1, keepdim=True)
        b3 = torch.cross(b1, b2, dim=-1)
        body = torch.stack((b1, b2, b3), dim=-1)  # (B, 21, 3, 3), columns b1 b2 b3
        root = torch.zeros_like(body[:, :1]) + self.eye.to(body.dtype)
        return torch.cat([root, body], dim=1)


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
) -> tuple[VPoser, dict]:
    """Train a VPoser on body poses and write ``vposer.pt`` + ``vposer.json`` into ``out_dir``.

    poses / val_poses: (N, 22, 3) or (N, 21, 3) axis-angle; by default every ``frame_every``-th
    frame of the synthetic "train" split (at most ``max_frames``) and of the "val" split (if it
    builds). ``out_dir=None`` writes nothing (tests). Returns (trained model in eval mode, record).
    """
    from priors import training

    data_info: dict = {}
    if poses is None:
        motions = training.load_split_motions("train")
        poses = training.pose_frames(motions, every=frame_every, max_frames=max_frames, seed=seed)
        data_info["train"] = {"source": "benchmark.synthetic.splits.build_split('train')", "motions": len(motions),
                              "frame_every": frame_every, "frames": int(poses.shape[0])}
        if val_poses is None:
            try:
                val_motions = training.load_split_motions("val")
                val_poses = training.pose_frames(val_motions, every=frame_every, max_frames=max_frames // 10, seed=seed)
                data_info["val"] = {"source": "benchmark.synthetic.splits.build_split('val')", "motions": len(val_motions),
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
        "prior": VPoserSlerp.name,
        "network": "VPoser V02_05 architecture (priors/vposer.py VPoser)",
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
    """``python -m priors.vposer --out priors/weights --steps 15000 --seed 0``: train the embedded weights."""
    import argparse

    ap = argparse.ArgumentParser(description="Train the embedded VPoser on the synthetic training split.")
    ap.add_argument("--out", default=str(DEFAULT_WEIGHTS.parent), help="output folder (default: %(default)s)")
    ap.add_argument("--steps", type=int, default=15000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--hidden", type=int, default=EMBEDDED_CONFIG["hidden"])
    ap.add_argument("--latent", type=int, default=EMBEDDED_CONFIG["latent"])
    ap.add_argument("--batch-size", type=int, default=256)
    ap.add_argument("--frame-every", type=int, default=2)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    _, rec = train_vposer(args.out, steps=args.steps, seed=args.seed, hidden=args.hidden, latent=args.latent,
                          batch_size=args.batch_size, frame_every=args.frame_every)
    print({k: rec[k] for k in ("train_wall_s", "final_train", "final_val", "checkpoint_bytes")})


__all__ = [
    "VPoser",
    "NormalDistDecoder",
    "ContinousRotReprDecoder",
    "CheckpointReport",
    "resolve_checkpoint",
    "read_state_dict",
    "load_vposer_checkpoint",
    "read_project_config",
    "VPoserSlerp",
    "vposer_loss",
    "train_vposer",
    "PAPER_CONFIG",
    "EMBEDDED_CONFIG",
]


if __name__ == "__main__":
    main()
