"""Plausibility checks on the data a user feeds in: one place, called by every loader.

A file can be well formed (right keys, shapes, finite values) and still not be what the harness
assumes: timestamps in milliseconds, translations in millimetres, a shape vector of another body.
Such data runs through every protocol and gives numbers that look like results (MPJPE 0.0 mm on
millisecond timestamps; 29,506,887 mm on translations x 1e6). The checks here refuse it with an
error that names the file, the field and the fix, and warn (``logging``, then go on) where data is
only unusual. Callers: :meth:`benchmark.core.motion.Motion.load`, :func:`benchmark.loaders.amass.load_amass`,
:func:`benchmark.loaders.bvh.load_bvh`, :mod:`benchmark.loaders.scans` (every frame, before any
work unit starts) and :func:`benchmark.core.motion.shape_for_body` (the shape against the
body, for ``run --data``, ``data convert --body`` and ``complete``).

Thresholds (module constants) and why:

- Time, on timestamps in seconds (a motion or a scan folder):
  ``MIN_FPS`` = 1 and ``MAX_FPS`` = 1,000 frames per second (rate = 1 / median interval): motion
  capture runs at 24-480 fps, depth/4D scanners at 5-120; millisecond timestamps show as 1,000x
  too slow (30 fps -> 0.03 fps), microseconds as 10^6x, minutes as 60x too fast. Error.
  ``MAX_DURATION_S`` = 3,600 s: no capture session the harness reads is longer than an hour
  (AMASS takes are seconds to minutes); millisecond timestamps of a 4 s take span 4,000 s. Error.
  ``MIN_DURATION_S`` = 0.1 s (span plus one interval; three frames at 30 fps), far shorter than
  any protocol's window: a warning, not an error (an excerpt or a test file is legitimate, and the
  rate check already catches the usual unit mistakes; timestamps in minutes of a capture slower than
  17 fps would show only here). A motion needs at least 2 frames (``MIN_MOTION_FRAMES``): one
  pose has no rate and no motion. Error.
- Space, in metres: ``MAX_TRANSLATION_M`` = 1,000 m for the root translation's distance from the
  origin and for the distance the body travels (the extent of its trajectory), and
  ``MAX_COORDINATE_M`` = 1,000 m for a scan point. A capture volume is metres to tens of metres;
  translations x 1,000 (millimetres) of a body standing 1 m from the origin already cross it, and
  float32 resolves only 0.06 mm at 1 km (and 6 cm at 10^6 m). Error. Beyond ``WARN_TRANSLATION_M`` /
  ``WARN_COORDINATE_M`` = 100 m: a warning (an outdoor capture can be that large; centimetres look
  like this too).
- Holes and teleports inside the part of a motion a table reads (:func:`window_defect`; the tables
  skip such a motion, or sls such a cycle, with the reason, instead of refusing the file, whose
  other parts may serve): a frame interval more than ``GAP_RATIO`` = 2.5 times the motion's median
  one is a hole (frames are missing: one dropped frame makes 2x; resampling would SLERP / LERP an
  invented motion across it), and a root step faster than ``MAX_ROOT_SPEED`` = 20 m/s is a teleport
  (a tracking glitch or two takes joined: a sprinter peaks near 12 m/s, the synthetic splits stay
  under 8).
- Scan frames: at least ``MIN_SCAN_POINTS`` = 3 points (fewer span no surface: no fit, Chamfer
  distance or height check means anything; a sparse marker set has dozens, a scanner thousands).
  Error.
- Shape vectors, against the body that will use them (same family only; a shape of another body
  is replaced by the neutral shape, as before):
  SMPL-family betas are PCA coefficients ordered by variance: a shorter vector is zero-padded (the
  mean shape), and a longer one is cut to the body's count when it has at most
  ``SMPL_BETAS_CUT_SILENTLY`` = 16 values (the count of every AMASS release; docs/real-data.md
  documents this cut, and the CLI's SMPL-family bodies take 10 betas). A longer vector is cut with a warning when the coefficients cut away are all zero
  (within ``SHAPE_ZERO_TOL``), and refused otherwise (300 SMPL-X betas are not 10 SMPL betas).
  Other bodies (Anny: 6 named phenotype parameters in [0, 1], neutral 0.5) take exactly their own
  count: a longer vector whose extra values are zero is cut with a warning; any other length is
  refused (zero-padding a phenotype is not the neutral body).

Data that passes every check is returned unchanged (no check alters a number), so results on
plausible data cannot move.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import torch

log = logging.getLogger(__name__)

MIN_FPS = 1.0
MAX_FPS = 1000.0
MIN_DURATION_S = 0.1
MAX_DURATION_S = 3600.0
MIN_MOTION_FRAMES = 2
WARN_TRANSLATION_M = 100.0
MAX_TRANSLATION_M = 1000.0
WARN_COORDINATE_M = 100.0
MAX_COORDINATE_M = 1000.0
MIN_SCAN_POINTS = 3
SMPL_FAMILY = ("smpl", "smplh", "smplx")
SMPL_BETAS_CUT_SILENTLY = 16
SHAPE_ZERO_TOL = 1e-6
GAP_RATIO = 2.5  # a frame interval this many times the median one is a hole (one dropped frame is 2x)
MAX_ROOT_SPEED = 20.0  # m/s between two frames; a sprinter peaks near 12, the synthetic splits under 8

# Time units people write by mistake: (name, seconds per unit, the fix). Timestamps written in
# unit u give a rate r per u, i.e. r / u frames per second.
_TIME_UNITS = (("milliseconds", 1e-3, "divide them by 1000"), ("microseconds", 1e-6, "divide them by 10^6"),
               ("nanoseconds", 1e-9, "divide them by 10^9"), ("minutes", 60.0, "multiply them by 60"),
               ("hours", 3600.0, "multiply them by 3600"))
_TYPICAL_FPS = (5.0, 500.0)  # a guessed unit must turn the rate into one of these
_LENGTH_UNITS = {100.0: "centimetres", 1000.0: "millimetres"}


def _np(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _emit(messages: list[str], warn: bool) -> list[str]:
    if warn:
        for m in messages:
            log.warning("%s", m)
    return messages


def _time_unit_guess(rate: float) -> str | None:
    """'the values look like milliseconds (...): divide them by 1000' when one common unit mistake
    turns ``rate`` into a typical capture rate, else None."""
    for name, seconds, fix in _TIME_UNITS:
        true_rate = rate / seconds
        if _TYPICAL_FPS[0] <= true_rate <= _TYPICAL_FPS[1]:
            return f"the values look like {name} ({true_rate:.4g} fps if so): {fix}"
    return None


def _length_scale_hint(metres: float) -> str:
    """How far off a length in metres looks, as a fix: the power of ten that brings it to <= 10 m."""
    factor = 10.0 ** math.ceil(math.log10(max(metres, 10.0) / 10.0))
    unit = _LENGTH_UNITS.get(factor)
    if unit:
        return f"give it in metres (the values look like {unit}: divide them by {factor:,.0f})"
    return (f"give it in metres (the values look about {factor:.0e} times too large: check how the file "
            "was written and divide them by that factor)")


# ------------------------------------------------------------------------------------------------ time
def check_timestamps(timestamps, where: str, field: str = "timestamps", fix: str | None = None,
                     warn: bool = True) -> list[str]:
    """Refuse timestamps (seconds) whose rate or span cannot be a capture; warn on a very short one.

    timestamps: (T,) strictly increasing (the loaders check order and finiteness before).
    where / field: the file and the field (or key) the message names. fix: what to do, in the
    caller's terms (its flag or file); default: the unit conversion the numbers suggest.
    Returns the warnings (logged when ``warn``). A single timestamp has nothing to check.
    """
    ts = _np(timestamps).reshape(-1)
    if ts.size < 2:
        return []
    median_dt = float(np.median(np.diff(ts)))
    rate = 1.0 / median_dt
    span = float(ts[-1] - ts[0])
    if not MIN_FPS * (1 - 1e-9) <= rate <= MAX_FPS * (1 + 1e-9):  # slack: 1 / (1 / 1000) is not exactly 1000
        guess = _time_unit_guess(rate)
        hint = fix or ("timestamps are seconds; " + guess if guess else "give the timestamps in seconds")
        raise ValueError(
            f"{where}: field {field!r} gives a frame rate of {rate:.4g} fps (1 / the median interval "
            f"{median_dt:.4g}) over {span:,.6g} s; a capture runs at {MIN_FPS:g}-{MAX_FPS:,.0f} fps. Fix: {hint}"
        )
    if span > MAX_DURATION_S:
        hint = fix or ("give the timestamps in seconds (milliseconds: divide them by 1000); a capture that really "
                       "lasts this long: cut it into takes of at most an hour")
        raise ValueError(
            f"{where}: field {field!r} spans {span:,.6g} s ({span / 3600:.3g} h); the harness reads captures of at "
            f"most {MAX_DURATION_S:,.0f} s (an hour). Fix: {hint}"
        )
    out = []
    duration = span + median_dt
    if duration < MIN_DURATION_S:
        out.append(f"{where}: the capture lasts only {duration:.4g} s ({ts.size} frames at {rate:.4g} fps), under "
                   f"{MIN_DURATION_S:g} s, shorter than any table window; if field {field!r} is not in seconds, "
                   "convert it")
    return _emit(out, warn)


# ------------------------------------------------------------------------------------------------ space
def check_translation(trans, where: str, field: str = "trans", fix: str | None = None,
                      warn: bool = True) -> list[str]:
    """Refuse a root translation (T, 3) in metres that puts the body, or moves it, beyond
    MAX_TRANSLATION_M; warn beyond WARN_TRANSLATION_M. Returns the warnings."""
    tr = _np(trans).reshape(-1, 3)
    if tr.shape[0] == 0:
        return []
    dist = np.linalg.norm(tr, axis=1)
    i = int(np.argmax(dist))
    reach = float(dist[i])
    travel = float(np.linalg.norm(tr.max(0) - tr.min(0)))
    what = (f"field {field!r} puts the body {reach:,.4g} m from the origin (frame {i}) and moves it over "
            f"{travel:,.4g} m")
    if reach > MAX_TRANSLATION_M or travel > MAX_TRANSLATION_M:
        hint = fix or _length_scale_hint(max(reach, travel))
        raise ValueError(
            f"{where}: {what}; a capture volume is metres to tens of metres, and the harness refuses more than "
            f"{MAX_TRANSLATION_M:,.0f} m. Fix: {hint}"
        )
    out = []
    if reach > WARN_TRANSLATION_M or travel > WARN_TRANSLATION_M:
        out.append(f"{where}: {what}, more than {WARN_TRANSLATION_M:g} m: unusual for a capture; check that it is in "
                   "metres")
    return _emit(out, warn)


def check_motion(motion, where: str, time_field: str = "timestamps", time_fix: str | None = None,
                 trans_field: str = "trans", trans_fix: str | None = None, warn: bool = True) -> list[str]:
    """Every check of a loaded :class:`benchmark.core.motion.Motion`: frame count, time units and
    translation scale. Raises ValueError (file, field, fix); returns (and logs) the warnings."""
    T = int(motion.poses.shape[0])
    if T < MIN_MOTION_FRAMES:
        raise ValueError(
            f"{where}: field 'poses' holds {T} frame; a motion needs at least {MIN_MOTION_FRAMES} (one pose has no "
            "frame rate and no motion to fit). Fix: export the whole take"
        )
    out = check_timestamps(motion.timestamps, where, time_field, time_fix, warn=False)
    out += check_translation(motion.trans, where, trans_field, trans_fix, warn=False)
    return _emit(out, warn)


# ------------------------------------------------------------------------------------------------ holes
def hole_defect(timestamps, t0: float, t1: float,
                fix: str = "split the motion there or fill the frames") -> tuple[str | None, torch.Tensor | None]:
    """(why, intervals): why the part [t0, t1] (seconds) of a recording with these ``timestamps`` spans
    a hole, or None: a frame interval it overlaps is more than ``GAP_RATIO`` times the median one.
    ``intervals``: the indices i of the intervals [t_i, t_i+1] the part overlaps (None: no interval).
    The reason names the times and ends with ``fix``. Motions (:func:`window_defect`) and captured
    scans (:mod:`benchmark.protocols.scan_completion`) share it."""
    ts = torch.as_tensor(timestamps, dtype=torch.float64)
    if ts.numel() < 2:
        return None, None
    dt = ts.diff()
    inside = torch.nonzero((ts[1:] > t0 + 1e-9) & (ts[:-1] < t1 - 1e-9)).flatten()  # intervals the part overlaps
    if inside.numel() == 0:
        return None, None
    med = float(dt.median())
    i = int(inside[dt[inside].argmax()])
    if float(dt[i]) > GAP_RATIO * med:
        return (f"frames are missing between {float(ts[i]):.3f} s and {float(ts[i + 1]):.3f} s (a {float(dt[i]):.3f} s "
                f"interval, {float(dt[i]) / med:.1f} x the median frame interval): the table would interpolate an "
                f"invented motion across the hole; {fix}"), inside
    return None, inside


def window_defect(motion, t0: float, t1: float) -> str | None:
    """Why the part [t0, t1] (seconds, the motion's own clock) of ``motion`` (``timestamps``, ``trans``)
    cannot be scored, or None: a frame interval it overlaps is more than ``GAP_RATIO`` times the
    motion's median one (a hole, :func:`hole_defect`), or the root moves faster than
    ``MAX_ROOT_SPEED`` between two of its frames (a teleport). The reason names the times and the fix.
    Used by the sls cycles (:mod:`benchmark.protocols.sls_cycles`) and by every table's window
    (:func:`benchmark.data.table_data.load_motions`)."""
    why, inside = hole_defect(motion.timestamps, t0, t1)
    if why is not None or inside is None:
        return why
    ts = torch.as_tensor(motion.timestamps, dtype=torch.float64)
    dt = ts.diff()
    step = torch.as_tensor(motion.trans, dtype=torch.float64).diff(dim=0).norm(dim=-1)[inside]
    speed = step / dt[inside]
    j = int(speed.argmax())
    if float(speed[j]) > MAX_ROOT_SPEED:
        k = int(inside[j])
        return (f"the root moves {float(step[j]):.2f} m between {float(ts[k]):.3f} s and {float(ts[k + 1]):.3f} s "
                f"({float(speed[j]):.0f} m/s; no body moves faster than {MAX_ROOT_SPEED:g}): a glitch or two takes "
                "joined; repair field 'trans' there or split the motion")
    return None


# ------------------------------------------------------------------------------------------------ scans
def check_scan_frame_size(points, where: str) -> None:
    """Refuse a scan frame (N, 3) with fewer than MIN_SCAN_POINTS points or non-finite values."""
    pts = _np(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{where}: the points must be an (N, 3) array, got shape {pts.shape}")
    if pts.shape[0] < MIN_SCAN_POINTS:
        raise ValueError(
            f"{where}: the frame has {pts.shape[0]} point(s); a frame needs at least {MIN_SCAN_POINTS} (fewer span no "
            "surface to fit or score). Fix: re-export the frame, or remove the file and its timestamp"
        )
    finite = np.isfinite(pts).all(1)
    if not finite.all():
        raise ValueError(f"{where}: point {int(np.argmax(~finite))} is not finite (NaN/inf); drop such points from "
                         "the file or re-export it")


def check_scan_coordinates(points, where: str, warn: bool = True) -> list[str]:
    """Refuse a scan frame (N, 3), in metres, with a point beyond MAX_COORDINATE_M of the origin;
    warn beyond WARN_COORDINATE_M. Returns the warnings (logged when ``warn``)."""
    dist = np.abs(_np(points)).max(1)
    far = float(dist.max()) if dist.size else 0.0
    if far > MAX_COORDINATE_M:
        raise ValueError(
            f"{where}: point {int(np.argmax(dist))} lies {far:,.4g} m from the origin along an axis; a capture volume "
            f"is metres to tens of metres, and the harness refuses more than {MAX_COORDINATE_M:,.0f} m. Fix: give the "
            "points in metres (--units cm|mm converts) with the origin near the subject"
        )
    out = []
    if far > WARN_COORDINATE_M:
        out.append(f"{where}: a point lies {far:,.4g} m from the origin, more than {WARN_COORDINATE_M:g} m: unusual "
                   "for a capture; check the units (--units m|cm|mm)")
    return _emit(out, warn)


def check_scan_points(points, where: str, warn: bool = True) -> list[str]:
    """Both scan-frame checks (size and finiteness, then coordinates) on (N, 3) points in metres."""
    check_scan_frame_size(points, where)
    return check_scan_coordinates(points, where, warn)


# ------------------------------------------------------------------------------------------------ shape
def shape_family(name: str | None) -> str:
    """'smplh-female' -> 'smplh'; None -> ''."""
    return (name or "").lower().split("-")[0]


def check_shape(shape, where: str, body_name: str, body_family: str, shape_dim: int, warn: bool = True) -> list[str]:
    """Check a shape vector (S,) of the same family as the body that will use it (``body_family``,
    ``shape_dim`` values) before it is cut or padded to ``shape_dim`` (rules: module docstring).
    Raises ValueError naming the file, the field and the fix; returns (and logs) the warnings."""
    s = _np(shape).reshape(-1)
    n, dim = int(s.size), int(shape_dim)
    if n == dim:
        return []
    pca = body_family in SMPL_FAMILY
    if n < dim:
        if pca:
            return []  # zero betas are the mean shape: padding is exact
        raise ValueError(
            f"{where}: field 'shape' has {n} values, body {body_name!r} takes {dim} named parameters, which zeros "
            f"cannot pad (its neutral shape is not zero). Fix: save all {dim} values of the body's shape, or drop the "
            "field 'shape' (the body's neutral shape is used)"
        )
    dropped = s[dim:]
    largest = float(np.abs(dropped).max())
    if largest <= SHAPE_ZERO_TOL:
        return _emit([f"{where}: field 'shape' has {n} values, body {body_name!r} takes {dim}; the last {n - dim} are "
                      "zero and are dropped"], warn)
    if pca and n <= SMPL_BETAS_CUT_SILENTLY:
        return []  # AMASS's 16 betas on a 10-beta body: the documented cut (PCA order: the smallest last)
    raise ValueError(
        f"{where}: field 'shape' has {n} values, body {body_name!r} takes {dim}, and the {n - dim} that would be cut "
        f"away are not zero (largest |value| {largest:.4g}): cutting them changes the body. Fix: save the shape the "
        f"body {body_name!r} uses ({dim} values: shape[:{dim}] if the first {dim} are meant), or drop the field "
        "'shape' (the body's neutral shape is used)"
    )
