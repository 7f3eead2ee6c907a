"""The test motions of a table (:func:`load_motions`): the synthetic test split, or ``--data``'s
motion files, shapes made fit for the body; shared by the protocols, the runner and the commands.
Which of them a profile runs: :func:`benchmark.core.work_units.select_sequences`.

A motion is skipped, with a warning that names its file and the reason, when it is too short for
the table's window (:func:`too_short`), or when the part of it the table reads (``window``:
:func:`read_part`) spans a hole in its timestamps or a root teleport
(:func:`benchmark.core.plausibility.window_defect`: the table would resample across it and score the
fit against an invented ground truth). When no motion is left the error names them all."""

from __future__ import annotations

import logging
from pathlib import Path

from benchmark.core.motion import Motion, shape_for_body
from benchmark.core.plausibility import window_defect
from benchmark.core.safe_loading import npz_read_error

log = logging.getLogger(__name__)


def too_short(motion, min_duration: float, sample_fps: float | None = None) -> bool:
    """Whether ``motion`` cannot serve a window of ``min_duration`` s: it lasts less (its frames and one
    period), or, sampled at ``sample_fps`` from its first frame (a table's capture rate), the window's
    last instant ``(round(min_duration * sample_fps) - 1) / sample_fps`` lies past its last frame (a
    120-frame 30 fps motion lasts 4.0 s, but a 4 s window at 50 fps needs it up to 3.98 s, not 3.967)."""
    if motion.duration + 1e-6 < min_duration:
        return True
    return sample_fps is not None and (round(min_duration * sample_fps) - 1) / sample_fps > motion.span + 1e-6


def read_part(motion, start: float, length: float) -> tuple[float, float]:
    """(t0, t1), seconds on the motion's clock, enclosing what a table reads of ``motion`` for a window
    of ``length`` s from ``start`` s after its first frame: from that instant (a table resampling the
    motion interpolates the frame interval around it) to ``length`` after the first frame at or after
    it (table1 cuts the motion there and samples its window from that frame)."""
    t = motion.timestamps
    t0 = float(t[0]) + float(start)
    later = t[t >= t0 - 1e-9]
    first = float(later[0]) if len(later) else t0
    return t0, first + float(length)


