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


def test_a_body_read_from_a_file_enters_the_data_hash_and_a_motions_file_path_does_not(tmp_path):
    """Another SMPL file (kind, gender or content) reruns the units: it used to reuse the previous
    body's numbers under the new body's name. The embedded Anny body leaves the hashes as stored. A
    motion read from another path (a moved --data folder) hashes the same."""
    import types

    from benchmark.core.motion import Motion
    from benchmark.run.table_run import body_identity, motion_sha256, with_body

    a, b = tmp_path / "SMPLH_MALE.npz", tmp_path / "SMPLX_NEUTRAL.npz"
    a.write_bytes(b"one model")
    b.write_bytes(b"another model")
    smplh = types.SimpleNamespace(name="smplh-male", model_type="smplh", shape_dim=10, source_path=a)
    smplx = types.SimpleNamespace(name="smplx-neutral", model_type="smplx", shape_dim=10, source_path=b)
    anny = types.SimpleNamespace(name="anny", shape_dim=6)
    assert body_identity(anny) is None and with_body("h", None) == "h"
    hashes = {with_body("h", body_identity(x)) for x in (smplh, smplx)}
    assert len(hashes) == 2 and "h" not in hashes
    b.write_bytes(b"one model")  # the same content under another name and kind is still another body
    assert with_body("h", body_identity(smplx)) != with_body("h", body_identity(smplh))

    motion = Motion(poses=torch.zeros(3, 22, 3), trans=torch.zeros(3, 3), timestamps=torch.arange(3) / 30.0,
                    meta={"format": "amass", "file": "/data/AMASS/a_poses.npz"})
    moved = Motion(poses=motion.poses, trans=motion.trans, timestamps=motion.timestamps,
                   meta={"format": "amass", "file": "../AMASS/a_poses.npz"})
    other = Motion(poses=motion.poses, trans=motion.trans, timestamps=motion.timestamps,
                   meta={"format": "amass", "file": "x", "gender": "male"})
    assert motion_sha256(motion) == motion_sha256(moved) != motion_sha256(other)
