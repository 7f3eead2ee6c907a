"""ONNX export of prior decoders (benchmark/tools/export_onnx.py), VPoser's export/encode/paper-network
additions and no-prior's export refusal and encode_motion."""

import json

import numpy as np
import onnxruntime as ort
import pytest
import roma
import torch
from torch import nn

from benchmark.tools.export_onnx import (
    NotExportableError,
    ParityError,
    check_parity,
    export_onnx,
    sha256_file,
    sidecar_path,
)
from priors.base import ExportableDecoder, ExportSpec
from priors.no_prior import NoPrior
from priors.vposer import VPoserSlerp
from priors.vposer.checkpoint import DEFAULT_WEIGHTS


@pytest.fixture(scope="module")
def vposer():
    if not DEFAULT_WEIGHTS.exists():
        pytest.skip(f"embedded weights missing: {DEFAULT_WEIGHTS}")
    return VPoserSlerp()


@pytest.fixture(scope="module")
def exported(vposer, tmp_path_factory):
    path = tmp_path_factory.mktemp("onnx") / "vposer.onnx"
    record = export_onnx(vposer, path)
    return path, record


def _run(path, z):
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return session.run(["rotations"], {"z": z.numpy()})[0]


def test_export_matches_decode_at_several_batch_sizes(vposer, exported):
    path, record = exported
    assert path.exists() and record["parity"]["ok"] and record["parity"]["batch"] == 3
    for batch in (1, 5):  # the trace used batch 2: the batch dimension is really dynamic
        result = check_parity(vposer, path, batch=batch)
        assert result["ok"] and result["outputs"]["rotations"]["shape"] == [batch, 22, 3, 3]
        assert result["max_abs_error"] < 1e-5
    # the exported graph computes what the adapter's decode computes (joint 0 identity, 1..21 VPoser)
    z = torch.randn(5, 32, generator=torch.Generator().manual_seed(3))
    onnx_rot = _run(path, z)
    ref = vposer.decode({"z": z[None]}, torch.zeros(1, 5)).rotations[0].numpy()
    np.testing.assert_allclose(onnx_rot, ref, atol=1e-5)
    np.testing.assert_array_equal(onnx_rot[:, 0], np.broadcast_to(np.eye(3, dtype=np.float32), (5, 3, 3)))


def test_sidecar_record(vposer, exported):
    path, record = exported
    side = json.loads(sidecar_path(path).read_text())
    assert sidecar_path(path) == path.with_suffix(".json")
    assert side == json.loads(json.dumps(record))
    assert side["prior"] == "vposer-slerp" and side["size"] == "embedded" and side["opset"] == 17
    assert side["weights_sha256"] == sha256_file(DEFAULT_WEIGHTS)
    assert side["onnx_sha256"] == sha256_file(path) and side["onnx_bytes"] == path.stat().st_size
    assert side["inputs"] == [{"name": "z", "shape": ["batch", 32], "dtype": "float"}]
    assert side["outputs"] == [{"name": "rotations", "shape": ["batch", 22, 3, 3], "dtype": "float"}]
    assert side["dynamic_axes"] == {"z": {"0": "batch"}, "rotations": {"0": "batch"}}
    assert side["versions"]["torch"] == torch.__version__ and side["versions"]["onnxruntime"] == ort.__version__
    parity = side["parity"]
    assert parity["ok"] and parity["example_batch"] == 2 and 0 <= parity["max_abs_error"] < 1e-5
    assert parity["tolerance_used"] <= 1.0
    assert side["decoder_parameters"] == 106_622  # embedded decoder: 32*256+256 + 256*256+256 + 256*126+126


def test_refuses_to_overwrite(vposer, exported, tmp_path):
    path, _ = exported
    before = path.read_bytes(), sidecar_path(path).read_text()
    with pytest.raises(FileExistsError, match="--force"):
        export_onnx(vposer, path, check=False)
    assert (path.read_bytes(), sidecar_path(path).read_text()) == before
    # a record alone also blocks; overwrite=True replaces only what an export wrote: not a .json
    # it did not write (a training record beside its checkpoint), then both of its own files
    other = tmp_path / "other.onnx"
    sidecar_path(other).write_text("{}")
    with pytest.raises(FileExistsError, match="other.json"):
        export_onnx(vposer, other, check=False)
    with pytest.raises(ValueError, match="not written by export-onnx"):
        export_onnx(vposer, other, check=False, overwrite=True)
    assert sidecar_path(other).read_text() == "{}" and not other.exists()
    sidecar_path(other).unlink()
    export_onnx(vposer, other, check=False)
    record = export_onnx(vposer, other, check=False, overwrite=True)
    assert other.exists() and record["parity"]["ok"] is None
    assert json.loads(sidecar_path(other).read_text())["onnx_sha256"] == sha256_file(other)
    with pytest.raises(ValueError, match=r"\.onnx"):
        export_onnx(vposer, tmp_path / "model.bin")


class _FrozenBatch(nn.Module):
    """A trace that records the example's batch size as a constant (int() on a shape)."""

    def forward(self, x):
        return x.new_zeros(int(x.shape[0]), x.shape[1]) + 2 * x


