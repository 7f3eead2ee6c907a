"""``python -m benchmark perf``: speed of the hot paths, measured side by side in one run.

Reports ratios between implementations measured in the same process (never absolute targets
checked against another machine's numbers).
"""

from __future__ import annotations

import time

import torch


def _timeit(fn, repeats: int = 3) -> float:
    fn()  # warm-up
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t0)
    return best


def skinning_perf(device: str = "cpu", frames: int = 240) -> dict:
    """Embedded body: frames per second, forward and forward+backward, batch of `frames` frames."""
    import roma

    from benchmark.body.anny_body import load_anny_body

    body = load_anny_body(device)
    g = torch.Generator().manual_seed(0)
    rot6 = (torch.randn(1, frames, 22, 3, generator=g) * 0.3).to(device)
    trans = torch.zeros(1, frames, 3, device=device)
    shape = body.default_shape(1).to(device)

    def fwd():
        with torch.no_grad():
            body(roma.rotvec_to_rotmat(rot6), trans, shape)

    def fwd_bwd():
        r = rot6.clone().requires_grad_(True)
        s = shape.clone().requires_grad_(True)
        out = body(roma.rotvec_to_rotmat(r), trans, s)
        out.vertices.sum().backward()

    t_f, t_fb = _timeit(fwd), _timeit(fwd_bwd)
    return {"frames": frames, "vertices": body.num_vertices, "forward_fps": frames / t_f, "forward_backward_fps": frames / t_fb}


def run_perf(device: str = "cpu", quick: bool = True) -> dict:
    from benchmark.metrics.perf import chamfer_perf

    print(f"device: {device}, torch {torch.__version__}, threads {torch.get_num_threads()}")
    sk = skinning_perf(device, frames=240)
    print(
        f"body skinning (Anny, {sk['vertices']} vertices, batch of {sk['frames']} frames): "
        f"forward {sk['forward_fps']:.0f} frames/s, forward+backward {sk['forward_backward_fps']:.0f} frames/s"
    )
    ch = chamfer_perf(frames=4 if quick else 16, device=device)
    print("chamfer (forward+backward, per frame):")
    for key, value in ch.items():
        print(f"  {key}: {value:.4g}" if isinstance(value, float) else f"  {key}: {value}")
    return {"skinning": sk, "chamfer": ch}
