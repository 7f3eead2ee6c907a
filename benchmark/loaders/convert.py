"""Convert a motion file (AMASS ``.npz``, BVH, or a harness ``.npz``) to the harness ``.npz``.

The CLI ``python -m benchmark data convert INPUT --out OUT.npz [--fps 30] [--force]`` calls
:func:`convert`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmark.core.motion import Motion, shape_for_body
from benchmark.core.safe_loading import npz_read_error


def detect_format(path) -> str:
    """'bvh', 'amass' or 'harness' from the extension and, for .npz, the keys; errors say why."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".bvh":
        return "bvh"
    if suffix != ".npz":
        raise ValueError(f"{path}: unsupported input format {suffix!r}; expected .bvh, an AMASS .npz or a harness .npz")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    if path.name.endswith("_shape.npz"):
        return "amass"  # the AMASS loader explains that shape files carry no motion
    try:
        with np.load(path, allow_pickle=False) as z:
            keys = set(z.files)
            pose_shape = z["poses"].shape if "poses" in keys else None
    except Exception as e:
        raise ValueError(f"{path}: not a readable .npz file without pickle ({npz_read_error(path, e)})") from e
    if keys & {"mocap_framerate", "mocap_frame_rate"}:
        return "amass"
    if pose_shape is not None and len(pose_shape) == 3 and ("timestamps" in keys or "fps" in keys):
        return "harness"
    if "betas" in keys and pose_shape is None:
        return "amass"
    raise ValueError(
        f"{path}: cannot tell the format from keys {sorted(keys)}: an AMASS file has 'poses' and "
        "'mocap_framerate' / 'mocap_frame_rate'; a harness file has 'poses' (T, 22, 3) and 'timestamps'"
    )


def load_motion(path, fps: float | None = None) -> Motion:
    """Load any supported motion file as a Motion (optionally resampled to ``fps``)."""
    fmt = detect_format(path)
    if fmt == "bvh":
        from benchmark.loaders.bvh import load_bvh

        return load_bvh(path, fps=fps)
    if fmt == "amass":
        from benchmark.loaders.amass import load_amass

        return load_amass(path, fps=fps)
    motion = Motion.load(path)
    return motion.resample_fps(fps) if fps is not None else motion


def convert(input_path, out_path, fps: float | None = None, overwrite: bool = False, body=None) -> Motion:
    """Read ``input_path`` (format detected), optionally resample to ``fps``, write the harness
    ``.npz`` at ``out_path`` with :meth:`Motion.save`, and return the Motion.

    body: a body model (:func:`benchmark.body.get_body`): the motion's shape is stored for it (SMPL
        betas cut or zero-padded to its shape count, another body's shape dropped); a shape whose
        length cannot be the body's is an error (:func:`benchmark.core.plausibility.check_shape`).

    Every loader checks what it reads (:mod:`benchmark.core.plausibility`): time units, translation
    scale; the error names the input file, the field and the fix.

    Refuses to replace an existing ``out_path`` unless ``overwrite=True`` (CLI: ``--force``). The
    output folder is checked (creatable, writable) before the input is read.
    """
    out_path = Path(out_path)
    if out_path.suffix.lower() != ".npz":
        raise ValueError(f"{out_path}: the output is a harness motion .npz; give a path ending in .npz")
    if out_path.is_dir():
        raise ValueError(f"--out {out_path}: is a folder; give the output file, e.g. {out_path / 'motion.npz'}")
    if out_path.exists() and not overwrite:
        raise FileExistsError(
            f"{out_path} already exists; refusing to overwrite it. Pass overwrite=True (CLI: --force) "
            "or choose another --out path"
        )
    if Path(input_path).resolve() == out_path.resolve():
        raise ValueError(f"{out_path}: output would replace the input file; choose another --out path")
    detect_format(input_path)  # a wrong format is reported before the output folder is checked
    if not Path(input_path).is_file():
        raise FileNotFoundError(f"{input_path}: no such file")
    from benchmark.core.outdir import check_out_dir

    check_out_dir(out_path.parent if str(out_path.parent) else Path("."), min_free_bytes=1 << 20,
                  what="the folder of --out")
    motion = load_motion(input_path, fps=fps)
    if body is not None:
        motion = shape_for_body(motion, body, str(input_path))
    motion.save(out_path)
    return motion
