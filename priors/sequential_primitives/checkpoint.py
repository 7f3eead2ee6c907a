"""Sequential latent primitives: the project checkpoint format, read strictly by :func:`load`
(``load(path, size) -> (SequentialPrimitives, CheckpointReport)``).

Official weights are not public (``NOT_PUBLIC``); a loader for them would have to map their keys onto
``OFFICIAL_MAPPING_NEEDS``.
"""

from __future__ import annotations

from pathlib import Path

from benchmark.core.safe_loading import UnsafeFileError, torch_load_weights
from priors.checkpoints import CheckpointReport, check_size, load_state_strict
from priors.sequential_primitives.model import ARCH_KEYS, FORMAT, PAPER_CONFIG, SequentialPrimitives


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
def _read(file: Path) -> dict:
    """The project checkpoint ``{"state_dict", "config"}``; clear errors for anything else."""
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


def load(path: str | Path, size: str = "embedded") -> tuple[SequentialPrimitives, CheckpointReport]:
    """The network of a project checkpoint, strictly loaded, and what was read.

    Official weights are not public, so both sizes read this project's format; size "paper" also
    requires the paper architecture (``PAPER_CONFIG``) in the file's config.
    """
    check_size("sequential-primitives", size)
    file = Path(path)
    ckpt = _read(file)
    arch = {k: ckpt["config"][k] for k in ARCH_KEYS}
    if size == "paper":
        diff = {k: (arch[k], PAPER_CONFIG[k]) for k in ARCH_KEYS
                if (list(arch[k]) if isinstance(arch[k], (list, tuple)) else arch[k]) != PAPER_CONFIG[k]}
        if diff:
            raise ValueError(f"{path}: not a paper-size checkpoint; config differs (found, paper): {diff}")
    net = SequentialPrimitives(**arch)
    loaded, _ = load_state_strict(net, ckpt["state_dict"], path, "SequentialPrimitives",
                                  note=f"config { {a: net.cfg[a] for a in ('latent', 'd_model', 'mlp_hidden', 'shape_dim')} }")
    return net, CheckpointReport(file=file, format="project", config=dict(ckpt["config"]), loaded=loaded)
