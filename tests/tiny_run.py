"""A table1 run through the real CLI, shrunk so that tests take seconds: one or two cells of 100
points, 1,000-point scans, 2 fit steps, 200 loss vertices (``tiny_table1(monkeypatch)`` patches the
catalog the CLI reads; the protocol code is the real one)."""

from __future__ import annotations

import copy

import numpy as np
import torch

import benchmark.run.catalog as catalog

_SPEC, _PROFILE = catalog.load_table_spec, catalog.get_profile


def tiny_table1(monkeypatch, fps=(5,)):
    def spec(name):
        s = copy.deepcopy(_SPEC(name))
        s["grid"] = {"points": [100], "fps": list(fps)}
        s["data"]["points_per_frame"] = 1000
        # the runner's mechanics (resume, locks, bodies, plug-ins), not the fit's rules: the cheap
        # version 1 start (T-pose heading score, no facing or limb search) keeps these runs at seconds
        s["objective"] = {**s["objective"], "facing": "heading8", "start_search": "none"}
        return s

    def profile(name, table=None):
        p = dict(_PROFILE("smoke", table))
        p.update(steps=2, surface_points=100, loss_vertices=200)
        return p

    monkeypatch.setattr(catalog, "load_table_spec", spec)
    monkeypatch.setattr(catalog, "get_profile", profile)


def write_motion(path, seed=0, seconds=4.0, scale=0.1, speed=0.0, shape=None, body=None):
    """A harness motion .npz: random small rotations, optional walk forward."""
    from benchmark.core.motion import Motion

    n = int(seconds * 30) + 1
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(n, dtype=torch.float64) / 30
    trans = torch.zeros(n, 3)
    trans[:, 2] = speed * t.float()
    Motion(poses=torch.randn(n, 22, 3, generator=g) * scale, trans=trans, timestamps=t, shape=shape, body=body,
           source="test", meta={"subject": "s"}).save(path)
    return path


def amass_file(path, seconds=4.0, betas=16, rate=30.0):
    """An AMASS-style SMPL-H .npz (poses (T, 156), trans, betas, mocap_framerate)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    n = int(seconds * rate) + 1
    rng = np.random.default_rng(0)
    np.savez(path, poses=rng.normal(0, 0.05, (n, 156)), trans=np.zeros((n, 3)), betas=rng.normal(0, 0.5, betas),
             mocap_framerate=np.array(rate), gender=np.array("neutral"))
    return path
