"""Motion-DVAE checkpoints, read by :func:`load` (``load(path, size) -> (MotionDVAE, CheckpointReport)``):
the project format and the official one (:func:`load_official`, with a key map), both strict
(:func:`priors.checkpoints.load_state_strict`)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import torch

from benchmark.core.safe_loading import STATE_DICT_FIX, UnsafeFileError, torch_load_weights
from priors.checkpoints import CheckpointReport, check_size, load_state_strict
from priors.motion_dvae.model import MotionDVAE, PAPER_CONFIG
from priors.motion_dvae.states import FPS


DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "motion_dvae.pt"
TRAIN_COMMAND = "python -m benchmark train motion-dvae"

OFFICIAL_UNKNOWN = (
    "the official Motion-DVAE checkpoint format is unknown (the repository, presumably "
    "github.com/g-fiche/Motion-DVAE, could not be read when this adapter was written)"
)


# -- checkpoints -----------------------------------------------------------------------------
def _read_project(path: Path) -> tuple[dict, dict]:
    """(state_dict, config) of a project checkpoint ``priors/weights/motion_dvae.pt``, strictly checked."""
    ckpt = torch_load_weights(path, f"retrain with `{TRAIN_COMMAND}`")
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), dict) or not isinstance(ckpt.get("config"), dict):
        top = sorted(ckpt)[:20] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(f"{path}: not a motion-dvae project checkpoint: expected {{'state_dict', 'config'}}, found {top}; "
                         f"retrain with `{TRAIN_COMMAND}`")
    cfg = ckpt["config"]
    missing = {"z_dim", "hidden", "mlp_hidden"} - set(cfg)
    if missing:
        raise ValueError(f"{path}: field 'config' lacks {sorted(missing)}; retrain with `{TRAIN_COMMAND}`")
    return ckpt["state_dict"], {"z_dim": int(cfg["z_dim"]), "hidden": int(cfg["hidden"]),
                                "mlp_hidden": int(cfg["mlp_hidden"]), "fps": float(cfg.get("fps", FPS)),
                                "feedback": bool(cfg.get("feedback", False)),
                                "encoder_residual": bool(cfg.get("encoder_residual", False))}


def _load_strict(model: MotionDVAE, state_dict: dict, source) -> list[str]:
    """Every key present with the model's shape, no extra key (:func:`priors.checkpoints.load_state_strict`)."""
    loaded, _ = load_state_strict(model, state_dict, source, "motion-dvae",
                                  note=f"config {model.config}; expected module names: {expected_modules()}")
    return loaded


def expected_modules() -> list[str]:
    return ["gen_rnn (nn.LSTM)", "prior_mean.net", "prior_logvar.net", "decoder.net", "encoder.{bwd_rnn,fwd_cell,post_mean,post_logvar}",
            "denoise_encoder.{...same as encoder}", "init_state.{bwd_rnn,mean,logvar}", "noise.head",
            "buffers state_mean, state_std, x0_mean, rest_joints"]


def load_official(path: str | Path, model: MotionDVAE | None = None,
                  key_map: dict | Callable[[str], str | None] | None = None) -> tuple[MotionDVAE, CheckpointReport]:
    """The official Motion-DVAE weights, whose format is unknown (what ``load(path, "paper")`` reads).

    Reads ``path`` (a torch file: a state dict, or a dict with ``state_dict`` / ``model``), renames
    its keys with ``key_map`` (a dict official-name -> our name, or a function returning our name
    or None to drop the key) and loads them strictly into ``model`` (default: the paper-size
    :class:`MotionDVAE`). Without a ``key_map`` the file's keys must already be ours. When the keys
    do not match, raises NotImplementedError naming what is unknown and what is expected: our module
    names are ``gen_rnn`` (the LSTM shared by prior and decoder, input [z_t, x^_0], hidden 1024),
    ``prior_mean``/``prior_logvar``/``decoder`` (HuMoR-style MLPs), ``encoder`` (``bwd_rnn``
    anti-causal LSTM over states, ``fwd_cell`` forward recurrence over z, ``post_mean`` /
    ``post_logvar``), ``denoise_encoder``, ``init_state`` and ``noise``; plus the buffers
    ``state_mean``/``state_std`` (data standardisation), ``x0_mean`` and ``rest_joints``, which
    an official file would not hold (set them from the official normalisation statistics / the
    SMPL-H neutral joints). The official wiring may also differ from ours (it is inferred).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"motion-dvae official weights: {path} does not exist ({OFFICIAL_UNKNOWN})")
    try:
        raw = torch_load_weights(path, STATE_DICT_FIX)
    except UnsafeFileError:
        raise
    except Exception as exc:
        raise NotImplementedError(f"{path}: cannot read it as a torch weights file ({type(exc).__name__}: {exc}); "
                                  f"{OFFICIAL_UNKNOWN}") from exc
    model = model if model is not None else MotionDVAE(**PAPER_CONFIG)
    sd = raw
    if isinstance(raw, dict):
        for key in ("state_dict", "model", "model_state_dict"):
            if isinstance(raw.get(key), dict):
                sd = raw[key]
                break
    if not isinstance(sd, dict) or not all(torch.is_tensor(v) for v in sd.values()):
        raise NotImplementedError(f"{path}: no tensor state dict found (top level {type(raw).__name__}); {OFFICIAL_UNKNOWN}")
    if key_map is not None:
        mapper = key_map.get if isinstance(key_map, dict) else key_map
        sd = {mapper(k): v for k, v in sd.items() if mapper(k) is not None}
    expected = model.state_dict()
    if set(sd) != set(expected):
        found = sorted(sd)[:8]
        raise NotImplementedError(
            f"{path}: its keys (e.g. {found}, {len(sd)} in all) do not match this implementation's "
            f"({len(expected)} tensors; modules {expected_modules()}): {OFFICIAL_UNKNOWN}. Write a key map "
            "(official name -> ours) and call priors.motion_dvae.checkpoint.load_official(path, key_map=...), checking "
            "the wiring in this module's docstring against the official code."
        )
    loaded = _load_strict(model, sd, path)
    return model, CheckpointReport(file=path, format="official", config=dict(model.config), loaded=loaded)


def load(path: str | Path, size: str = "embedded", key_map: dict | Callable[[str], str | None] | None = None
         ) -> tuple[MotionDVAE, CheckpointReport]:
    """The Motion-DVAE network of a checkpoint, strictly loaded, and what was read.

    size "embedded": the project's file (``priors/weights/motion_dvae.pt``) at the size its config
    says; size "paper": an official file through :func:`load_official` (its keys mapped by ``key_map``).
    """
    check_size("motion-dvae", size)
    if size == "paper":
        return load_official(path, key_map=key_map)
    path = Path(path)
    sd, cfg = _read_project(path)
    model = MotionDVAE(**cfg)
    loaded = _load_strict(model, sd, path)
    return model, CheckpointReport(file=path, format="project", config=cfg, loaded=loaded)
