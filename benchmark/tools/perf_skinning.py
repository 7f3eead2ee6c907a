"""Skinning rows of ``python -m benchmark perf``: the embedded body's frames per second, and the
fits' loss-vertex skinning in its reference form against the one-GEMM form, side by side."""

from __future__ import annotations

import contextlib

import torch

from benchmark.tools.perf_clock import timeit


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

    t_f, t_fb = timeit(fwd), timeit(fwd_bwd)
    return {"frames": frames, "vertices": body.num_vertices, "forward_fps": frames / t_f, "forward_backward_fps": frames / t_fb,
            "loss_vertices": loss_vertex_skinning_compare(body, device)}


def loss_vertex_skinning_compare(body, device: str = "cpu", sequences: int = 8, frames: int = 100,
                                 vertices: int = 3000) -> dict:
    """The fits' skinning of their loss vertices (one rest mesh per sequence posed in every frame;
    the sls quick profile's sizes), forward + backward: the reference form (a 3 x 4 matrix per vertex
    and frame) against the one-GEMM form the body uses for a vertex subset; seconds and the largest
    coordinate difference (m)."""
    import roma

    from benchmark.body.lbs import shared_rest_blend_skinning

    g = torch.Generator().manual_seed(0)
    idx = body.loss_vertex_indices(vertices).to(device)
    rest = body.prepare(body.default_shape(sequences).to(device))
    rot = roma.rotvec_to_rotmat(torch.randn(sequences, frames, 22, 3, generator=g) * 0.3).to(device)
    S, _ = body._joint_transforms(rest, rot)
    S = S.detach()
    v0, w = rest.vertices[:, idx].detach(), body.weights[idx]
    forms = {"reference": reference_subset_skinning, "gemm": shared_rest_blend_skinning}
    res = {"sequences": sequences, "frames": frames, "vertices": int(idx.numel())}
    outs = {}
    for name, form in forms.items():
        def step():
            v, T = v0.clone().requires_grad_(True), S.clone().requires_grad_(True)
            out = form(v, w, T)
            out.square().sum().backward()
            outs[name] = out.detach()
        res[f"{name}_s"] = timeit(step)
    res["gemm_vs_reference"] = res["gemm_s"] / res["reference_s"]
    res["max_abs_diff_m"] = float((outs["gemm"] - outs["reference"]).abs().max())
    return res


def reference_subset_skinning(vertices: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """``shared_rest_blend_skinning``'s signature, computed in the reference form (a 3 x 4 matrix per
    vertex and frame): the "before" of the side-by-side timings."""
    from benchmark.body.lbs import linear_blend_skinning

    return linear_blend_skinning(vertices[:, None], weights, transforms)


@contextlib.contextmanager
def subset_skinning(form: str):
    """The Anny body's loss-vertex skinning in ``form``: "gemm" (what the body uses) or "reference"
    (the 3 x 4 matrix per vertex and frame it used before 2026-12-06), for a side-by-side timing."""
    from benchmark.body import anny_body

    used = anny_body.shared_rest_blend_skinning
    if form == "reference":
        anny_body.shared_rest_blend_skinning = reference_subset_skinning
    try:
        yield
    finally:
        anny_body.shared_rest_blend_skinning = used


__all__ = ["skinning_perf", "loss_vertex_skinning_compare", "reference_subset_skinning", "subset_skinning"]
