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
(:func:`benchmark.core.surface_sampling.sample_surface`). Point clouds always contribute their points.
Units are taken as they are in the files: the project expects metres, y up.

Plausibility (:mod:`benchmark.core.plausibility`, thresholds there): timestamps must give 1-1,000 fps
over at most an hour (millisecond timestamps are refused, naming the fix); every frame needs at
least 3 points and coordinates within 1 km of the origin. :class:`ScanSequence` (what ``run
table1 --data scans=DIR`` and ``complete DIR`` read) checks every frame file when it is built, so a
bad frame is an error before any work unit starts; a PLY whose header declares more vertices than
the file holds (a truncated ASCII PLY) is an error too.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from benchmark.data.observations import PointCloudSequence
from benchmark.core.plausibility import (check_scan_coordinates, check_scan_frame_size, check_scan_points,
                                    check_timestamps)
from benchmark.core.safe_loading import npz_read_error
from benchmark.core.surface_sampling import sample_surface

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
    # hidden files (macOS's ._frame_0001.ply metadata twins, editors' .swp) are never frames
    frames = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in FRAME_SUFFIXES
              and not p.name.startswith(".")]
    if not frames:
        raise FileNotFoundError(
            f"scan folder {folder}: no frames found; expected one file per frame with suffix "
            f"{', '.join(FRAME_SUFFIXES)} (e.g. frame_0001.ply)"
        )
    return sorted(frames, key=lambda p: natural_key(p.name))


def _not_frames(folder: Path) -> str:
    """``"; not frames: a.npy, b.txt"``: the folder's other visible files (the timestamps file aside),
    for a message about a frame count; empty when there are none."""
    other = sorted(p.name for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")
                   and p.suffix.lower() not in FRAME_SUFFIXES and p.name not in TIMESTAMP_FILES)
    return f"; not frames (a frame is {', '.join(FRAME_SUFFIXES)}): {', '.join(other[:5])}" if other else ""


def _check_points(path: Path, points: np.ndarray, what: str) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{path}: {what} must be an (N, 3) array, got shape {points.shape}")
    if points.shape[0] == 0:
        raise ValueError(f"{path}: the frame has no points; remove the file or re-export it")
    if not np.issubdtype(points.dtype, np.number) or not np.isfinite(points).all():
        raise ValueError(f"{path}: {what}: non-numeric or non-finite values (NaN/inf); clean the file (drop those "
                         "points) or re-export it")
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
                f"{path}: unreadable npz file ({npz_read_error(path, exc)}); re-export it with np.savez(path, points=...)"
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
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: the file is empty (0 bytes); re-export the frame, or remove the file and its "
                         "timestamp")

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
    declared = _ply_vertex_count(path) if suffix == ".ply" else None
    if declared is not None and declared != vertices.shape[0]:
        raise ValueError(
            f"{path}: the PLY header declares {declared} vertices but the file holds {vertices.shape[0]}; the file is "
            "truncated or damaged: re-export it"
        )
    faces = np.asarray(getattr(geometry, "faces", np.zeros((0, 3))))
    if sample is None:
        return vertices
    if faces.size == 0:
        raise ValueError(f"{path}: sample={sample} needs a mesh with faces, but the file is a point cloud; drop sample")
    points = sample_surface(torch.from_numpy(vertices), torch.from_numpy(faces.astype(np.int64)), sample, generator)
    return points.numpy()


def _ply_vertex_count(path: Path) -> int | None:
    """The vertex count a PLY header declares (``element vertex N``), or None if it has none."""
    with open(path, "rb") as f:
        head = f.read(65536)
    end = head.find(b"end_header")
    if end < 0:
        return None
    m = re.search(rb"^element\s+vertex\s+(\d+)\s*$", head[:end], re.MULTILINE)
    return int(m.group(1)) if m else None


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
        values = np.asarray(values, dtype=np.float64).reshape(-1)
    except Exception as exc:
        raise ValueError(f"{path}: unreadable timestamps ({exc}); write one time in seconds per frame") from exc
    return values, path


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
                f"or {TIMESTAMP_FILES[1]} to the folder, or pass fps= (e.g. fps=50)"
            )
    if ts.shape[0] != T:
        raise ValueError(
            f"scan folder {folder}: {source} gives {ts.shape[0]} timestamps for {T} frame files; "
            f"give exactly one time per frame{_not_frames(Path(folder))}"
        )
    if not np.isfinite(ts).all() or (T > 1 and not (np.diff(ts) > 0).all()):
        raise ValueError(f"scan folder {folder}: timestamps from {source} must be finite and strictly increasing")
    check_timestamps(ts, f"scan folder {folder}", field=source.replace("the ", "", 1))

    generator = torch.Generator().manual_seed(seed) if sample is not None else None
    clouds = [read_scan_frame(path, sample, generator) for path in frames]
    for path, cloud in zip(frames, clouds):
        check_scan_points(cloud, str(path))
    counts = [c.shape[0] for c in clouds]
    points = torch.zeros(1, T, max(counts), 3, dtype=dtype)
    for t, cloud in enumerate(clouds):  # file IO is per frame anyway
        points[0, t, : cloud.shape[0]] = torch.from_numpy(cloud).to(dtype)
    return PointCloudSequence(
        points=points,
        lengths=torch.tensor([counts], dtype=torch.long),
        timestamps=torch.from_numpy(ts)[None],
    )


