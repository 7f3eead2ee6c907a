"""Loading HM-VAE checkpoints: the official trainer's files and the project's embedded weights.

**No official HM-VAE weights were ever published** (``lijiaman/hm-vae`` README and issue #1: the
scripts point to unpublished paths such as ``clean_outputs/.../gen_00250000.pt``). Size "paper"
therefore loads checkpoints that someone trained with the official code:

- Official VAE checkpoint, written by ``trainer_motion_vae.py save``: ``gen_XXXXXXXX.pt`` =
  ``{'state_dict': TwoHierSAVAEModel.state_dict()}`` saved with
  ``torch.save(..., _use_new_zipfile_serialization=False)`` (legacy format). Its keys are those of
  :class:`priors.hmvae.model.HMVAE` plus a full duplicate ``dec.enc.*`` of ``enc.*`` (the official
  decoder holds a reference to the encoder). The loader checks every ``dec.enc.*`` tensor equals its
  ``enc.*`` twin and drops them (they differ only if the file was edited: error), then loads
  strictly: every key present with the expected shape, no leftovers, and the frozen masks and
  pooling matrices equal to the ones rebuilt from the skeleton (a different skeleton or
  ``skeleton_dist`` is an error). ``latent_d`` / ``shallow_latent_d`` are read from the latent
  heads' shapes (the released training config says shallow 24, the test config 12); everything else
  must be the len-64 paper architecture.
- Official trajectory checkpoint (same trainer, ``configs/trajectory_model.yaml``): ``{'state_dict'}``
  with ``enc.layers.*`` and ``fc_mapping.*``. It also needs two files from the repository's
  ``utils/data/``: ``all_amass_data_mean_std.npy`` (2 x 579 standardisation statistics; dims
  360:432 joint positions, 576:579 root velocity) and ``skeleton_offsets.npy`` (24 x 3 FK offsets).

``weights`` for size "paper" (the ``--weights hmvae=...`` value):

- ``PATH`` : the VAE checkpoint file, or a folder holding ``gen.pt`` or ``gen_XXXXXXXX.pt`` files
  (the highest iteration is taken); for ``hmvae-trajectory`` the folder must also hold the
  trajectory model as ``traj.pt`` or ``trajectory/gen*.pt``, and the two ``.npy`` files (in the
  trajectory checkpoint's folder or in PATH);
- ``VAE,TRAJ`` : the two checkpoints (files or folders) separately; the ``.npy`` files are looked
  for beside TRAJ, then beside VAE.

Project checkpoints (``priors/weights/hmvae.pt``, ``hmvae_trajectory.pt``, written by
:mod:`priors.hmvae.train`): ``{"state_dict": learnable tensors only, "config": {...}}``; the frozen
masks and pooling matrices are omitted (rebuilt from the skeleton), the config holds the
architecture, ``world_up`` ("y") and, for the trajectory model, its statistics and FK skeleton.
"""

from __future__ import annotations

import logging
import pickle
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from benchmark.core.safe_loading import UnsafeFileError, is_lightning_bookkeeping, torch_load_with_stand_ins
from priors.checkpoints import CheckpointReport, check_size, load_state_strict
from priors.hmvae.model import PAPER_CONFIG, HMVAE, HMVAEConfig
from priors.hmvae.skeleton import PARENTS24, frozen_parameter_names
from priors.hmvae.trajectory import PAPER_TRAJECTORY_CONFIG, TrajectoryConfig, TrajectoryModel

log = logging.getLogger(__name__)

NO_RELEASE = (
    "HM-VAE has no published weights (lijiaman/hm-vae ships training code only); train the len-64 model "
    "with the official code (configs/len64_no_aug_hm_vae.yaml, which writes gen_XXXXXXXX.pt) and pass that file, "
    "or use size='embedded' (python -m benchmark train hmvae)"
)
MEAN_STD_FILE = "all_amass_data_mean_std.npy"
OFFSETS_FILE = "skeleton_offsets.npy"
POS_DIMS = slice(360, 432)
VEL_DIMS = slice(576, 579)


VAE_FILE = "hmvae.pt"
TRAJECTORY_FILE = "hmvae_trajectory.pt"
DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / VAE_FILE  # hmvae_trajectory.pt beside it
TRAIN_COMMAND = "python -m benchmark train hmvae  (or: python -m priors.hmvae.train --out priors/weights)"


