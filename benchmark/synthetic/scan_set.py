"""A captured-like test scan set from the synthetic test split: ``python -m benchmark data make-scans``.

Each selected test sequence becomes one folder in the layout :mod:`benchmark.loaders.scans` reads::

    OUT/<sequence>/frame_0000.ply ...   binary PLY point clouds (float32 x y z), one per frame
    OUT/<sequence>/timestamps.txt       one time in seconds per frame
    OUT/<sequence>/ground_truth/motion.npz   the generating motion (harness .npz) for the window;
                                        loaders never read it (it is in a sub-folder), ``complete``
                                        uses it for diagnostics against the truth
    OUT/.benchmark-output.json          the marker: written by make-scans, and which sequence
                                        folders; ``--force`` replaces only such a folder's sequences

Frames: ``points`` points per frame after the holes, sampled uniformly over the generator's posed
mesh (``benchmark.data.observations.make_scans``) with i.i.d. Gaussian noise of ``noise_mm`` per axis;
holes: the ``holes`` fraction of each frame's points nearest to one random point of that frame is
cut away (one contiguous patch, about that fraction of the surface, as an occluder would). Written
in ``units`` with ``up`` as the up axis, so the loader's --units / --up conversions can be tested.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger(__name__)

COMMAND = "data make-scans"


def write_ply_points(path: Path, points: np.ndarray) -> None:
    """A binary little-endian PLY point cloud (float32 x, y, z)."""
    pts = np.ascontiguousarray(points, dtype="<f4")
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {pts.shape[0]}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(pts.tobytes())


def write_ply_mesh(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """A binary little-endian PLY triangle mesh."""
    v = np.ascontiguousarray(vertices, dtype="<f4")
    f_ = np.asarray(faces, dtype=np.int64)
    rec = np.empty(f_.shape[0], dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rec["n"], rec["i"] = 3, f_
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {v.shape[0]}\n"
              "property float x\nproperty float y\nproperty float z\n"
              f"element face {f_.shape[0]}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(v.tobytes())
        fh.write(rec.tobytes())


def cut_hole(points: torch.Tensor, fraction: float, generator: torch.Generator) -> torch.Tensor:
    """(N, 3) -> the points left after removing the ``fraction`` nearest to a random one of them."""
    n = points.shape[0]
    k = int(round(fraction * n))
    if k <= 0:
        return points
    centre = points[int(torch.randint(n, (1,), generator=generator))]
    d = (points - centre).norm(dim=-1)
    keep = torch.argsort(d)[k:].sort().values
    return points[keep]


def folder_name(sequence_id: str) -> str:
    """The sequence id as a folder name (it becomes the scan sequence's id in tables); only path
    separators are replaced, so synthetic ids (``synthetic:test:0002``) survive on POSIX systems."""
    name = sequence_id.replace("/", "_").replace("\\", "_")
    return "_" + name[1:] if name.startswith(".") else name


def make_scan_set(out: str | Path, sequences=4, fps: float = 60.0, points: int = 10000, noise_mm: float = 3.0,
                  holes: float = 0.1, duration: float = 4.0, seed: int = 0, up: str = "y", units: str = "m",
                  body=None, overwrite: bool = False, table_capture: int | None = None,
                  table_spec: dict | None = None) -> list[Path]:
    """Write the scan set (module docstring); ``sequences``: a count (the same deterministic selection
    as ``run``'s profiles: :func:`benchmark.core.work_units.select_sequences`) or a list of ids.

    ``table_capture=SEED``: write, for each sequence, the very capture ``run table1 --seed SEED``
    synthesises for a one-sequence work unit (table1's capture rate, points per frame, scan noise
    and capture seed; ``fps``, ``points``, ``noise_mm``, ``holes`` and ``duration`` are ignored), so
    that ``run table1 --data scans=OUT`` sees the same observations as the synthetic run (the
    check of the scan path; smoke units hold one sequence). ``table_spec``: the spec of table1 for that
    (``data make-scans`` loads ``benchmark/tables/table1.yaml``; tests use shorter windows).
    """
    from benchmark.loaders.scans import UNITS, Z_UP_TO_Y_UP
    from benchmark.data.observations import make_scans
    from benchmark.core.outdir import check_not_overlapping, claim_out_dir, remove_entries, write_marker
    from benchmark.synthetic.splits import build_split, cache_dir
    from benchmark.core.work_units import select_sequences, stable_seed

    # every argument is checked before anything in `out` is touched; then only an earlier
    # make-scans output is replaced (its marker lists it; benchmark.core.outdir.claim_out_dir)
    if not 0.0 <= holes < 1.0:
        raise ValueError(f"holes must be a fraction in [0, 1), got {holes}")
    if table_capture is not None and table_spec is None:
        raise ValueError("table_capture: give table_spec, table1's spec (benchmark.run.catalog.load_table_spec('table1'))")
    if units not in UNITS or up not in ("y", "z"):
        raise ValueError(f"units must be one of {list(UNITS)} and up one of y, z; got {units!r}, {up!r}")
    for name, value, ok, rule in (("fps", fps, fps > 0, "> 0"), ("points", points, points >= 1, ">= 1"),
                                  ("noise_mm", noise_mm, noise_mm >= 0, ">= 0"), ("duration", duration, duration > 0, "> 0")):
        if not ok:
            raise ValueError(f"{name} must be {rule}, got {value}")
    if isinstance(sequences, (list, tuple)):
        if not sequences:
            raise ValueError("sequences: give at least one test sequence id")
    elif sequences != "all" and int(sequences) < 1:
        raise ValueError(f"sequences must be >= 1, got {sequences}")
    split_cache = cache_dir("test")
    check_not_overlapping(out, [("synthetic split cache", split_cache.parent)])
    out, earlier = claim_out_dir(out, COMMAND, overwrite)
    if body is None:
        from benchmark.body import get_body

        body = get_body("anny")
    by_id = {m.source: m for m in build_split("test")}
    ids = list(sequences) if isinstance(sequences, (list, tuple)) else select_sequences(by_id, sequences)
    unknown = [i for i in ids if i not in by_id]
    if unknown:
        raise KeyError(f"unknown test sequence ids {unknown[:3]}; e.g. {sorted(by_id)[:2]}")
    names = [folder_name(sid) for sid in ids]
    if len(set(names)) != len(names):
        raise ValueError(f"sequences: an id is given twice ({[n for n in names if names.count(n) > 1][0]})")
    sampled = int(round(points / (1.0 - holes)))
    if table_capture is not None:
        d = table_spec["data"]
        if float(d.get("window_start_s", 0.0)):
            raise ValueError("table_capture: table1's window_start_s is not 0; not supported")
        fps, sampled, noise_mm, holes, duration = (float(d["capture_fps"]), int(d["points_per_frame"]),
                                                   1000.0 * float(d.get("scan_noise_std", 0.0)), 0.0, float(d["window_s"]))
    frames = int(round(duration * fps))
    if frames < 1:
        raise ValueError(f"duration {duration:g} s at {fps:g} fps gives no frame; give a longer duration or a higher fps")
    short = [(sid, by_id[sid].duration) for sid in ids if (frames - 1) / fps > by_id[sid].duration + 1e-6]
    if short:
        raise ValueError(f"duration {duration:g} s: sequence {short[0][0]} lasts only {short[0][1]:.3f} s; give a "
                         f"duration of at most {min(d for _, d in short):.2f} s")
    remove_entries(out, earlier)
    write_marker(out, COMMAND, names)
    written = []
    for sid in ids:
        motion = by_id[sid]
        folder = out / folder_name(sid)
        folder.mkdir(parents=True)
        capture_seed = (stable_seed("capture", table_capture, sid) if table_capture is not None
                        else stable_seed("make-scans", seed, sid))
        scans, _ = make_scans(body, [motion], fps=fps, num_points=sampled, noise_std=noise_mm / 1000.0,
                              seed=capture_seed, duration=duration)
        g = torch.Generator().manual_seed(stable_seed("holes", seed, sid))
        ts = scans.timestamps[0].numpy() - float(scans.timestamps[0, 0])
        for t in range(scans.num_frames):
            pts = cut_hole(scans.frame_points(0, t), holes, g).double().numpy()
            if up == "z":
                pts = pts @ Z_UP_TO_Y_UP  # inverse of the loader's (x, y, z) -> (x, z, -y)
            write_ply_points(folder / f"frame_{t:04d}.ply", pts / UNITS[units])
        np.savetxt(folder / "timestamps.txt", ts, fmt="%.6f", header=f"seconds; {fps:g} fps capture of {sid}")
        t0 = float(motion.timestamps[0])
        truth = motion.window(t0, min(duration, motion.duration))
        truth = dataclasses.replace(truth, timestamps=truth.timestamps - t0, source=f"{sid} (make-scans ground truth)")
        truth.save(folder / "ground_truth" / "motion.npz")
        written.append(folder)
        log.info("wrote %s: %d frames", folder, scans.num_frames)
    write_marker(out, COMMAND, names, files=True)  # its files too: a later --force replaces only them
    return written
