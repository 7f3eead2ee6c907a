"""encoder-check: encode -> decode error of a prior's encoder, clean and under per-frame joint noise."""

import pytest
import torch

from benchmark.tools.encoder_check import check_encoders, format_rows, joint_noise


def test_joint_noise_turns_the_body_joints_only_and_is_seeded():
    rot = torch.eye(3).expand(2, 5, 22, 3, 3).clone()
    a = joint_noise(rot, 2.0, torch.Generator().manual_seed(0))
    b = joint_noise(rot, 2.0, torch.Generator().manual_seed(0))
    assert torch.equal(a, b) and torch.equal(a[:, :, 0], rot[:, :, 0])
    angle = torch.arccos(((a[:, :, 1:].diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1))
    assert 0.01 < float(angle.mean()) < 0.1  # about 2 deg x sqrt(8/pi) per joint, in radians
    assert joint_noise(rot, 0.0, torch.Generator()) is rot


def test_a_per_frame_encoder_projects_noise_and_a_prior_without_encoder_is_na(anny_body):
    rows = check_encoders(["vposer-slerp", "no-prior"], anny_body, sequences=2, window_s=1.0, noise_deg=(0.0, 2.0))
    clean, noisy, na = rows
    assert (clean["prior"], clean["noise_deg"], clean["input_mm"]) == ("vposer-slerp", 0.0, 0.0)
    assert 0 < clean["decoded_mm"] < 20 and len(clean["per_sequence_mm"]) == 2
    # VPoser's encoder maps a joint-noised pose back towards its manifold: below the noise's own error
    assert noisy["input_mm"] > 10 and clean["decoded_mm"] < noisy["decoded_mm"] < noisy["input_mm"]
    assert na["prior"] == "no-prior" and "no encoder" in na["na"]
    text = format_rows(rows)
    assert "| vposer-slerp | 2 |" in text and "| no-prior | n/a |" in text


@pytest.mark.parametrize("kw, message", [({"window_s": 0.0}, "--window"), ({"sequences": 0}, "--sequences"),
                                         ({"noise_deg": (-1.0,)}, "--noise-deg")])
def test_bad_options_are_named(anny_body, kw, message):
    with pytest.raises(ValueError, match=message):
        check_encoders(["vposer-slerp"], anny_body, **kw)
