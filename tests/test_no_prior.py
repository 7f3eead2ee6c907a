"""The no-prior baseline: free per-observed-frame 6D rotations."""

import pytest
import roma
import torch

from priors.base import FitBatch
from priors.no_prior import NoPrior


def _batch(B: int, n: int) -> FitBatch:
    return FitBatch(
        points=torch.zeros(B, n, 4, 3),
        lengths=torch.full((B, n), 4),
        timestamps=torch.arange(n, dtype=torch.float32).expand(B, n) * 0.1,
        window_s=4.0,
        output_timestamps=torch.arange(120, dtype=torch.float32).expand(B, 120) / 30,
    )


def test_declarations():
    p = NoPrior()
    assert p.name == "no-prior" and p.window.kind == "per-frame"
    assert not p.encodes_translation and not p.encodes_root_orientation
    assert p.joints == tuple(range(1, 22)) and p.sixd_layout == "interleaved"
    assert p.parameter_count() == 0
    with pytest.raises(ValueError, match="no weights"):
        NoPrior(weights="/some/file")


def test_init_is_identity_and_deterministic():
    p = NoPrior()
    lat = p.init_latents(_batch(2, 6), torch.Generator().manual_seed(0))
    assert set(lat) == {"pose"} and lat["pose"].shape == (2, 6, 21, 6)
    assert torch.equal(lat["pose"][0, 0, 0], torch.tensor([1.0, 0.0, 0.0, 1.0, 0.0, 0.0]))
    assert torch.equal(lat["pose"], p.init_latents(_batch(2, 6), torch.Generator().manual_seed(99))["pose"])
    R = p.decode(lat, torch.zeros(2, 6)).rotations
    assert R.shape == (2, 6, 22, 3, 3)
    torch.testing.assert_close(R, torch.eye(3).expand(2, 6, 22, 3, 3))


def test_decode_hand_example_and_round_trip():
    p = NoPrior()
    pose = p.init_latents(_batch(1, 2), torch.Generator())["pose"].clone()
    # interleaved: a1 = elements (0, 2, 4) = (0, 1, 0), a2 = (1, 3, 5) = (-1, 0, 0) -> Rz(+90 deg)
    pose[0, 1, 4] = torch.tensor([0.0, -1.0, 1.0, 0.0, 0.0, 0.0])
    R = p.decode({"pose": pose}, torch.zeros(1, 2)).rotations
    torch.testing.assert_close(R[0, 1, 5], torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    torch.testing.assert_close(R[0, 1, 0], torch.eye(3))  # root stays identity
    # random rotations -> their first two columns, row-major -> the same rotations
    Rr = roma.random_rotmat((1, 2, 21), generator=torch.Generator().manual_seed(2))
    six = Rr[..., :, :2].reshape(1, 2, 21, 6)
    torch.testing.assert_close(p.decode({"pose": six}, torch.zeros(1, 2)).rotations[:, :, 1:], Rr)


def test_gradients_prior_term_and_errors():
    p = NoPrior()
    pose = (torch.randn(3, 4, 21, 6, generator=torch.Generator().manual_seed(1))).requires_grad_()
    R = p.decode({"pose": pose}, torch.zeros(3, 4)).rotations
    torch.testing.assert_close(R.transpose(-1, -2) @ R, torch.eye(3).expand_as(R), atol=1e-5, rtol=0)
    R[..., 2, 0].sum().backward()
    assert pose.grad is not None and pose.grad.abs().sum() > 0
    assert torch.equal(p.prior_term({"pose": pose}), torch.zeros(3))
    with pytest.raises(ValueError, match="per-frame"):
        p.decode({"pose": pose}, torch.zeros(3, 5))
    with pytest.raises(ValueError, match=r"\(B, n, 21, 6\)"):
        p.decode({"pose": pose[..., :3]}, torch.zeros(3, 4))
