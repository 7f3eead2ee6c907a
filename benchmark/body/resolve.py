"""Find SMPL / SMPL-H / SMPL-X model files on disk (they are licensed: the user downloads them).

Resolution order:

1. the explicit ``path`` (a command-line flag): a model file, or a root folder. When given, it is
   the only place looked at: a typo must not silently load another model from somewhere else.
2. the roots in the environment variable ``BENCHMARK_BODY_MODELS`` (``os.pathsep``-separated);
3. the user data directory ``$XDG_DATA_HOME/motion-benchmark/body_models``
   (``~/.local/share/motion-benchmark/body_models`` when ``XDG_DATA_HOME`` is unset).

Layouts accepted under each root (the smplx layout, and AMASS's for SMPL-H); the root may also be
the model-type folder itself (``<root>`` = ``.../smpl``):

    <root>/smpl/SMPL_NEUTRAL.pkl    SMPL_MALE.pkl    SMPL_FEMALE.pkl     (or .npz)
    <root>/smplh/SMPLH_NEUTRAL.pkl  SMPLH_MALE.pkl   SMPLH_FEMALE.pkl    (or .npz)
    <root>/smplh/neutral/model.npz  male/model.npz   female/model.npz    (AMASS)
    <root>/smplx/SMPLX_NEUTRAL.npz  SMPLX_MALE.npz   SMPLX_FEMALE.npz    (or .pkl)
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

ENV_VAR = "BENCHMARK_BODY_MODELS"
MODEL_KINDS = ("smpl", "smplh", "smplx")
GENDERS = ("neutral", "male", "female")
_EXTENSIONS = {"smpl": (".pkl", ".npz"), "smplh": (".pkl", ".npz"), "smplx": (".npz", ".pkl")}
EXPECTED_LAYOUT = """\
  <root>/smpl/SMPL_NEUTRAL.pkl    SMPL_MALE.pkl    SMPL_FEMALE.pkl     (or .npz)
  <root>/smplh/SMPLH_NEUTRAL.pkl  SMPLH_MALE.pkl   SMPLH_FEMALE.pkl    (or .npz)
  <root>/smplh/neutral/model.npz  male/model.npz   female/model.npz    (AMASS layout)
  <root>/smplx/SMPLX_NEUTRAL.npz  SMPLX_MALE.npz   SMPLX_FEMALE.npz    (or .pkl)
  (<root> may also be the model folder itself, e.g. <root>/SMPL_NEUTRAL.pkl)"""


def user_data_dir() -> Path:
    """``$XDG_DATA_HOME/motion-benchmark/body_models`` or ``~/.local/share/motion-benchmark/body_models``."""
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "motion-benchmark" / "body_models"


def _check(kind: str, gender: str) -> tuple[str, str]:
    kind, gender = kind.lower(), gender.lower()
    if kind not in MODEL_KINDS:
        raise ValueError(f"unknown body-model kind {kind!r}; choose one of {MODEL_KINDS}")
    if gender not in GENDERS:
        raise ValueError(f"unknown gender {gender!r}; choose one of {GENDERS}")
    return kind, gender


def candidate_files(root: str | Path, kind: str, gender: str = "neutral") -> list[Path]:
    """The files looked for under one root, in order (see the module docstring)."""
    kind, gender = _check(kind, gender)
    root = Path(root).expanduser()
    stem = f"{kind.upper()}_{gender.upper()}"
    out = []
    for folder in (root / kind, root):
        out += [folder / (stem + ext) for ext in _EXTENSIONS[kind]]
        out.append(folder / gender / "model.npz")
    return out


def candidate_roots(path: str | Path | None = None) -> list[tuple[str, Path]]:
    """(origin, root) pairs in resolution order; origin names where the root came from."""
    if path is not None:
        return [("path argument", Path(path).expanduser())]
    roots = [(f"${ENV_VAR}", Path(p).expanduser()) for p in os.environ.get(ENV_VAR, "").split(os.pathsep) if p]
    roots.append(("user data directory", user_data_dir()))
    return roots


def resolve_body_model_file(kind: str, gender: str = "neutral", path: str | Path | None = None) -> Path:
    """The model file for ``kind`` ('smpl' | 'smplh' | 'smplx') and ``gender``.

    ``path`` may be the file itself or a root folder. Raises FileNotFoundError listing every path
    tried and the expected layouts.
    """
    kind, gender = _check(kind, gender)
    tried: list[tuple[str, Path]] = []
    for origin, root in candidate_roots(path):
        if origin == "path argument" and not root.is_dir():
            if root.is_file():
                return root
            tried.append((origin, root))
            continue
        for candidate in candidate_files(root, kind, gender):
            if candidate.is_file():
                return candidate
            tried.append((origin, candidate))
    lines = "\n".join(f"  [{origin}] {p}" for origin, p in tried)
    note = (
        "  (an explicit path was given, so $BENCHMARK_BODY_MODELS and the user data directory were not searched)\n"
        if path is not None
        else ""
    )
    raise FileNotFoundError(
        f"no {kind.upper()} model file for gender {gender!r} was found. Paths tried, in order:\n{lines}\n{note}"
        f"Expected layout under a root folder:\n{EXPECTED_LAYOUT}\n"
        f"Fix: pass the file or root folder explicitly, set {ENV_VAR}=<root>, or place the files under "
        f"{user_data_dir()}. The model files are licensed: download them from smpl.is.tue.mpg.de (SMPL), "
        f"mano.is.tue.mpg.de (SMPL-H) or smpl-x.is.tue.mpg.de (SMPL-X)."
    )


def file_gender(file: str | Path) -> str | None:
    """The gender a body-model file's name or folder says (``SMPL_MALE.pkl``, ``SMPLH_female.pkl``,
    AMASS's ``male/model.npz``), or None."""
    p = Path(file)
    for word in (p.stem.lower().replace("-", "_").split("_")[-1], p.parent.name.lower()):
        if word in ("male", "female", "neutral"):
            return word
    return None


def load_body(
    kind: str,
    gender: str | None = None,
    path: str | Path | None = None,
    num_betas: int = 10,
    device: str | torch.device | None = None,
    dtype: torch.dtype = torch.float32,
):
    """Resolve, read and build an :class:`~benchmark.body.smpl.SMPLBody`.

    ``gender`` None: the neutral model, or for a file the gender its name or folder says
    (:func:`file_gender`; the body is named for it). Raises ValueError if the file found holds
    another model type than ``kind``, or its name says another gender than the one asked for.
    """
    from benchmark.body.smpl import SMPLBody
    from benchmark.body.smpl_files import read_body_model_file

    asked = gender
    kind, gender = _check(kind, gender or "neutral")
    file = resolve_body_model_file(kind, gender, path)
    said = file_gender(file)
    if said is not None and asked is not None and said != gender:
        raise ValueError(f"{file}: its name says the {said} model, but the body asked for is {kind}:{gender}; "
                         f"point to the {gender} file, or drop ':{gender}'")
    gender = said or gender  # a file named for its gender names the body (smplh=.../male/model.npz -> smplh-male)
    data = read_body_model_file(file)
    if data.model_type != kind:
        raise ValueError(
            f"{file}: asked for a {kind!r} model but the file holds {data.model_type!r} "
            f"({data.num_joints} joints); point to a {kind.upper()} file or ask for kind={data.model_type!r}"
        )
    body = SMPLBody(data, num_betas=num_betas, name=f"{kind}-{gender}", dtype=dtype)
    return body.to(device) if device is not None else body