class _Adapter(ExportableDecoder):
    name, size, paper, weights_path = "frozen", "embedded", "", None

    def __init__(self, module):
        self.module = module

    def export_decoder(self):
        return ExportSpec(self.module, (torch.randn(2, 4),), ["x"], ["y"])


def test_frozen_batch_is_caught_and_leaves_no_file(tmp_path):
    path = tmp_path / "frozen.onnx"
    with pytest.raises(ParityError, match="batch 3"):
        export_onnx(_Adapter(_FrozenBatch()), path)
    assert list(tmp_path.iterdir()) == []
    export_onnx(_Adapter(_FrozenBatch()), path, check=False)  # exports; only the check can see it
    with pytest.raises(ParityError):
        check_parity(_Adapter(_FrozenBatch()), path, batch=1)


def test_parity_outside_tolerance_names_output_and_numbers(tmp_path):
    lin = nn.Linear(4, 3)
    path = tmp_path / "lin.onnx"
    export_onnx(_Adapter(lin), path)
    with torch.no_grad():
        lin.bias += 0.01  # PyTorch now differs from the file by 0.01
    with pytest.raises(ParityError, match="'y'.*max abs error 0.01") as info:
        check_parity(_Adapter(lin), path, batch=4)
    assert isinstance(info.value, AssertionError) and not info.value.result["ok"]
    assert info.value.result["max_abs_error"] == pytest.approx(0.01, rel=1e-3)
    with pytest.raises(ValueError, match="differ from the example"):
        check_parity(_Adapter(lin), path, batch=2)


def test_no_prior_is_not_exportable(tmp_path):
    with pytest.raises(NotImplementedError, match="no decoder network"):
        NoPrior().export_decoder()
    with pytest.raises(NotExportableError, match="no-prior"):
        export_onnx(NoPrior(), tmp_path / "np.onnx")
    assert list(tmp_path.iterdir()) == []


def test_vposer_paper_network_random_weights():
    net = VPoserSlerp.paper_network()
    assert sum(p.numel() for p in net.parameters()) == 936_252
    assert not net.training and net.hidden == 512 and net.latent == 32


def test_vposer_encode_motion_round_trip_beats_a_random_latent(vposer):
    g = torch.Generator().manual_seed(1)
    B, T = 2, 6
    ts = torch.arange(T, dtype=torch.float32).expand(B, T) / 30
    # in-distribution poses: decoded from latents, with a random root that the encoder must ignore
    rot = vposer.decode({"z": 0.7 * torch.randn(B, T, 32, generator=g)}, ts).rotations.clone()
    rot[:, :, 0] = roma.random_rotmat(B * T).reshape(B, T, 3, 3)
    lat = vposer.encode_motion(rot, torch.zeros(B, T, 3), ts)
    assert set(lat) == {"z"} and lat["z"].shape == (B, T, 32) and not lat["z"].requires_grad
    assert torch.equal(lat["z"], vposer.encode_motion(rot, torch.zeros(B, T, 3), ts)["z"])  # deterministic

    def err(decoded):
        return roma.rotmat_geodesic_distance(decoded.rotations[:, :, 1:], rot[:, :, 1:]).mean().item()

    rec = err(vposer.decode(lat, ts))
    rnd = err(vposer.decode({"z": torch.randn(B, T, 32, generator=g)}, ts))
    assert rec < 0.3 * rnd, (rec, rnd)
    with pytest.raises(ValueError, match=r"\(B, T, 22, 3, 3\)"):
        vposer.encode_motion(rot[:, :, 1:], None, ts)
    with pytest.raises(ValueError, match="timestamps"):
        vposer.encode_motion(rot, None, ts[:, :3])


def test_no_prior_encode_motion_is_exact():
    prior = NoPrior()
    assert not prior.has_encoder
    B, T = 2, 4
    rot = roma.random_rotmat(B * T * 22).reshape(B, T, 22, 3, 3)
    ts = torch.arange(T, dtype=torch.float32).expand(B, T)
    lat = prior.encode_motion(rot, torch.zeros(B, T, 3), ts)
    assert lat["pose"].shape == (B, T, 21, 6)
    out = prior.decode(lat, ts).rotations
    torch.testing.assert_close(out[:, :, 1:], rot[:, :, 1:], atol=1e-5, rtol=0)
    assert torch.equal(out[:, :, 0], torch.eye(3).expand(B, T, 3, 3))
    with pytest.raises(ValueError, match="trans"):
        prior.encode_motion(rot, torch.zeros(B, T, 2), ts)


def test_an_opset_too_old_for_the_decoder_is_one_line_naming_the_minimum(tmp_path, capfd):
    """Motion-DVAE's decoder needs opset 13 (aten::unflatten): the error names --opset and 13, and
    torch's dump of the whole graph stays off the terminal; no file is left."""
    from benchmark.cli import main

    out = tmp_path / "md.onnx"
    assert main(["export-onnx", "motion-dvae", "--opset", "11", "--out", str(out)]) == 2
    captured = capfd.readouterr()
    assert "--opset 11: motion-dvae's decoder uses the operator aten::unflatten, which ONNX has from opset 13" in captured.err
    assert "Torch IR graph" not in captured.out + captured.err
    assert not any(tmp_path.iterdir())
