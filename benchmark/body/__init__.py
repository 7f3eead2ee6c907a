"""Body models: the embedded Anny body and SMPL-family files, behind one interface.

``get_body(spec)`` resolves a body spec:
    "anny"                          the embedded default (Anny, re-rigged to SMPL-22)
    "smpl", "smplh", "smplx"        SMPL-family files found by the resolver (flag, env, user dir)
    "smpl=/path/to/file_or_root"    an explicit file or root folder (also with :male / :female)
"""

from __future__ import annotations

from benchmark.body.base import BodyModel, BodyOutput, RestState

BODY_KINDS = {
    "anny": "embedded: Anny (PyPI anny, CC0 assets), cmu_mb rig re-rigged to SMPL-22, 6 phenotype shape parameters",
    "smpl": "user file: SMPL (.pkl/.npz), 24 joints; <root>/smpl/SMPL_{NEUTRAL,MALE,FEMALE}.pkl",
    "smplh": "user file: SMPL-H; <root>/smplh/{neutral,male,female}/model.npz (AMASS) or <root>/smplh/SMPLH_*.pkl",
    "smplx": "user file: SMPL-X; <root>/smplx/SMPLX_{NEUTRAL,MALE,FEMALE}.npz",
}


def parse_body_spec(spec: str) -> tuple[str, str | None, str | None]:
    """'smplh=/models:female' -> ('smplh', '/models', 'female'); no ``:gender``: None (the neutral
    model, or the gender a model file's name or folder says)."""
    kind, _, rest = spec.partition("=")
    kind = kind.strip().lower()
    gender = None
    path = rest or None
    if path and ":" in path.rsplit("/", 1)[-1]:
        path, _, gender = path.rpartition(":")
    if kind not in BODY_KINDS:
        import difflib

        close = difflib.get_close_matches(kind, BODY_KINDS, n=1)
        hint = f" Did you mean {close[0]!r}?" if close else ""
        raise ValueError(f"unknown body model {kind!r}.{hint} Known: {', '.join(BODY_KINDS)}")
    return kind, path, gender


def get_body(spec: str = "anny", device="cpu", num_betas: int = 10) -> BodyModel:
    kind, path, gender = parse_body_spec(spec)
    if kind == "anny":
        if path:
            raise ValueError("the embedded 'anny' body takes no path")
        from benchmark.body.anny_body import load_anny_body

        return load_anny_body(device)
    from benchmark.body.resolve import load_body

    return load_body(kind, gender=gender, path=path, num_betas=num_betas, device=device)


__all__ = ["BodyModel", "BodyOutput", "RestState", "get_body", "parse_body_spec", "BODY_KINDS"]