# ----------------------------------------------------------------------------------------------
# Conventions (--up, --units), sanity checks, and scan roots (one folder per sequence)
# ----------------------------------------------------------------------------------------------
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
UP_AXES = ("y", "z")
# A standing adult is 1.4-2.1 m tall; a frame whose extent along the up axis, in metres after
# the unit conversion, lies outside this range is almost surely in other units (error), unless
# the subject is crouching or lying (the error says how to tell).
PLAUSIBLE_HEIGHT_M = (0.3, 3.0)
# z-up -> y-up, the same fixed rotation as the AMASS loader: (x, y, z) -> (x, z, -y).
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
# A timestamp interval more than this many times the median interval is reported as a gap.
GAP_FACTOR = 1.5


def to_harness_frame(points: np.ndarray, up: str = "y", units: str = "m") -> np.ndarray:
    """(N, 3) points in the capture's convention -> metres, y up."""
    if units not in UNITS:
        raise ValueError(f"units must be one of {', '.join(UNITS)}, got {units!r}")
    if up not in UP_AXES:
        raise ValueError(f"up axis must be one of {', '.join(UP_AXES)}, got {up!r}")
    out = np.asarray(points, dtype=np.float64) * UNITS[units]
    if up == "z":
        out = out @ Z_UP_TO_Y_UP.T
    return out


def check_units(points_m: np.ndarray, path: Path, up: str, units: str, warn: bool = True) -> list[str]:
    """Error naming ``path`` when a frame (already converted to metres, y up) cannot be a person
    in these units; a warning when its extent says the up axis is probably another one (logged
    when ``warn``; returned either way)."""
    lo, hi = points_m.min(0), points_m.max(0)
    extent = hi - lo
    height = float(extent[1])
    if not PLAUSIBLE_HEIGHT_M[0] <= height <= PLAUSIBLE_HEIGHT_M[1]:
        raw = height / UNITS[units]
        guess = [u for u, f in UNITS.items() if 1.0 <= raw * f <= 2.2 and u != units]
        hint = (f"the numbers look like {guess[0]}: pass --units {guess[0]}" if guess
                else "check the units (--units m|cm|mm) and the up axis (--up y|z)")
        raise ValueError(
            f"{path}: the body is {raw:,.4g} units tall along the up axis ({up}); read as {units} that is "
            f"{height:.4g} m, not a person's height ({PLAUSIBLE_HEIGHT_M[0]}-{PLAUSIBLE_HEIGHT_M[1]} m); {hint}"
        )
    horizontal = max(float(extent[0]), float(extent[2]))
    out = []
    if height < 0.6 * horizontal:
        other = "z" if up == "y" else "y"
        out.append(f"{path}: the body is {height:.2f} m tall along the up axis ({up}) but {horizontal:.2f} m wide: is "
                   f"the capture {other}-up? (pass --up {other}; ignore this for a lying or crouching subject)")
    if warn:
        for message in out:
            log.warning("%s", message)
    return out


def check_timestamp_gaps(ts: np.ndarray, where: str) -> None:
    """Warn about gaps (an interval over GAP_FACTOR x the median), naming the source."""
    if ts.shape[0] < 3:
        return
    dt = np.diff(ts)
    med = float(np.median(dt))
    gaps = np.nonzero(dt > GAP_FACTOR * med)[0]
    if gaps.size:
        log.warning("%s: %d gap(s) in the timestamps (the largest %.4f s after frame %d, median interval %.4f s); "
                    "table1 leaves out a sequence with a gap over 2.5 x the median in its window; across a smaller "
                    "one ground truth and observed frames use the nearest capture frame", where, gaps.size, float(dt[gaps].max()),
                    int(gaps[np.argmax(dt[gaps])]), med)


