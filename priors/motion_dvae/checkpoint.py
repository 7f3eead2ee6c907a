"""Motion-DVAE checkpoints: the project format (strict) and the official one (strict, with a key map)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import torch

from benchmark.safe_loading import STATE_DICT_FIX, UnsafeFileError, torch_load_weights
from priors.motion_dvae.model import FPS, MotionDVAE, PAPER_CONFIG


DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "motion_dvae.pt"
TRAIN_COMMAND = "python -m benchmark train motion-dvae"

OFFICIAL_UNKNOWN = (
    "the official Motion-DVAE checkpoint format is unknown (the repository, presumably "
    "github.com/g-fiche/Motion-DVAE, could not be read when this adapter was written)"
)


# -- checkpoints -----------------------------------------------------------------------------
def read_project_checkpoint(path: str | Path) -> tuple[dict, dict]:
    """(state_dict, config) of a project checkpoint ``priors/weights/motion_dvae.pt``, strictly checked."""
    path = Path(path)
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


def load_state_strict(model: MotionDVAE, state_dict: dict, source: str) -> None:
    """Copy ``state_dict`` into ``model``: every key present with the model's shape, no extra key."""
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state_dict))
    if missing:
        raise KeyError(f"{source}: missing {len(missing)} key(s), e.g. {missing[:5]}; a motion-dvae checkpoint holds "
                       f"{len(expected)} tensors (module names: {expected_modules()})")
    extra = sorted(set(state_dict) - set(expected))
    if extra:
        raise KeyError(f"{source}: unexpected key(s) {extra[:5]} (total {len(extra)}); expected module names: {expected_modules()}")
    for k, v in expected.items():
        t = state_dict[k]
        if not torch.is_tensor(t) or tuple(t.shape) != tuple(v.shape):
            found = tuple(t.shape) if torch.is_tensor(t) else type(t).__name__
            raise ValueError(f"{source}: key {k!r} has shape {found}, expected {tuple(v.shape)} for config {model.config}")
    model.load_state_dict(state_dict, strict=True)


def expected_modules() -> list[str]:
    return ["gen_rnn (nn.LSTM)", "prior_mean.net", "prior_logvar.net", "decoder.net", "encoder.{bwd_rnn,fwd_cell,post_mean,post_logvar}",
            "denoise_encoder.{...same as encoder}", "init_state.{bwd_rnn,mean,logvar}", "noise.head",
            "buffers state_mean, state_std, x0_mean, rest_joints"]


def load_official(path: str | Path, model: MotionDVAE | None = None,
                  key_map: dict | Callable[[str], str | None] | None = None) -> MotionDVAE:
    """Hook for the official Motion-DVAE weights, whose format is unknown.

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
    model = model if model is not None else MotionDVAE(**PAPER_CONFIG)
    try:
        raw = torch_load_weights(path, STATE_DICT_FIX)
    except UnsafeFileError:
        raise
    except Exception as exc:
        raise NotImplementedError(f"{path}: cannot read it as a torch weights file ({type(exc).__name__}: {exc}); "
                                  f"{OFFICIAL_UNKNOWN}") from exc
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
    load_state_strict(model, sd, str(path))
    return model
