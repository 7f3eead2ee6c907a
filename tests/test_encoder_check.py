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


def test_weights_build_the_adapter_from_the_given_checkpoint(anny_body, monkeypatch):
    from benchmark.run import registry
    from priors.vposer.checkpoint import DEFAULT_WEIGHTS

    built = []
    real = registry.make_adapter

    def spy(name, size="embedded", weights=None, device="cpu"):
        built.append((name, size, weights))
        return real(name, size=size, weights=weights, device=device)

    monkeypatch.setattr(registry, "make_adapter", spy)
    kw = dict(sequences=1, window_s=1.0, noise_deg=(0.0,))
    given = check_encoders(["vposer-slerp"], anny_body, weights={"vposer-slerp": str(DEFAULT_WEIGHTS)}, **kw)
    plain = check_encoders(["vposer-slerp"], anny_body, **kw)
    assert built == [("vposer-slerp", "embedded", str(DEFAULT_WEIGHTS)), ("vposer-slerp", "embedded", None)]
    assert given[0]["decoded_mm"] == plain[0]["decoded_mm"]  # the embedded file, named: the same encoder
    with pytest.raises(ValueError, match="not checked"):
        check_encoders(["vposer-slerp"], anny_body, weights={"hmvae": str(DEFAULT_WEIGHTS)}, **kw)


def test_cli_weights_name_a_missing_file_before_any_work(tmp_path, capsys):
    from benchmark.cli import main

    missing = tmp_path / "nope.pt"
    for argv, message in ((["--weights", f"motion-dvae={missing}"], "nope.pt: no such file"),
                          (["--weights", "motion-dvae"], "must look like NAME=VALUE"),
                          (["--weights", f"hmvae={missing}"], "not checked")):
        assert main(["encoder-check", "--prior", "motion-dvae", *argv]) == 2
        err = capsys.readouterr().err
        assert message in err and "MPJPE" not in err, err


def test_a_window_longer_than_every_motion_is_named(anny_body):
    with pytest.raises(ValueError, match=r"synthetic test split: every motion is shorter than the 1000\.0 s window.*--window"):
        check_encoders(["vposer-slerp"], anny_body, sequences=1, window_s=1000.0, noise_deg=(0.0,))


def test_cli_numbers_are_range_checked(capsys):
    from benchmark.cli import main

    for argv, message in ((["--seed", "-1"], "argument --seed: -1 is out of range"),
                          (["--sequences", "0"], "argument --sequences: 0 is out of range"),
                          (["--window", "nan"], "argument --window"),
                          (["--noise-deg", "-2"], "argument --noise-deg: -2 is out of range")):
        with pytest.raises(SystemExit) as exc:
            main(["encoder-check", "--prior", "vposer-slerp", *argv])
        assert exc.value.code == 2 and message in capsys.readouterr().err