class ScanSequence:
    """One captured sequence folder: the frame list and timestamps at construction, the points on
    demand (:meth:`read_frames`). Units and up axis are converted on reading.

    check: read and check every frame file now (:meth:`validate`), so that a bad frame is an error
    before any work starts (False: only the timestamps are checked; frames on reading).
    rate_flag: the command-line flag that gives a capture rate to a folder without timestamps, named
    in that error (``complete``: ``--capture-fps``; None: the fix is a timestamps file).
    """

    def __init__(self, folder: str | Path, up: str = "y", units: str = "m", fps: float | None = None,
                 check: bool = True, rate_flag: str | None = None):
        self.folder = Path(folder)
        self.up, self.units = up, units
        to_harness_frame(np.zeros((1, 3)), up, units)  # validates both
        self.frames = list_scan_frames(self.folder)
        found = read_timestamps(self.folder)
        if found is not None:
            ts, path = found
            source = str(path)
        elif fps is not None:
            if not fps > 0:
                raise ValueError(f"fps must be > 0, got {fps}")
            ts, source = np.arange(len(self.frames), dtype=np.float64) / float(fps), f"fps={fps}"
        else:
            rate = f", or give the capture rate with {rate_flag} (e.g. {rate_flag} 50)" if rate_flag else ""
            raise ValueError(
                f"scan folder {self.folder}: no timestamps; add {self.folder / TIMESTAMP_FILES[0]} with one time in "
                f"seconds per frame, in frame order (a 50 fps capture: 0.00, 0.02, 0.04, ...), or "
                f"{TIMESTAMP_FILES[1]}{rate}"
            )
        if ts.shape[0] != len(self.frames):
            raise ValueError(
                f"{source}: {ts.shape[0]} timestamps for {len(self.frames)} frame files in {self.folder}; "
                f"give exactly one time per frame (frames are the .ply/.obj/.npz files, in natural order)"
                f"{_not_frames(self.folder)}"
            )
        if not np.isfinite(ts).all() or (ts.shape[0] > 1 and not (np.diff(ts) > 0).all()):
            bad = int(np.argmax(~np.isfinite(ts))) if not np.isfinite(ts).all() else int(np.argmax(np.diff(ts) <= 0)) + 1
            raise ValueError(f"{source}: timestamps must be finite and strictly increasing (entry {bad}, "
                             f"frame {self.frames[min(bad, len(self.frames) - 1)].name}: {float(ts[bad])!r})")
        if len(self.frames) < 2:
            raise ValueError(f"scan folder {self.folder}: one frame only; a sequence needs at least two")
        fix = None
        if found is None:
            fix = (f"give the capture rate in frames per second{' (' + rate_flag + ')' if rate_flag else ''}, or add "
                   f"{TIMESTAMP_FILES[0]} (one time in seconds per frame)")
        check_timestamps(ts, source if found is not None else f"scan folder {self.folder} ({source})",
                         field="timestamps" if found is not None else "fps", fix=fix)
        check_timestamp_gaps(ts, source)
        self.timestamps = ts
        self.timestamps_source = source
        self.source = f"scans:{self.folder}"
        self.meta = {"subject": "", "folder": str(self.folder), "up": up, "units": units}
        self._validated = False
        if check:
            self.validate()

    def validate(self) -> None:
        """Read and check every frame file (parse, point count, finite, plausible coordinates in
        metres, a person's height): the first bad frame is an error naming its file. Warnings are
        logged once per sequence (the first, and how many frames had one)."""
        warnings: list[str] = []
        for i in range(len(self.frames)):
            self._read_frame(i, warnings)
        kinds: dict = {}  # the first warning of each kind (its text without file and numbers)
        for w in warnings:
            kinds.setdefault(re.sub(r"[-+]?\d[\d.e+-]*", "#", w.split(": ", 1)[-1]), w)
        frames = {w.split(": ", 1)[0] for w in warnings}
        for n, w in enumerate(kinds.values()):
            more = (f" (warnings on {len(frames)} frame(s) of {self.folder} in all)"
                    if n == len(kinds) - 1 and len(frames) > 1 else "")
            log.warning("%s%s", w, more)
        self._validated = True

    def content_sha256(self) -> str:
        """Content hash of the capture as a unit reads it: the up axis and units, the timestamps
        and every frame file's bytes (resume reuses a stored unit only for the same capture)."""
        import hashlib

        h = hashlib.sha256(f"scans;up:{self.up};units:{self.units};".encode())
        ts = np.ascontiguousarray(np.asarray(self.timestamps, dtype=np.float64))
        h.update(ts.tobytes())
        for frame in self.frames:
            path = Path(frame)
            h.update(f"{path.name}:".encode())
            h.update(path.read_bytes())
        return h.hexdigest()

    @property
    def capture_fps(self) -> float:
        return float(1.0 / np.median(np.diff(self.timestamps)))

    @property
    def duration(self) -> float:
        """Span plus one median frame period, as :attr:`benchmark.core.motion.Motion.duration`."""
        return float(self.timestamps[-1] - self.timestamps[0]) + 1.0 / self.capture_fps

    def _read_frame(self, i: int, warnings: list[str]) -> np.ndarray:
        path = self.frames[int(i)]
        pts = to_harness_frame(read_scan_frame(path), self.up, self.units)
        check_scan_frame_size(pts, str(path))
        warnings += check_units(pts, path, self.up, self.units, warn=False)
        warnings += check_scan_coordinates(pts, str(path), warn=False)
        return pts

    def read_frames(self, indices) -> list[np.ndarray]:
        """(N_i, 3) float64 points in metres, y up, of the given frames (each checked; warnings are
        logged unless :meth:`validate` has logged them already)."""
        out, warnings = [], []
        for i in indices:
            out.append(self._read_frame(int(i), warnings))
        if not self._validated:
            for message in warnings:
                log.warning("%s", message)
        return out

    def nearest_frames(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Indices of the capture frames nearest in time to ``t`` (absolute seconds) and the
        signed offsets (capture time - t). Ties go to the earlier frame."""
        ts = self.timestamps
        j = np.clip(np.searchsorted(ts, t), 1, len(ts) - 1)
        left, right = ts[j - 1], ts[j]
        idx = np.where(t - left <= right - t, j - 1, j)
        return idx, ts[idx] - t


def parse_scan_data(data: str) -> tuple[Path, dict]:
    """``scans=DIR[?up=z&units=mm&fps=50]`` -> (DIR, options). The options come from ``run``'s
    ``--up`` / ``--units`` flags (or are written by hand)."""
    if not data.startswith("scans="):
        raise ValueError(f"--data {data!r}: a scan root is given as scans=DIR")
    body = data[len("scans="):]
    path, _, query = body.partition("?")
    options = {}
    for item in filter(None, query.split("&")):
        key, sep, value = item.partition("=")
        if not sep or key not in ("up", "units", "fps"):
            raise ValueError(f"--data {data!r}: unknown option {item!r}; known: up=y|z, units=m|cm|mm, fps=F")
        options[key] = float(value) if key == "fps" else value
    if not path:
        raise ValueError("--data scans=DIR: the folder is missing")
    return Path(path), options


def scan_data_spec(data: str | None, up: str | None, units: str | None) -> str | None:
    """The ``--data`` value with ``run``'s --up / --units folded in (they apply to scans= only)."""
    if up in (None, "y") and units in (None, "m"):
        return data
    if not data or not data.startswith("scans="):
        raise ValueError("--up and --units apply to captured scans only: use them with --data scans=DIR")
    extra = "&".join(f"{k}={v}" for k, v in (("up", up), ("units", units)) if v is not None)
    return data + ("&" if "?" in data else "?") + extra


def find_scan_sequences(root: str | Path, up: str = "y", units: str = "m", fps: float | None = None) -> dict:
    """Scan sequences under ``root`` by id: each sub-folder holding frame files (its name is the
    id), or ``root`` itself when it holds frames. Error when there are none. Every frame of every
    sequence is read and checked here (:meth:`ScanSequence.validate`), before any work unit."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"--data scans={root}: the folder does not exist")

    def has_frames(p: Path) -> bool:
        return any(f.is_file() and f.suffix.lower() in FRAME_SUFFIXES for f in p.iterdir())

    folders = [root] if has_frames(root) else sorted((p for p in root.iterdir() if p.is_dir() and has_frames(p)),
                                                   key=lambda p: natural_key(p.name))
    if not folders:
        raise FileNotFoundError(
            f"--data scans={root}: no sequence folders; expected {root}/<sequence>/frame_0001.ply ... plus "
            f"timestamps.txt in each (see benchmark/loaders/scans.py)"
        )
    return {(p.name if p != root else root.name): ScanSequence(p, up=up, units=units, fps=fps) for p in folders}
