"""Captured point-cloud sequences from a folder of per-frame files.

Layout::

    <folder>/
        frame_0001.ply       one file per frame: .ply / .obj (read through trimesh) or .npz
        frame_0002.ply       (key ``points``, an (N, 3) array); formats may be mixed
        ...
        timestamps.txt       optional: one time in seconds per frame (whitespace separated,
                             '#' comments), or timestamps.npy, an (T,) array in seconds

Frames are ordered by natural sort of their file names (``frame_2`` before ``frame_10``).
Timestamps come, in this order of precedence, from the ``timestamps`` argument, a timestamps
file in the folder, or ``fps`` (frame i at i / fps seconds).

Meshes (a PLY/OBJ with faces) contribute their vertices as the frame's points, unless ``sample``
is given: then ``sample`` points are drawn uniformly over each mesh's surface area
(:func:`benchmark.observations.sample_surface`). Point clouds always contribute their points.
Units are taken as they are in the files: the project expects metres, y up.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from benchmark.observations import PointCloudSequence, sample_surface

log = logging.getLogger(__name__)

FRAME_SUFFIXES = (".ply", ".obj", ".npz")
TIMESTAMP_FILES = ("timestamps.txt", "timestamps.npy")


def natural_key(name: str) -> tuple:
    """Sort key treating digit runs as numbers: 'f2' < 'f10'."""
    return tuple((0, int(part), part) if part.isdigit() else (1, 0, part.lower())
                 for part in re.split(r"(\d+)", name) if part)


def list_scan_frames(folder: str | Path) -> list[Path]:
    """The frame files of a scan folder, naturally sorted (error if there are none)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"scan folder {folder} does not exist or is not a directory")
    frames = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in FRAME_SUFFIXES]
    if not frames:
        raise FileNotFoundError(
            f"scan folder {folder}: no frames found; expected one file per frame with suffix "
            f"{', '.join(FRAME_SUFFIXES)} (e.g. frame_0001.ply)"
        )
    return sorted(frames, key=lambda p: natural_key(p.name))


def _check_points(path: Path, points: np.ndarray, what: str) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{path}: {what} must be an (N, 3) array, got shape {points.shape}")
    if points.shape[0] == 0:
        raise ValueError(f"{path}: the frame has no points; remove the file or re-export it")
    if not np.issubdtype(points.dtype, np.number) or not np.isfinite(points).all():
        raise ValueError(f"{path}: {what} holds non-numeric or non-finite values (NaN/inf); clean the file")
    return points.astype(np.float64, copy=False)


def read_scan_frame(path: str | Path, sample: int | None = None,
                    generator: torch.Generator | None = None) -> np.ndarray:
    """(N, 3) float64 points of one frame file (see the module docstring for the rules)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                keys = list(data.files)
                points = data["points"] if "points" in keys else None
        except Exception as exc:  # not a zip, pickled content, truncated file
            raise ValueError(
                f"{path}: unreadable npz file ({exc}); re-export it with np.savez(path, points=...)"
            ) from exc
        if points is None:
            raise ValueError(
                f"{path}: no 'points' array (found keys {sorted(keys)}); save the frame with "
                "np.savez(path, points=array_of_shape_N_3)"
            )
        if sample is not None:
            raise ValueError(
                f"{path}: sample={sample} applies to meshes, but an npz frame holds points only; drop sample"
            )
        return _check_points(path, points, "'points'")
    if suffix not in (".ply", ".obj"):
        raise ValueError(f"{path}: unsupported frame format {suffix!r}; use one of {', '.join(FRAME_SUFFIXES)}")

    import trimesh

    try:
        geometry = trimesh.load(path, process=False)
    except Exception as exc:
        raise ValueError(
            f"{path}: unreadable {suffix[1:].upper()} file ({exc}); re-export it as a valid mesh or point cloud"
        ) from exc
    if isinstance(geometry, trimesh.Scene):
        if len(geometry.geometry) == 0:
            raise ValueError(f"{path}: the file holds no geometry (no vertices); remove it or re-export it")
        geometry = geometry.dump(concatenate=True)
    vertices = getattr(geometry, "vertices", None)
    if vertices is None:
        raise ValueError(f"{path}: trimesh read a {type(geometry).__name__} without vertices; re-export the frame")
    vertices = _check_points(path, vertices, "the vertices")
    faces = np.asarray(getattr(geometry, "faces", np.zeros((0, 3))))
    if sample is None:
        return vertices
    if faces.size == 0:
        raise ValueError(f"{path}: sample={sample} needs a mesh with faces, but the file is a point cloud; drop sample")
    points = sample_surface(torch.from_numpy(vertices), torch.from_numpy(faces.astype(np.int64)), sample, generator)
    return points.numpy()


def read_timestamps(folder: str | Path) -> tuple[np.ndarray, Path] | None:
    """(T,) float64 seconds from the folder's timestamps file, or None if it has none."""
    folder = Path(folder)
    found = [folder / name for name in TIMESTAMP_FILES if (folder / name).is_file()]
    if not found:
        return None
    if len(found) > 1:
        raise ValueError(f"scan folder {folder}: both {found[0].name} and {found[1].name} are present; keep one")
    path = found[0]
    try:
        if path.suffix == ".npy":
            values = np.load(path, allow_pickle=False)
        else:
            values = np.loadtxt(path, dtype=np.float64, comments="#", ndmin=1)
    except Exception as exc:
        raise ValueError(f"{path}: unreadable timestamps ({exc}); write one time in seconds per frame") from exc
    return np.asarray(values, dtype=np.float64).reshape(-1), path