def load_motions(data: str | None, min_duration: float, body=None, sample_fps: float | None = None,
                 window: tuple[float, float] | None = None) -> dict:
    """Test motions by id: the synthetic test split by default, or a folder of motion files (each
    checked by its loader: :mod:`benchmark.core.plausibility`). Motions too short for the window
    (:func:`too_short`; ``sample_fps``: the rate the table samples them at) are skipped with a warning.
    ``window`` = (start after the first frame, length), seconds: the window the table reads of each
    motion; a motion with a hole or a root teleport there (:func:`skip_defects`) is skipped too. sls
    passes none (it checks each of its cycles)."""
    files_by_id = {}
    if data is None:
        from benchmark.synthetic.splits import build_split

        motions = build_split("test")
        by_id = {m.source: m for m in motions}
    elif data.startswith("scans="):
        raise ValueError(f"--data {data}: captured scans are read by the completion protocol (table1) only")
    else:
        from benchmark.loaders.amass import is_shape_file, load_amass

        root = Path(data.split("=", 1)[-1])
        files = [root]
        if root.is_dir():  # motion.npz or motion.NPZ (data convert writes either)
            files = sorted(p for p in root.rglob("*") if p.suffix.lower() == ".npz" and p.is_file())
        if not files:
            raise FileNotFoundError(f"--data {data}: no .npz motion files under {root}")
        import numpy as np

        by_id, shape_files = {}, []
        for f in files:
            try:
                with np.load(f, allow_pickle=False) as npz:
                    keys = set(npz.files)
            except Exception as exc:  # not a zip, a pickle, truncated...
                raise ValueError(f"--data {data}: {f} is not a readable .npz file ({npz_read_error(f, exc)}); "
                                 "remove it from the folder or re-export it (python -m benchmark data convert)") from None
            if root.is_dir() and is_shape_file(f, keys):
                shape_files.append(f)  # an AMASS subject's shape.npz / *_shape.npz beside its sequences
                continue
            try:
                m = load_amass(f) if "mocap_framerate" in keys or "mocap_frame_rate" in keys else Motion.load(f)
            except KeyError as exc:
                text = exc.args[0] if exc.args and isinstance(exc.args[0], str) and " " in exc.args[0] else \
                    f"{f}: no field {exc} (fields present: {sorted(keys)})"
                raise ValueError(f"--data {data}: {text}; convert the file with "
                                 "`python -m benchmark data convert FILE --out FILE.npz`") from None
            key = str(f.relative_to(root) if root.is_dir() else f.name)
            by_id[key], files_by_id[key] = m, str(f)
    if data is not None and shape_files:
        log.info("--data %s: %d AMASS shape file(s) hold no motion and are not test sequences (e.g. %s)",
                 data, len(shape_files), shape_files[0])
        if not by_id:
            raise FileNotFoundError(f"--data {data}: no motion files under {root}, only AMASS shape files "
                                    f"(e.g. {shape_files[0]}); give the folder of the *_poses.npz / *_stageii.npz sequences")
    if body is not None:
        by_id = {k: shape_for_body(m, body, files_by_id.get(k)) for k, m in by_id.items()}
    short = [k for k, m in by_id.items() if too_short(m, min_duration, sample_fps)]
    if short and len(short) == len(by_id):
        longest = max(short, key=lambda k: by_id[k].duration)
        where, needs, fix = (f"--data {data}", "this table needs", f"give motions of at least {min_duration:.1f} s") \
            if data is not None else ("the synthetic test split", "asked for",
                                      "ask for a shorter window (the command's --window, where it has one)")
        rate = "" if sample_fps is None else f" at {sample_fps:g} fps"
        if sample_fps is not None and data is not None:
            last = (round(min_duration * sample_fps) - 1) / sample_fps
            fix += f" with frames up to {last:.3f} s after their first (the window's last instant at {sample_fps:g} fps)"
        raise ValueError(f"{where}: every motion is shorter than the {min_duration:.1f} s window {needs}{rate} "
                         f"({len(short)} of {len(by_id)}; the longest, {files_by_id.get(longest, longest)}, "
                         f"lasts {by_id[longest].duration:.2f} s: {by_id[longest].num_frames} frames over "
                         f"{by_id[longest].span:.3f} s): {fix}")
    if short:
        log.warning("skipping %d motions shorter than the %.1f s window: %s", len(short), min_duration, short[:5])
    kept = {k: m for k, m in by_id.items() if k not in short}
    if window is not None:
        where = f"--data {data}" if data is not None else "the synthetic test split"
        kept = skip_defects(kept, window, where, files_by_id, len(short))
    return kept


def skip_defects(motions: dict, window: tuple[float, float], where: str, files_by_id: dict | None = None,
                 n_short: int = 0) -> dict:
    """``motions`` less those whose window (``window`` = (start after the first frame, length), seconds;
    the part :func:`read_part` encloses) spans a hole in the timestamps or a root teleport
    (:func:`benchmark.core.plausibility.window_defect`): each is skipped with a warning naming its file
    (``files_by_id``, else its id), the time and the fix; a ValueError names them all when none is
    left (``n_short``: how many were already skipped as too short, for the message)."""
    start, length = float(window[0]), float(window[1])
    bad = {}
    for k, m in motions.items():
        t0, t1 = read_part(m, start, length)
        why = window_defect(m, t0, t1)
        if why is not None:
            rel = f"{t0 - float(m.timestamps[0]):.2f}-{t1 - float(m.timestamps[0]):.2f} s"
            bad[k] = f"{(files_by_id or {}).get(k, k)} (within the {length:g} s window the table reads, {rel} after " \
                     f"its first frame): {why}"
    if bad and len(bad) == len(motions):
        short = f"; the other {n_short} are shorter than the window" if n_short else ""
        raise ValueError(f"{where}: no usable motion is left: every one of the {len(bad)} long enough for the "
                         f"{length:g} s window has a hole in its timestamps or a root teleport within it{short}: "
                         + "; ".join(bad.values()))
    for k in bad:
        log.warning("skipping %s", bad[k])
    if bad:
        log.warning("skipped %d of %d motions for a hole or a root teleport within the window (above)",
                    len(bad), len(motions))
    return {k: m for k, m in motions.items() if k not in bad}
