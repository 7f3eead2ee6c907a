"""The completion protocol (table1) on captured scans: ``run table1 --data scans=DIR``.

The same windows, degradation, fit and scores as on the synthetic data (completion_unit.py), with
the capture taking the place of the synthesised one. The rules specific to captures (docs/protocol.md
states them; docs/captures.md repeats them for users):

- Window: the 4 s window starts at the capture frame nearest to the first timestamp plus the
  spec's ``window_start_s``; a sequence whose frames do not reach the last output timestamp
  (window start + window - 1/output_fps, within half a capture period) is skipped with a warning
  naming it, and so is one with a hole in the timestamps inside that span (an interval over 2.5 x
  the sequence's median one, :func:`window_hole`: its ground truth and observed frames would come
  from frames far from their instants, as the motion tables skip a motion with a hole); a root with
  no usable sequence is an error.
- Observed frames: at a cell's rate F, the capture frame nearest in time to each instant
  t0 + k / F, k = 0 .. window*F - 1. When the capture rate is a multiple of F this is "keep every
  k-th frame", exactly the synthetic rule; otherwise the largest time offset is recorded per
  sequence (``obs_time_offset_max_s``). Points: the same seeded random subset per frame as
  :func:`benchmark.data.degrade.degrade`.
- Ground truth for the Chamfer columns, at each 30 fps output timestamp t: the dense capture frame
  at t when there is one (always, for capture rates that are multiples of 30 fps); otherwise the
  capture frame nearest in time, t_i, interpolated to t: each of its points moves the fraction
  |t - t_i| / |t_j - t_i| of the way to its nearest neighbour in the neighbouring frame t_j on
  t's side (nearest-neighbour scene flow; exact for motion normal to the surface, which is what
  a Chamfer distance sees). The largest |t - t_i| is recorded per sequence
  (``gt_time_offset_max_s``; at most half a capture period). The frames of each sequence are cut
  to that sequence's smallest point count by a seeded random subset (in random order, as the
  synthetic i.i.d. scans; the subset's seed is the sequence's own); sequences of different sizes keep theirs (``UnitData.gt_points`` is
  then a list, one (1, T, N_b, 3) tensor per sequence), so a sequence's score never depends on the
  sequences batched with it (scan rules revision 2, :data:`SCAN_RULES_REVISION`).
- MPJPE: ``n/a``, reason "no ground-truth joints".
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from benchmark.loaders.scans import ScanSequence, find_scan_sequences, parse_scan_data
from benchmark.data.observations import PointCloudSequence

log = logging.getLogger(__name__)

# The revision of the rules above, in every captured sequence's data hash (benchmark.run.table_run):
# 2 (2026-12-07): the ground truth cut per sequence, by the sequence's own seed, no longer to the unit's
# smallest frame by the unit's seed.
SCAN_RULES_REVISION = 2

# An output instant within this many seconds of a capture frame's timestamp is that frame's instant.
TIME_MATCH_S = 1e-6


def load_scan_sequences(spec: dict, data: str) -> dict:
    """The usable scan sequences of ``--data scans=DIR[?up=..&units=..]`` by id (see module doc).

    Every frame file of every sequence is read and checked here (:meth:`ScanSequence.validate`:
    parse, point count, finite, coordinates, a person's height; timestamps' rate and span), so a
    bad capture is one error naming its file before the run plans or starts any work unit."""
    root, options = parse_scan_data(data)
    found = find_scan_sequences(root, up=options.get("up", "y"), units=options.get("units", "m"),
                                fps=options.get("fps"))
    d = spec["data"]
    window, start = float(d["window_s"]), float(d.get("window_start_s", 0.0))
    out_fps = float(spec["output_fps"])
    usable, short = {}, []
    for sid, seq in found.items():
        needed = start + window - 1.0 / out_fps
        if seq.timestamps[-1] - seq.timestamps[0] + 0.5 / seq.capture_fps < needed - 1e-9:
            short.append(f"{seq.folder} ({seq.timestamps[-1] - seq.timestamps[0]:.3f} s of frames)")
        else:
            usable[sid] = seq
    if short:
        log.warning("skipping %d scan sequence(s) shorter than the %.1f s window (frames must reach %.3f s): %s",
                    len(short), window, start + window - 1.0 / out_fps, "; ".join(short))
    holes = {}
    for sid, seq in usable.items():
        why = window_hole(seq, start, window - 1.0 / out_fps)
        if why is not None:
            holes[sid] = f"{seq.timestamps_source}: {why}"
    if holes:
        log.warning("skipping %d scan sequence(s) with a hole in the %.1f s window: %s",
                    len(holes), window, "; ".join(holes.values()))
        usable = {sid: seq for sid, seq in usable.items() if sid not in holes}
    if not usable and holes:
        raise ValueError(f"--data {data}: none of the {len(found)} sequence folder(s) under {root} is usable: "
                         f"{len(short)} do not cover the {window:g} s window (+{start:g} s start) and {len(holes)} "
                         f"have a hole in it: {'; '.join(holes.values())}")
    if not usable:
        raise ValueError(f"--data {data}: none of the {len(found)} sequence folder(s) under {root} covers the "
                         f"{window:g} s window (+{start:g} s start); capture longer sequences")
    rates = sorted({round(s.capture_fps, 3) for s in usable.values()})
    print(f"scans: {len(usable)} sequences under {root} (capture rates {', '.join(f'{r:g}' for r in rates)} fps, "
          f"units {options.get('units', 'm')}, {options.get('up', 'y')} up)")
    return usable


def window_start(seq: ScanSequence, start: float) -> tuple[int, float]:
    """(index, time) of the capture frame the window starts at: the one nearest to the first
    timestamp plus ``start`` seconds (``data.window_start_s``)."""
    idx, _ = seq.nearest_frames(np.array([seq.timestamps[0] + start]))
    return int(idx[0]), float(seq.timestamps[idx[0]])


def window_hole(seq: ScanSequence, start: float, span: float) -> str | None:
    """Why the part of ``seq`` the window reads (from its first frame, :func:`window_start`, for
    ``span`` s: the last output instant) spans a hole in the timestamps, or None
    (:func:`benchmark.core.plausibility.hole_defect`: an interval over 2.5 x the median one).
    Across a hole the ground truth and the observed frames would come from frames far from their
    instants, so such a sequence is left out, as a motion with a hole is."""
    from benchmark.core.plausibility import hole_defect

    _, t0 = window_start(seq, start)
    why, _ = hole_defect(seq.timestamps, t0, t0 + span,
                         fix="split the capture at the hole into two sequence folders, or capture the missing frames")
    return why


class ScanCompletionData:
    """Unit data from captured scans (one batch cached in process, as CompletionData)."""

    def __init__(self, table_spec: dict, body, sequences: dict, seed: int):
        self.spec = table_spec
        self.body = body
        self.motions = sequences
        self.seed = seed
        self._cache: dict = {}
        self._frames: dict = {}

    def _window_start(self, seq: ScanSequence) -> tuple[int, float]:
        return window_start(seq, float(self.spec["data"].get("window_start_s", 0.0)))

    def _points(self, sid: str, indices) -> list[np.ndarray]:
        seq = self.motions[sid]
        missing = sorted({int(i) for i in indices} - set(self._frames.get(sid, {})))
        store = self._frames.setdefault(sid, {})
        for i, pts in zip(missing, seq.read_frames(missing)):
            store[i] = pts.astype(np.float32)
        return [store[int(i)] for i in indices]

    def _ground_truth_frame(self, sid: str, i: int, offset: float) -> np.ndarray:
        """Capture frame ``i`` moved to the output instant ``t_i - offset``: each point goes that
        fraction of the way to its nearest neighbour in the neighbouring frame on the instant's
        side (the frame itself when the instant is a capture instant)."""
        (points,) = self._points(sid, [i])
        if abs(offset) <= TIME_MATCH_S:
            return points
        seq = self.motions[sid]
        j = i - 1 if offset > 0 else i + 1
        if not 0 <= j < len(seq.timestamps):
            return points
        import scipy.spatial

        (other,) = self._points(sid, [j])
        _, nn = scipy.spatial.cKDTree(other).query(points, k=1)
        w = abs(offset) / abs(seq.timestamps[j] - seq.timestamps[i])
        return (points + w * (other[nn] - points)).astype(np.float32)

    def unit_data(self, sequence_ids: list[str]):
        from benchmark.protocols.unit_data import UnitData
        from benchmark.core.work_units import stable_seed

        key = tuple(sequence_ids)
        if key in self._cache:
            return self._cache[key]
        self._frames = {}
        d = self.spec["data"]
        window = float(d["window_s"])
        out_fps = float(self.spec["output_fps"])
        n_out = int(round(window * out_fps))
        rel = np.arange(n_out, dtype=np.float64) / out_fps
        gt, extra = [], []
        for sid in sequence_ids:  # each sequence cut to its own smallest frame, by its own seed: never by its batch
            g = torch.Generator().manual_seed(stable_seed("gt-scan", self.seed, sid))
            seq = self.motions[sid]
            _, t0 = self._window_start(seq)
            idx, off = seq.nearest_frames(t0 + rel)
            frames = [self._ground_truth_frame(sid, int(i), float(o)) for i, o in zip(idx, off)]
            extra.append({"gt_time_offset_max_s": float(np.abs(off).max()), "capture_fps": seq.capture_fps})
            sizes = [f.shape[0] for f in frames]
            count, median = min(sizes), float(np.median(sizes))
            if count < 0.5 * median:
                # every ground-truth frame of the sequence is cut to one size: a sparse frame would cut them all
                i = int(idx[int(np.argmin(sizes))])
                raise ValueError(f"scans {sid}: capture frame {i} (t = {float(seq.timestamps[i]):.3f} s) holds "
                                 f"{count} points, under half the median ({median:.0f}) of the sequence's ground-truth "
                                 f"frames; remove that frame from the capture (or export it again)")
            if count < median:
                log.info("scans %s: ground-truth frames cut to %d points (their median: %d)", sid, count, median)
            gt.append(torch.stack([torch.from_numpy(f)[torch.randperm(f.shape[0], generator=g)[:count]]
                                   for f in frames])[None])
        out_t = torch.from_numpy(rel)[None].expand(len(sequence_ids), -1).clone()
        if len({x.shape[2] for x in gt}) == 1:
            gt = torch.cat(gt)
        data = UnitData(scans=None, out_t=out_t, gt_points=gt, gt_joints=None, row_extra=extra)
        self._cache = {key: data}
        return data

    def observe(self, sequence_ids: list[str], points: int | None, fps: float, seed: int) -> tuple[PointCloudSequence, list]:
        """The cell's observation (nearest capture frames at ``fps``, then a seeded random point
        subset) and, per sequence, the largest |observed frame time - nominal instant| in seconds."""
        from benchmark.data.degrade import degrade

        n = int(round(float(self.spec["data"]["window_s"]) * fps))
        clouds, times, offsets = [], [], []
        for sid in sequence_ids:
            seq = self.motions[sid]
            _, t0 = self._window_start(seq)
            idx, off = seq.nearest_frames(t0 + np.arange(n, dtype=np.float64) / fps)
            if n > 1 and not (np.diff(idx) > 0).all():
                raise ValueError(f"scan folder {seq.folder}: the capture ({seq.capture_fps:.4g} fps, "
                                 f"{seq.timestamps_source}) has no distinct frame for every instant at {fps:g} fps; "
                                 "the table needs captures at least as fast as its densest observed rate")
            clouds.append(self._points(sid, idx))
            times.append(seq.timestamps[idx])
            offsets.append(float(np.abs(off).max()))
        width = max(c.shape[0] for seq in clouds for c in seq)
        pts = torch.zeros(len(clouds), n, width, 3)
        lengths = torch.zeros(len(clouds), n, dtype=torch.long)
        for b, seq in enumerate(clouds):
            for t, c in enumerate(seq):
                pts[b, t, : c.shape[0]] = torch.from_numpy(c)
                lengths[b, t] = c.shape[0]
        if points is not None and float(lengths.double().median()) < SPARSE_CAPTURE * points:
            raise CellNotServed(f"the capture holds {int(lengths.double().median())} points per observed frame (median; "
                                f"{', '.join(sequence_ids[:3])}): a cell of {points} points per frame cannot be drawn "
                                "from it")
        dense = PointCloudSequence(points=pts, lengths=lengths, timestamps=torch.from_numpy(np.stack(times)))
        return degrade(dense, points, None, seed=seed), offsets


# a cell asks a capture for more points per frame than its median observed frame's by more than this
# factor: it is n/a (the 10,000-point cell of a 300-point capture would be the 300-point one, labelled 10,000)
SPARSE_CAPTURE = 0.9


class CellNotServed(ValueError):
    """A cell a capture cannot serve (too few points per frame): the unit is n/a with this reason."""


def is_scan_source(motions: dict) -> bool:
    return bool(motions) and all(isinstance(m, ScanSequence) for m in motions.values())