# -- files -----------------------------------------------------------------------------------
def _iteration(p: Path) -> int:
    m = re.fullmatch(r"gen_(\d+)\.pt", p.name)
    return int(m.group(1)) if m else -1


def resolve_checkpoint_file(path: str | Path, what: str = "HM-VAE") -> Path:
    """A checkpoint file from a file or a folder (``gen.pt``, else the highest ``gen_XXXXXXXX.pt``)."""
    p = Path(path).expanduser()
    if p.is_file():
        return p
    if not p.exists():
        raise FileNotFoundError(f"{what} weights not found: {p} does not exist. {NO_RELEASE}")
    if (p / "gen.pt").is_file():
        return p / "gen.pt"
    cands = sorted(p.glob("gen_*.pt"), key=lambda c: (_iteration(c), c.name))
    if not cands:
        raise FileNotFoundError(
            f"no {what} checkpoint in folder {p}: expected {p}/gen.pt or {p}/gen_XXXXXXXX.pt (as written by the "
            f"official trainer_motion_vae.py). {NO_RELEASE}"
        )
    return cands[-1]


@dataclass
class PaperFiles:
    vae: Path
    trajectory: Path | None = None
    mean_std: Path | None = None
    offsets: Path | None = None


def resolve_paper_weights(spec: str | Path, need_trajectory: bool) -> PaperFiles:
    """The files of a size-"paper" ``weights`` value (module docstring: ``PATH`` or ``VAE,TRAJ``)."""
    if spec is None:
        raise ValueError(f"HM-VAE size 'paper' needs weights (a gen_XXXXXXXX.pt file or folder). {NO_RELEASE}")
    parts = [s.strip() for s in str(spec).split(",") if s.strip()]
    if len(parts) not in (1, 2):
        raise ValueError(f"HM-VAE weights {spec!r}: expected 'PATH' or 'VAE_CKPT,TRAJECTORY_CKPT'")
    vae = resolve_checkpoint_file(parts[0], "HM-VAE")
    files = PaperFiles(vae=vae)
    if not need_trajectory:
        return files
    if len(parts) == 2:
        traj = resolve_checkpoint_file(parts[1], "HM-VAE trajectory model")
    else:
        root = Path(parts[0]).expanduser()
        tried = [root / "traj.pt", root / "trajectory"]
        if not root.is_dir():
            raise ValueError(
                f"hmvae-trajectory weights {spec!r}: a single file holds only the VAE; pass 'VAE_CKPT,TRAJECTORY_CKPT' "
                f"or a folder with gen*.pt, traj.pt (or trajectory/gen*.pt), {MEAN_STD_FILE} and {OFFSETS_FILE}"
            )
        if tried[0].is_file():
            traj = tried[0]
        elif tried[1].is_dir():
            traj = resolve_checkpoint_file(tried[1], "HM-VAE trajectory model")
        else:
            raise FileNotFoundError(f"no trajectory checkpoint for hmvae-trajectory: tried {[str(t) for t in tried]}")
    files.trajectory = traj
    dirs = [traj.parent, vae.parent] + ([Path(parts[0]).expanduser()] if Path(parts[0]).expanduser().is_dir() else [])
    for attr, name in (("mean_std", MEAN_STD_FILE), ("offsets", OFFSETS_FILE)):
        found = next((d / name for d in dirs if (d / name).is_file()), None)
        if found is None:
            raise FileNotFoundError(
                f"hmvae-trajectory needs {name} from the official repository (lijiaman/hm-vae utils/data/"
                f"{'for_all_data_motion_model/' if name == MEAN_STD_FILE else ''}{name}); looked in {[str(d) for d in dirs]}"
            )
        setattr(files, attr, found)
    return files


def _torch_load(file: Path) -> object:
    try:
        # a Lightning checkpoint's bookkeeping (another prior's file) is read inert: the key checks then
        # say what the file is instead of calling it unsafe
        return torch_load_with_stand_ins(file, is_lightning_bookkeeping,
                                         "re-save the weights only: torch.save({'state_dict': model.state_dict()}, path)")[0]
    except UnsafeFileError:
        raise
    except pickle.UnpicklingError as exc:
        raise ValueError(
            f"{file}: cannot be read as a plain tensor checkpoint ({str(exc).splitlines()[0]}); expected "
            "{'state_dict': model.state_dict()} as written by the official trainer or by priors.hmvae.train"
        ) from exc
    except Exception as exc:
        raise ValueError(f"{file}: not a torch checkpoint ({type(exc).__name__}: {exc})") from exc


