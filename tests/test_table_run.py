"""Loading user motion folders for a table run, and sequence selection."""

import torch

from benchmark.core.motion import Motion
from benchmark.data.table_data import load_motions
from benchmark.core.work_units import select_sequences


class _Body:
    name = "anny"
    shape_dim = 6


def _motion(seconds, shape=None, body=None, subject="s"):
    n = int(seconds * 30) + 1
    return Motion(poses=torch.zeros(n, 22, 3), trans=torch.zeros(n, 3),
                  timestamps=torch.arange(n, dtype=torch.float64) / 30, shape=shape, body=body,
                  source="test", meta={"subject": subject})


def test_load_motion_folder_skips_short_and_fixes_foreign_shapes(tmp_path):
    _motion(5.0, shape=torch.zeros(16), body="smplh").save(tmp_path / "a.npz")
    _motion(2.0).save(tmp_path / "short.npz")
    _motion(4.5, shape=torch.full((6,), 0.3), body="anny").save(tmp_path / "sub" / "b.npz")
    got = load_motions(str(tmp_path), 4.0, body=_Body())
    assert sorted(got) == ["a.npz", "sub/b.npz"]
    assert got["a.npz"].shape is None  # SMPL-H betas do not apply to the Anny body
    assert torch.allclose(got["sub/b.npz"].shape, torch.full((6,), 0.3))


def test_select_sequences_spreads_over_subjects():
    motions = {f"{s}_{i}": _motion(4.0, subject=s) for s in "abcd" for i in range(5)}
    chosen = select_sequences(motions, 4)
    assert len(chosen) == 4 and {c[0] for c in chosen} == set("abcd")
    assert select_sequences(motions, "all") == sorted(motions)
