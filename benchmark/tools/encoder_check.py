"""How a prior's encoder copes with a noisy motion: ``python -m benchmark encoder-check``.

The completion tables start every window prior with an encoder from the prior-free fit, encoded
(table1 ``start_search: observation``). That start is a per-frame fit: its joint angles are a few
degrees off, frame by frame. An encoder trained on clean motion alone may map such a motion far
off its manifold, and the fit then starts, and often ends, there. This check measures it on the
quick test windows, independently of any fit:

- the clean windows (``window`` seconds at 30 fps of the profile's test sequences, the
  reconstruction table's rules: the motion's own body shape, its root and translation given to the
  rigid parameters the prior does not decode) are encoded and decoded: ``clean`` is the
  reconstruction error (the prior's floor);
- the same windows with every body joint (not the root, not the translation) rotated by a random
  rotation of ``noise_deg`` degrees standard deviation per axis, drawn independently per frame
  (seeded), are encoded and decoded. ``input_mm`` is the noisy motion's own MPJPE against the
  clean one, ``decoded_mm`` the decoded motion's. A robust encoder gives ``decoded_mm`` close to
  ``clean`` or below ``input_mm``; one that is not gives more than either.

MPJPE: 22 joints, no alignment, mm, mean over every frame of every window; ``worst_mm`` the worst
window's mean.
"""

from __future__ import annotations

import copy
import math

import torch

NOISE_DEG = (0.0, 2.0, 5.0)


def joint_noise(rotations: torch.Tensor, noise_deg: float, generator: torch.Generator) -> torch.Tensor:
    """rotations (B, T, 22, 3, 3) with every body joint (1..21) turned by an independent random
    rotation per frame (axis-angle components N(0, noise_deg^2), degrees); the root is untouched."""
    import roma

    if noise_deg <= 0:
        return rotations
    B, T, J = rotations.shape[:3]
    aa = torch.randn(B, T, J - 1, 3, generator=generator, dtype=torch.float64) * math.radians(noise_deg)
    turn = roma.rotvec_to_rotmat(aa).to(rotations)
    return torch.cat([rotations[:, :, :1], turn @ rotations[:, :, 1:]], dim=2)


def check_options(sequences: int, window_s: float, noise_deg) -> None:
    """ValueError naming the option when one is out of range."""
    if not (math.isfinite(window_s) and window_s > 0):
        raise ValueError(f"encoder-check: --window must be > 0 seconds, got {window_s}")
    if sequences < 1:
        raise ValueError(f"encoder-check: --sequences must be >= 1, got {sequences}")
    bad = [n for n in noise_deg if not (math.isfinite(n) and n >= 0)]
    if bad:
        raise ValueError(f"encoder-check: --noise-deg must be finite and >= 0, got {bad}")


def check_encoders(priors: list[str], body, sequences: int = 8, window_s: float = 4.0,
                   noise_deg=NOISE_DEG, seed: int = 0, device: str = "cpu", size: str = "embedded",
                   weights: dict | None = None) -> list[dict]:
    """One row per (prior, noise): ``{"prior", "noise_deg", "input_mm", "decoded_mm", "worst_mm",
    "per_sequence_mm"}``; a prior without an encoder gets one row with ``"na"`` (the reason).
    ``size`` and ``weights`` ({prior: checkpoint path}) build the adapters as ``run`` does (a prior
    not in ``weights``: its embedded weights)."""
    from benchmark.core.work_units import select_sequences
    from benchmark.metrics.pose import mpjpe
    from benchmark.protocols.motion_fit import (MotionSource, MotionTargets, decode_parameters, init_motion_state,
                                                joints_of, load_table_motions)
    from benchmark.run.catalog import load_table_spec
    from benchmark.run.registry import check_weights_option, make_adapter
    from priors.base import has_motion_encoder

    check_options(sequences, window_s, noise_deg)
    weights = dict(weights or {})
    check_weights_option(weights, priors, "checked")
    adapters = {name: make_adapter(name, size=size, weights=weights.get(name), device=device) for name in priors}  # an unknown name fails before any data
    spec = copy.deepcopy(load_table_spec("reconstruction"))
    motions = load_table_motions(spec, None, body, longest_window_s=window_s)
    ids = select_sequences(motions, sequences)
    clean = MotionSource(spec, body, motions, seed).clean(ids, window_s)
    ts = clean.timestamps
    T = int(ts.shape[1])

    def mean_mm(rot, trans):
        with torch.no_grad():
            j = joints_of(body, clean.shapes, rot, trans)
        return [float(v) / T * 1000.0 for v in mpjpe(j, clean.joints, reduction="sum")]

    # the noisy inputs and their own error: the same for every prior
    inputs = []
    for noise in noise_deg:
        rot = joint_noise(clean.rotations, float(noise), torch.Generator().manual_seed(seed))
        given = mean_mm(rot, clean.trans)
        inputs.append((float(noise), rot, sum(given) / len(given)))
    rows = []
    for name, adapter in adapters.items():
        if not has_motion_encoder(adapter):
            rows.append({"prior": name, "na": "no encoder (has_encoder is False or encode_motion is missing)"})
            continue
        for noise, rot, input_mm in inputs:
            targets = MotionTargets(timestamps=ts, shapes=clean.shapes, window_s=window_s, joints=clean.joints,
                                    init_rotations=rot, init_trans=clean.trans)
            with torch.no_grad():
                latents = adapter.encode_motion(rot, clean.trans, ts)
                state = init_motion_state(adapter, body, targets, torch.Generator().manual_seed(seed), device,
                                          latents=latents)
                out_rot, out_trans = decode_parameters(state, ts)
            decoded = mean_mm(out_rot, out_trans)
            rows.append({"prior": name, "noise_deg": noise, "input_mm": input_mm,
                         "decoded_mm": sum(decoded) / len(decoded), "worst_mm": max(decoded),
                         "per_sequence_mm": decoded})
    return rows


def format_rows(rows: list[dict]) -> str:
    """A Markdown table of :func:`check_encoders`'s rows."""
    lines = ["| prior | joint noise (deg) | input MPJPE | decoded MPJPE | worst window |", "| --- | --: | --: | --: | --: |"]
    for r in rows:
        if "na" in r:
            lines.append(f"| {r['prior']} | n/a | {r['na']} | | |")
            continue
        lines.append(f"| {r['prior']} | {r['noise_deg']:g} | {r['input_mm']:.1f} | {r['decoded_mm']:.1f} | {r['worst_mm']:.1f} |")
    return "\n".join(lines)