def _load_plain_array(file: Path) -> np.ndarray:
    """A numeric ``.npy`` array of the official release, read without pickle."""
    try:
        return np.load(file, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:  # object arrays (pickled), truncated or not an .npy
        raise ValueError(f"{file}: not a plain numeric .npy array, read without pickle ({exc}); use the file of "
                         "the official repository (lijiaman/hm-vae utils/data/)") from None


def _state_dict_of(ckpt: object, file: Path, what: str) -> dict:
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), dict):
        top = sorted(map(str, ckpt))[:20] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(
            f"{file}: not an {what} checkpoint: expected a dict with a 'state_dict' entry "
            f"({{'state_dict': model.state_dict()}} as saved by the official trainer), found {top}"
        )
    return ckpt["state_dict"]


# -- strict mapping --------------------------------------------------------------------------
def drop_duplicate_encoder(sd: dict, file: Path) -> tuple[dict, list[str]]:
    """Check the official duplicate ``dec.enc.*`` entries equal ``enc.*`` and drop them."""
    dup = sorted(k for k in sd if k.startswith("dec.enc."))
    for k in dup:
        twin = "enc." + k[len("dec.enc."):]
        if twin not in sd:
            raise KeyError(f"{file}: key {k!r} duplicates the encoder but {twin!r} is missing; the checkpoint is incomplete")
        a, b = sd[k], sd[twin]
        if not (torch.is_tensor(a) and torch.is_tensor(b) and a.shape == b.shape and torch.equal(a, b)):
            raise ValueError(
                f"{file}: key {k!r} differs from {twin!r}; in a checkpoint written by the official trainer the decoder's "
                "encoder reference is the encoder itself, so the two must be equal (was the file edited?)"
            )
    return {k: v for k, v in sd.items() if not k.startswith("dec.enc.")}, dup


FIXED_NOTE = ("a skeleton mask / pooling matrix is rebuilt from the 24-joint HM-VAE skeleton (skeleton_dist 2); "
              "the checkpoint uses another topology")


def _load_strict(model: nn.Module, sd: dict, file: Path, what: str, frozen_optional: bool = False) -> list[str]:
    """:func:`priors.checkpoints.load_state_strict` with HM-VAE's fixed tensors: every key, every
    shape, no leftovers, the frozen masks / pooling matrices equal to the model's (absent is
    allowed with ``frozen_optional``: project files). Returns the loaded keys."""
    frozen = frozen_parameter_names(model)
    loaded, _ = load_state_strict(
        model, sd, file, what, optional=frozen if frozen_optional else (), fixed=frozen, fixed_note=FIXED_NOTE,
        note=f"config {model.config}; is this the right model (VAE vs trajectory, len-64 vs len-8) and size?",
    )
    return loaded


