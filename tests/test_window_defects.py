"""User motions (``run TABLE --data``) with a hole in their timestamps or a root teleport inside the
window a table reads are skipped with a warning naming the file, the time and the fix; nothing
usable left is an error naming them all. Before, table1, denoise, inbetween and reconstruction
resampled across a 1 s hole or a 5 m one-frame jump and scored the fit against that invented ground
truth. The rule is sls's (:func:`benchmark.core.plausibility.window_defect`). Tiny handmade files,
no body model."""

import copy
import logging

import numpy as np
import pytest

from benchmark.run.catalog import load_table_spec
from benchmark.run.table_run import table_protocol

FPS = 30.0


def write(folder, name, hole_at: int | None = None, jump_at: int | None = None, seconds: float = 7.0):
    """A 30 fps motion walking +z at 1.2 m/s; ``hole_at``: frames from there on 1 s later (30 frames
    missing); ``jump_at``: the root 5 m further along x from that frame on."""
    n = int(seconds * FPS)
    t = np.arange(n) / FPS
    trans = np.stack([0 * t, 0.02 * np.cos(4 * np.pi * t), 1.2 * t], -1)
    if hole_at is not None:
        t[hole_at:] += 1.0
    if jump_at is not None:
        trans[jump_at:, 0] += 5.0
    poses = np.zeros((n, 22, 3), np.float32)
    poses[:, 1, 0] = 0.5 * np.sin(2 * np.pi * t)
    np.savez(folder / name, poses=poses, trans=trans.astype(np.float32), timestamps=t, fps=np.float64(FPS),
             source=np.str_(name))


@pytest.fixture()
def folder(tmp_path):
    write(tmp_path, "clean.npz")
    write(tmp_path, "hole.npz", hole_at=30)  # frames missing between 0.967 s and 2.000 s
    write(tmp_path, "teleport.npz", jump_at=45)  # 5 m between 1.467 s and 1.500 s
    write(tmp_path, "late_hole.npz", hole_at=90)  # between 2.967 s and 4.000 s: inside 4 s, after 2 s
    write(tmp_path, "after.npz", hole_at=180)  # between 5.967 s and 7.000 s: after every window
    return tmp_path


def load(table, data, spec=None):
    spec = spec or copy.deepcopy(load_table_spec(table))
    return table_protocol(spec).load_motions(spec, str(data), None)


@pytest.mark.parametrize("table", ["table1", "denoise", "inbetween", "reconstruction"])
def test_hole_and_teleport_in_the_window_are_skipped_with_their_reason(folder, table, caplog):
    with caplog.at_level(logging.WARNING, logger="benchmark.data.table_data"):
        motions = load(table, folder)
    # table1 reads 4 s from the first frame, the motion tables 2 s: the late hole matters to table1 only
    kept = ["after.npz", "clean.npz"] + (["late_hole.npz"] if table != "table1" else [])
    assert sorted(motions) == kept
    text = caplog.text
    assert f"skipping {folder / 'hole.npz'}" in text
    assert "frames are missing between 0.967 s and 2.000 s" in text and "split the motion there or fill the frames" in text
    assert f"skipping {folder / 'teleport.npz'}" in text
    assert "the root moves 5.00 m between 1.467 s and 1.500 s" in text and "repair field 'trans' there" in text
    assert ("late_hole.npz" in text) == (table == "table1")
    assert "after.npz" not in text and "clean.npz" not in text
    assert np.allclose(np.asarray(motions["clean.npz"].trans), np.asarray(load(table, folder / "clean.npz")["clean.npz"].trans))


def test_reconstruction_checks_its_longest_window(folder):
    spec = copy.deepcopy(load_table_spec("reconstruction"))
    spec["grid"]["window"] = [2.0, 4.0]
    assert sorted(load("reconstruction", folder, spec)) == ["after.npz", "clean.npz"]


@pytest.mark.parametrize("table", ["table1", "denoise"])
def test_nothing_usable_left_is_an_error_naming_every_motion(folder, table):
    for name in ("clean.npz", "after.npz", "late_hole.npz"):
        (folder / name).unlink()
    with pytest.raises(ValueError, match=r"no usable motion is left: every one of the 2 .*hole\.npz .*frames are "
                                         r"missing between 0\.967 s and 2\.000 s.*teleport\.npz .*the root moves 5\.00 m"):
        load(table, folder)


def test_default_split_loses_no_motion():
    """The synthetic test split: every motion passes (no hole, no root step near 20 m/s)."""
    from benchmark.core.plausibility import window_defect
    from benchmark.synthetic.splits import build_split

    motions = build_split("test")
    assert len(motions) == 170
    assert [m.source for m in motions if window_defect(m, -1e9, 1e9) is not None] == []


def test_a_plug_in_protocol_s_default_loader_checks_its_window(folder, caplog):
    """A table added by entry point that keeps the default ``Protocol.load_motions`` gets the same
    check over its spec's window (``window_start_s`` + ``window_s``)."""
    from benchmark.protocols.base import Protocol

    spec = {"data": {"window_s": 2.0}}
    with caplog.at_level(logging.WARNING, logger="benchmark.data.table_data"):
        motions = Protocol().load_motions(spec, str(folder), None)
    assert sorted(motions) == ["after.npz", "clean.npz", "late_hole.npz"]  # the late hole lies after 2 s
    assert "frames are missing between 0.967 s and 2.000 s" in caplog.text
    spec["data"]["window_start_s"] = 2.5  # 2.5-4.5 s: only the late hole is read
    assert sorted(Protocol().load_motions(spec, str(folder), None)) == ["after.npz", "clean.npz", "hole.npz",
                                                                        "teleport.npz"]
