"""The tables make their data on the CPU whatever the run's device (``BodyModel.on_cpu``; on a GPU
``tests/test_gpu.py`` checks that a CUDA run fits the observations a CPU run fits, fingerprint for
fingerprint). On the CPU the body is its own CPU body: no copy is made, and nothing moves."""

from __future__ import annotations

import torch

from benchmark.body import base


def test_a_cpu_body_is_its_own_cpu_body_and_keeps_its_loss_vertices(anny_body):
    assert anny_body.on_cpu() is anny_body and anny_body not in base._CPU_COPIES
    first = anny_body.loss_vertex_indices(300)
    assert first.device.type == "cpu" and anny_body.loss_vertex_indices(300) is first  # chosen once
    assert first.unique().numel() == 300 and anny_body.loss_vertex_indices(10**9) is None


def test_every_table_source_builds_on_the_cpu_body(anny_body):
    from benchmark.protocols.completion_unit import CompletionData
    from benchmark.protocols.denoise import DenoiseSource
    from benchmark.protocols.sls_data import SlsData

    for source in (CompletionData({}, anny_body, {}, 0), SlsData({}, anny_body, {}, 0)):
        assert source.body is anny_body
    spec = {"data": {"fps": 30, "window_s": 1.0, "num_markers": 12}}
    markers = DenoiseSource(spec, anny_body, {}, 0).marker_indices()
    assert markers.device.type == "cpu" and markers.shape == (12,) and markers.dtype == torch.long