def load_scan_folder(
    folder: str | Path,
    timestamps: Sequence[float] | np.ndarray | torch.Tensor | None = None,
    fps: float | None = None,
    sample: int | None = None,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
) -> PointCloudSequence:
    """One captured sequence: a PointCloudSequence with B = 1 and T = the number of frame files.

    timestamps: (T,) seconds (overrides any timestamps file); fps: used when there is no
    timestamps argument or file. sample: points per mesh frame drawn over the surface (with a
    ``torch.Generator`` seeded by ``seed``, frame after frame); None uses the mesh vertices.
    Points are padded to the largest frame; ``lengths`` holds each frame's count.
    """
    folder = Path(folder)
    frames = list_scan_frames(folder)
    if sample is not None and sample < 1:
        raise ValueError(f"sample must be a positive number of points per frame, got {sample}")
    T = len(frames)

    source = "the timestamps argument"
    if timestamps is not None:
        ts = np.asarray(torch.as_tensor(timestamps, dtype=torch.float64).cpu(), dtype=np.float64).reshape(-1)
    else:
        from_file = read_timestamps(folder)
        if from_file is not None:
            ts, path = from_file
            source = path.name
            if fps is not None:
                log.warning("%s: using the timestamps file; fps=%s is ignored", folder, fps)
        elif fps is not None:
            if not fps > 0:
                raise ValueError(f"fps must be > 0, got {fps}")
            ts = np.arange(T, dtype=np.float64) / float(fps)
            source = f"fps={fps}"
        else:
            raise ValueError(
                f"scan folder {folder}: no timestamps; add {TIMESTAMP_FILES[0]} (one time in seconds per frame) "
                f"or {TIMESTAMP_FILES[1]} to the folder, or pass fps= (e.g. --fps 50)"
            )
    if ts.shape[0] != T:
        raise ValueError(
            f"scan folder {folder}: {source} gives {ts.shape[0]} timestamps for {T} frame files; "
            "give exactly one time per frame"
        )
    if not np.isfinite(ts).all() or (T > 1 and not (np.diff(ts) > 0).all()):
        raise ValueError(f"scan folder {folder}: timestamps from {source} must be finite and strictly increasing")

    generator = torch.Generator().manual_seed(seed) if sample is not None else None
    clouds = [read_scan_frame(path, sample, generator) for path in frames]
    counts = [c.shape[0] for c in clouds]
    points = torch.zeros(1, T, max(counts), 3, dtype=dtype)
    for t, cloud in enumerate(clouds):  # file IO is per frame anyway
        points[0, t, : cloud.shape[0]] = torch.from_numpy(cloud).to(dtype)
    return PointCloudSequence(
        points=points,
        lengths=torch.tensor([counts], dtype=torch.long),
        timestamps=torch.from_numpy(ts)[None],
    )
