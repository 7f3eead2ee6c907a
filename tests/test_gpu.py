"""Checks that need a CUDA device (``python -m pytest -m gpu``; skipped without one): the paths the
CPU suite cannot exercise, each a defect a CPU imitation of CUDA found (docs/history.md, GPU runs).

- Motion-DVAE's fits differentiate the latents through its frozen LSTMs: cuDNN computes an RNN's
  backward only in training mode (``priors.motion_dvae.adapter.cudnn_rnn_backward``).
- sls's dense columns degrade scans sampled on the device with lengths that were on the CPU.
- One smoke unit of every table and prior runs on the device: ``python -m benchmark device-check``.
- The data of a table is made on the CPU whatever the device (``BodyModel.on_cpu``): a GPU run fits
  the very observations a CPU run does, with the same fingerprints and the same loss vertices.
"""

from __future__ import annotations

import pytest
import torch

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]


def test_motion_dvae_latents_get_gradients_through_its_frozen_lstms_on_cuda():
    from benchmark.run.registry import make_adapter
    from priors.base import FitBatch

    adapter = make_adapter("motion-dvae", device="cuda")
    t = torch.arange(60, dtype=torch.float64)[None] / 30.0  # the prior's 2 s window at 30 fps
    batch = FitBatch(points=torch.zeros(1, 60, 1, 3, device="cuda"), lengths=torch.ones(1, 60, dtype=torch.long,
                     device="cuda"), timestamps=t.cuda(), window_s=2.0, output_timestamps=t.cuda())
    latents = {k: v.detach().clone().requires_grad_(v.is_floating_point())
               for k, v in adapter.mean_latents(batch).items()}
    out = adapter.decode(latents, t.cuda())
    loss = out.rotations.square().sum() + adapter.prior_term(latents).sum()
    loss.backward()
    assert all(v.grad is not None and torch.isfinite(v.grad).all() for v in latents.values() if v.requires_grad)
    assert not any(m.training for m in adapter.modules() if isinstance(m, torch.nn.RNNBase))  # put back


def test_sls_dense_column_and_table1_units_run_on_cuda(tmp_path):
    from benchmark.body.anny_body import load_anny_body
    from benchmark.run.catalog import get_profile, load_table_spec
    from benchmark.run.table_run import run_table

    body = load_anny_body("cuda")  # its own copy: the session's CPU body (the anny_body fixture) stays where it is
    for name, grid in (("sls", {"sweep": ["p100"]}), ("table1", {"points": [100], "fps": [5]})):
        spec = {**load_table_spec(name), "grid": grid}
        result = run_table(spec, get_profile("smoke", table=name), ["no-prior", "motion-dvae"], body, "cuda", 0,
                           tmp_path / name, backend_options={"jobs": 1})
        assert not result["failures"], result["failures"]


def test_a_cuda_run_fits_the_observations_a_cpu_run_fits(tmp_path, anny_body):
    import json

    from benchmark.body.anny_body import load_anny_body
    from benchmark.run.catalog import get_profile, load_table_spec
    from benchmark.run.table_run import run_table

    body = load_anny_body("cuda")
    assert body.on_cpu().faces.device.type == "cpu" and anny_body.faces.device.type == "cpu"
    assert torch.equal(body.loss_vertex_indices(3000).cpu(), anny_body.loss_vertex_indices(3000))
    for name, grid in (("sls", {"sweep": ["p100"]}), ("table1", {"points": [100], "fps": [5]})):
        spec = {**load_table_spec(name), "grid": grid}
        prints = []
        for device, b in (("cpu", anny_body), ("cuda", body)):
            profile = {**get_profile("smoke", table=name), "steps": 2}
            result = run_table(spec, profile, ["no-prior"], b, device, 0, tmp_path / name / device, backend_options={"jobs": 1})
            assert not result["failures"], result["failures"]
            (unit,) = sorted((tmp_path / name / device / "units").glob("*.json"))
            prints.append(json.loads(unit.read_text())["fingerprint"])
        assert prints[0] == prints[1], name