def infer_vae_config(sd: dict, file: Path, world_up: str = "z") -> HMVAEConfig:
    """The paper len-64 config with the latent sizes read from the latent heads."""
    def shape(key):
        if key not in sd or not torch.is_tensor(sd[key]):
            raise KeyError(f"{file}: missing key {key!r}; not an HM-VAE (TwoHierSAVAEModel) checkpoint")
        return tuple(sd[key].shape)

    s0, s3 = shape("enc.latent_enc_layers.0.weight"), shape("enc.latent_enc_layers.3.weight")
    if s0[0] % 2 or s3[0] % 2:
        raise ValueError(f"{file}: latent heads have odd output sizes {s0}, {s3}; expected 2 * latent size")
    return HMVAEConfig(**{**PAPER_CONFIG.to_dict(), "shallow_latent_d": s0[0] // 2, "latent_d": s3[0] // 2, "world_up": world_up})


def _official_vae(path: str | Path) -> tuple[HMVAE, CheckpointReport]:
    """An official ``gen_XXXXXXXX.pt`` (file or folder) -> HMVAE (z-up world), strictly."""
    file = resolve_checkpoint_file(path, "HM-VAE")
    sd = _state_dict_of(_torch_load(file), file, "HM-VAE")
    sd, dropped = drop_duplicate_encoder(sd, file)
    cfg = infer_vae_config(sd, file, world_up="z")
    model = HMVAE(cfg)
    loaded = _load_strict(model, sd, file, "HM-VAE len-64 model")
    log.info("HM-VAE official weights %s: %d tensors, dropped %d duplicate dec.enc.* keys", file, len(loaded), len(dropped))
    return model, CheckpointReport(file=file, format="official-legacy", config=cfg.to_dict(), loaded=loaded, ignored=dropped)


def _official_trajectory(files: PaperFiles) -> tuple[TrajectoryModel, CheckpointReport]:
    """The official trajectory checkpoint + mean/std + skeleton offsets -> TrajectoryModel (z-up)."""
    file = files.trajectory
    sd = _state_dict_of(_torch_load(file), file, "HM-VAE trajectory")
    model = TrajectoryModel(TrajectoryConfig(**{**PAPER_TRAJECTORY_CONFIG.to_dict(), "world_up": "z"}))
    loaded = _load_strict(model, sd, file, "HM-VAE trajectory model")
    ms = _load_plain_array(files.mean_std)
    if ms.ndim != 2 or ms.shape[0] != 2 or ms.shape[1] < VEL_DIMS.stop:
        raise ValueError(f"{files.mean_std}: expected the official (2, 579) mean/std array, got shape {ms.shape}")
    off = _load_plain_array(files.offsets)
    if off.shape != (len(PARENTS24), 3):
        raise ValueError(f"{files.offsets}: expected (24, 3) skeleton offsets, got shape {off.shape}")
    rest = np.zeros_like(off)
    for j, p in enumerate(PARENTS24):  # parent-relative offsets -> rest positions (root at its offset)
        rest[j] = off[j] if p < 0 else rest[p] + off[j]
    model.set_statistics(ms[0, POS_DIMS], ms[1, POS_DIMS], ms[0, VEL_DIMS], ms[1, VEL_DIMS], rest)
    return model, CheckpointReport(file=file, format="official-legacy", config=model.config.to_dict(), loaded=loaded)


# -- project files ---------------------------------------------------------------------------
def learnable_state_dict(model: nn.Module) -> dict:
    """The state dict without the frozen masks / pooling matrices (what project files store)."""
    frozen = frozen_parameter_names(model)
    return {k: v for k, v in model.state_dict().items() if k not in frozen}


def _project_payload(path: Path, kind: str) -> tuple[dict, dict]:
    if Path(path).is_dir() or not Path(path).exists():
        raise FileNotFoundError(f"{path}: not a file")
    ckpt = _torch_load(Path(path))
    sd = _state_dict_of(ckpt, Path(path), kind)
    cfg = ckpt.get("config")
    if not isinstance(cfg, dict) or "model" not in cfg:
        raise ValueError(
            f"{path}: field 'config' with the {kind} architecture ('model') is missing; this looks like an official "
            "checkpoint (load it with size='paper') or a file from another prior; retrain with "
            "`python -m benchmark train hmvae`"
        )
    return sd, cfg


def _project_vae(path: str | Path) -> tuple[HMVAE, CheckpointReport]:
    path = Path(path)
    sd, cfg = _project_payload(path, "HM-VAE")
    if cfg.get("kind") != "hmvae":
        raise ValueError(f"{path}: config.kind is {cfg.get('kind')!r}, expected 'hmvae' (is this the trajectory file?)")
    model = HMVAE(HMVAEConfig.from_dict(cfg["model"]))
    loaded = _load_strict(model, sd, path, "HM-VAE", frozen_optional=True)
    return model, CheckpointReport(file=path, format="project", config=cfg, loaded=loaded)


def _project_trajectory(path: str | Path) -> tuple[TrajectoryModel, CheckpointReport]:
    path = Path(path)
    sd, cfg = _project_payload(path, "HM-VAE trajectory")
    if cfg.get("kind") != "hmvae-trajectory":
        raise ValueError(f"{path}: config.kind is {cfg.get('kind')!r}, expected 'hmvae-trajectory'")
    model = TrajectoryModel(TrajectoryConfig.from_dict(cfg["model"]))
    loaded = _load_strict(model, sd, path, "HM-VAE trajectory model", frozen_optional=True)
    st = cfg.get("statistics")
    if not isinstance(st, dict):
        raise ValueError(f"{path}: config.statistics (standardisation and FK skeleton) is missing; retrain the trajectory model")
    model.set_statistics(st["pos_mean"], st["pos_std"], st["vel_mean"], st["vel_std"], st["rest_joints"])
    return model, CheckpointReport(file=path, format="project", config=cfg, loaded=loaded)


def resolve_embedded_files(path: str | Path, trajectory: bool) -> tuple[Path, Path]:
    """(VAE file, trajectory file) of a size-"embedded" ``weights`` value: a file (the trajectory
    model beside it as hmvae_trajectory.pt), ``VAE,TRAJ``, or a folder holding hmvae.pt and
    hmvae_trajectory.pt. The trajectory file must exist only when ``trajectory``."""
    parts = [s.strip() for s in str(path).split(",") if s.strip()]
    first = Path(parts[0]).expanduser()
    if first.is_dir():
        vae_file, traj_file = first / VAE_FILE, first / TRAJECTORY_FILE
    else:
        vae_file = first
        traj_file = Path(parts[1]).expanduser() if len(parts) > 1 else first.parent / TRAJECTORY_FILE
    needed = [vae_file] + ([traj_file] if trajectory else [])
    missing = [str(p) for p in needed if not p.is_file()]
    if missing and vae_file.is_file() and len(parts) == 1 and not first.is_dir():
        raise FileNotFoundError(
            f"{first}: hmvae-trajectory needs two files, the VAE and the trajectory model, and "
            f"{traj_file} is not beside it; pass `VAE.pt,TRAJECTORY.pt` or a folder holding {VAE_FILE} and "
            f"{TRAJECTORY_FILE}")
    if missing:
        raise FileNotFoundError(
            f"embedded HM-VAE weights not found: {missing}. Train them with `{TRAIN_COMMAND}` "
            "(writes hmvae.pt and hmvae_trajectory.pt), or use size='paper' with a checkpoint of the official trainer"
        )
    return vae_file, traj_file


def load(path: str | Path, size: str = "embedded", trajectory: bool = False) -> tuple[nn.Module, CheckpointReport]:
    """The HM-VAE network(s) of a checkpoint, strictly loaded, and what was read.

    size "paper": checkpoints written by the official trainer (module docstring: ``PATH`` or
    ``VAE,TRAJ``); size "embedded": the project's files (:func:`resolve_embedded_files`). Returns the
    :class:`~priors.hmvae.model.HMVAE`, or with ``trajectory`` an ``nn.ModuleDict`` of ``"vae"`` and
    ``"trajectory"`` (a :class:`~priors.hmvae.trajectory.TrajectoryModel`). The report's ``parts``
    hold the report of each network.
    """
    check_size("hmvae", size)
    traj = rt = None
    if size == "paper":
        files = resolve_paper_weights(path, need_trajectory=trajectory)
        vae, rv = _official_vae(files.vae)
        if trajectory:
            traj, rt = _official_trajectory(files)
    else:
        vae_file, traj_file = resolve_embedded_files(path, trajectory)
        vae, rv = _project_vae(vae_file)
        if trajectory:
            traj, rt = _project_trajectory(traj_file)
    parts = {"vae": rv, **({"trajectory": rt} if rt is not None else {})}
    report = CheckpointReport(
        file=rv.file, files=[r.file for r in parts.values()], format=rv.format, config=rv.config, parts=parts,
        loaded=[f"{name}.{k}" for name, r in parts.items() for k in r.loaded],
        ignored=[f"{name}.{k}" for name, r in parts.items() for k in r.ignored],
    )
    return (vae if traj is None else nn.ModuleDict({"vae": vae, "trajectory": traj})), report


def save_official_format(path: str | Path, state_dict: dict) -> Path:
    """Write ``{'state_dict': ...}`` exactly as the official trainer does (legacy serialisation)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": state_dict}, path, _use_new_zipfile_serialization=False)
    return path


__all__ = [
    "NO_RELEASE",
    "VAE_FILE",
    "TRAJECTORY_FILE",
    "DEFAULT_WEIGHTS",
    "PaperFiles",
    "resolve_checkpoint_file",
    "resolve_paper_weights",
    "resolve_embedded_files",
    "drop_duplicate_encoder",
    "infer_vae_config",
    "learnable_state_dict",
    "load",
    "save_official_format",
]
