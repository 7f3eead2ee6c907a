"""Batched SLERP/LERP to output timestamps, against a naive per-element reference."""

import roma
import torch

from benchmark.core.interpolate import bracket, lerp_frames, slerp_frames


def _naive_lerp(x, src, dst):
    out = torch.empty(x.shape[0], dst.shape[1], *x.shape[2:], dtype=x.dtype)
    for b in range(x.shape[0]):
        for k, t in enumerate(dst[b].tolist()):
            s = src[b].tolist()
            if t <= s[0]:
                out[b, k] = x[b, 0]
            elif t >= s[-1]:
                out[b, k] = x[b, -1]
            else:
                i = max(j for j in range(len(s)) if s[j] <= t)
                i = min(i, len(s) - 2)
                w = (t - s[i]) / (s[i + 1] - s[i])
                out[b, k] = (1 - w) * x[b, i] + w * x[b, i + 1]
    return out


def test_lerp_matches_naive_including_clamping():
    g = torch.Generator().manual_seed(0)
    src = torch.tensor([[0.0, 0.2, 0.4, 0.6], [0.1, 0.2, 0.5, 0.9]], dtype=torch.float64)
    dst = torch.tensor([[-0.1, 0.0, 0.05, 0.3, 0.6, 0.7], [0.0, 0.15, 0.2, 0.35, 0.9, 1.2]], dtype=torch.float64)
    x = torch.randn(2, 4, 3, generator=g)
    assert torch.allclose(lerp_frames(x, src, dst), _naive_lerp(x, src, dst), atol=1e-6)


def test_slerp_hits_key_frames_and_midpoints():
    axis = torch.tensor([0.0, 1.0, 0.0])
    R = roma.rotvec_to_rotmat(torch.stack([axis * 0.0, axis * 1.0])).reshape(1, 2, 1, 3, 3)
    src = torch.tensor([[0.0, 1.0]], dtype=torch.float64)
    dst = torch.tensor([[0.0, 0.25, 0.5, 1.0, 2.0]], dtype=torch.float64)
    out = slerp_frames(R, src, dst)[0, :, 0]
    angles = roma.rotmat_to_rotvec(out)[:, 1]
    assert torch.allclose(angles, torch.tensor([0.0, 0.25, 0.5, 1.0, 1.0]), atol=1e-5)


def test_bracket_single_source_frame_holds():
    i0, i1, w = bracket(torch.tensor([[0.3]]), torch.tensor([[0.0, 0.3, 1.0]]))
    assert (i0 == 0).all() and (i1 == 0).all() and (w == 0).all()
