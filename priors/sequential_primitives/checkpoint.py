"""Sequential latent primitives: the project checkpoint format (strict reader and loader).

Official weights are not public (``NOT_PUBLIC``); a loader for them would have to map their keys onto
``OFFICIAL_MAPPING_NEEDS``.
"""

from __future__ import annotations

from pathlib import Path

import torch

from benchmark.safe_loading import UnsafeFileError, torch_load_weights
from priors.sequential_primitives.model import ARCH_KEYS, FORMAT, SequentialPrimitives


DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "sequential_primitives.pt"

NOT_PUBLIC = (
    "the official sequential-primitives code (gitlab.inria.fr/mmarsot/new_segmentation, research-only licence) and "
    "any official weights are not public/reachable from this project, so their checkpoint format is unknown"
)
OFFICIAL_MAPPING_NEEDS = (
    "motion_encoder.embed (Linear 123 -> d_model: per-frame perceptron on [20 joints 6D, gamma]), "
    "motion_encoder.core.encoder / .core.decoder / .core.queries (transformer over frames, m query tokens), "
    "motion_encoder.head (d_model -> 2D: mu, logvar), "
    "decoder.seg_mlp (time-independent MLP [z, beta] -> duration logit, yaw (cos, sin), t_x, t_z), "
    "decoder.in_z / decoder.in_t / decoder.body (time-dependent MLP [z, beta, f(tau - Delta)] -> 20x6D + gamma), "
    "decoder.trans_center / decoder.trans_scale (translation normalisation, metres), "
    "point_encoder.pointnet.mlp / .pointnet.out / .core / .head (initialisation encoder)"
)


# -- checkpoints --------------------------------------------------------------------------------
def read_checkpoint(file: str | Path) -> dict:
    """The project checkpoint ``{"state_dict", "config"}``; clear errors for anything else."""
    file = Path(file)
    if not file.exists():
        raise FileNotFoundError(f"sequential-primitives weights not found: {file}")
    try:
        ckpt = torch_load_weights(file, "retrain with `python -m benchmark train sequential-primitives`")
    except UnsafeFileError:
        raise
    except Exception as exc:
        raise ValueError(
            f"{file}: not readable as a sequential-primitives project checkpoint ({type(exc).__name__}: "
            f"{str(exc).splitlines()[0] if str(exc) else ''}); {NOT_PUBLIC}. A loader for official weights would "
            f"have to map their keys onto: {OFFICIAL_MAPPING_NEEDS}"
        ) from exc
    cfg = ckpt.get("config") if isinstance(ckpt, dict) else None
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), dict) or not isinstance(cfg, dict) \
            or cfg.get("format") != FORMAT:
        found = sorted(ckpt)[:20] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(
            f"{file}: not a sequential-primitives project checkpoint (expected a dict with 'state_dict' and a "
            f"'config' whose 'format' is {FORMAT!r}; found top-level {found}). {NOT_PUBLIC}: pass a checkpoint "
            "written by priors.sequential_primitives.train.train_sequential_primitives, or write a key mapping from the "
            f"official files onto: {OFFICIAL_MAPPING_NEEDS}"
        )
    missing = [k for k in ARCH_KEYS if k not in cfg]
    if missing:
        raise ValueError(f"{file}: field 'config' lacks {missing}; retrain with train_sequential_primitives")
    return ckpt


def load_into(net: SequentialPrimitives, ckpt: dict, file: str | Path) -> None:
    """Strict load: every key with the network's shape; extra keys are an error too."""
    sd = ckpt["state_dict"]
    expected = net.state_dict()
    for k, v in expected.items():
        if k not in sd:
            raise KeyError(f"{file}: missing key {k!r} (shape {tuple(v.shape)}); the checkpoint must hold all "
                           f"{len(expected)} entries of SequentialPrimitives")
        if tuple(sd[k].shape) != tuple(v.shape):
            raise ValueError(f"{file}: key {k!r} has shape {tuple(sd[k].shape)}, expected {tuple(v.shape)} for config "
                             f"{ {a: net.cfg[a] for a in ('latent', 'd_model', 'mlp_hidden', 'shape_dim')} }")
    extra = sorted(set(sd) - set(expected))
    if extra:
        raise KeyError(f"{file}: unexpected keys {extra[:10]} (not SequentialPrimitives entries)")
    net.load_state_dict(sd, strict=True)


def network_from_checkpoint(file: str | Path) -> SequentialPrimitives:
    ckpt = read_checkpoint(file)
    net = SequentialPrimitives(**{k: ckpt["config"][k] for k in ARCH_KEYS})
    load_into(net, ckpt, file)
    return net
