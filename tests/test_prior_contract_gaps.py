"""Mistakes a prior author plausibly makes, each of which used to crash with a bare torch error, pass
the conformance kit and then break table1, or give a silent wrong number: each is now named by the
harness (the prior, the hook or declaration, the fix). One small adapter, varied per case."""

from __future__ import annotations

import pytest
import torch

from benchmark.core.rotations import matrix_to_sixd
from benchmark.protocols.fit_state import FitState, body_parameters
from priors.base import Decoded, FitBatch


def _docstring_example() -> type:
    """The minimal adapter of ``priors/base.py``'s docstring (``TPosePull``), run as written."""
    import textwrap

    import priors.base as base

    doc = base.__doc__
    block = doc[doc.index("::\n", doc.index("Minimal example:")) + 3:]
    lines = []
    for line in block.splitlines():
        if line.strip() and not line.startswith("    "):
            break
        lines.append(line)
    namespace: dict = {}
    exec(textwrap.dedent("\n".join(lines)), namespace)
    return namespace["TPosePull"]


class Pull(_docstring_example()):
    """The docstring example of priors/base.py: per-frame 6D poses pulled towards the T-pose."""

    name = "pull"


def _state(adapter, B=1, n=4):
    t = (torch.arange(n, dtype=torch.float64) / 5)[None].expand(B, n)
    batch = FitBatch(points=torch.zeros(B, n, 1, 3), lengths=torch.ones(B, n, dtype=torch.long), timestamps=t,
                     window_s=1.0, output_timestamps=t)
    latents = {k: v.requires_grad_(v.is_floating_point()) for k, v in adapter.init_latents(batch, torch.Generator()).items()}
    return FitState(adapter=adapter, latents=latents, shape_param=torch.zeros(B, 6), obs_t=t, window_s=1.0)


def test_decode_in_float64_is_named_not_a_dtype_error_inside_the_body():
    class Float64(Pull):
        def decode(self, latents, timestamps, shape=None):
            return Decoded(rotations=super().decode(latents, timestamps, shape).rotations.double())

    st = _state(Float64())
    with pytest.raises(ValueError, match=r"prior 'pull': decode returned rotations as torch.float64 on cpu, "
                                         r"expected torch.float32 on cpu .*cast"):
        body_parameters(st, st.obs_t, observed=True)
    body_parameters(_state(Pull()), st.obs_t, observed=True)  # the example itself passes


def test_decode_returning_a_tuple_is_named():
    class Pair(Pull):
        def decode(self, latents, timestamps, shape=None):
            return super().decode(latents, timestamps, shape).rotations, None

    st = _state(Pair())
    with pytest.raises(ValueError, match=r"prior 'pull': decode returned tuple, expected a priors.base.Decoded"):
        body_parameters(st, st.obs_t, observed=True)


def test_encodes_translation_without_a_decoded_translation_is_named():
    class NoTrans(Pull):
        encodes_translation = True

    st = _state(NoTrans())
    st.offset = torch.zeros(1, 3)  # what init_state frees for a prior that encodes translation
    with pytest.raises(ValueError, match=r"prior 'pull' declares encodes_translation = True but decode returned "
                                         r"trans=None.*or declare encodes_translation = False"):
        body_parameters(st, st.obs_t, observed=True)


def test_a_decoded_translation_under_encodes_translation_false_is_named():
    """A prior that declares encodes_translation = False (the protocol fits free per-frame
    translation) but returns trans anyway: the decoded translation used to be added silently to the
    free one; now the fit stops, naming the prior, the declaration and both fixes."""
    class StrayTrans(Pull):
        def decode(self, latents, timestamps, shape=None):
            rot = super().decode(latents, timestamps, shape).rotations
            return Decoded(rotations=rot, trans=torch.ones(*rot.shape[:2], 3))

    st = _state(StrayTrans())
    st.trans = torch.zeros(1, 4, 3)  # what init_state frees for a prior that does not encode translation
    with pytest.raises(ValueError, match=r"prior 'pull' declares encodes_translation = False but decode returned a "
                                         r"translation.*return trans=None.*or declare encodes_translation = True"):
        body_parameters(st, st.obs_t, observed=True)


def test_a_frozen_network_that_is_no_submodule_is_named_as_the_declaration():
    from benchmark.run.registry import make_adapter, register, unregister

    class WrongFrozen(Pull):
        frozen_network = "model"  # the network is self.net

        def __init__(self, size="embedded", weights=None, device="cpu"):
            super().__init__(size=size, weights=weights, device=device)
            self.net = torch.nn.Linear(3, 3)

    register("wrong-frozen", WrongFrozen)
    try:
        with pytest.raises(ValueError, match=r"prior 'pull' declares frozen_network = 'model', but has no submodule "
                                             r"of that name .*e.g. self.net = ... and frozen_network = 'net'"):
            make_adapter("wrong-frozen")
    finally:
        unregister("wrong-frozen")


def _check(cls, capsys):
    from benchmark.run.registry import register, unregister
    from benchmark.tools.conformance import check_prior

    register(cls.name, cls)
    try:
        ok = check_prior(cls.name, steps=3, verbose=True)
    finally:
        unregister(cls.name)
    return ok, capsys.readouterr().out


def test_check_prior_fails_a_prior_term_with_no_gradient(capsys):
    """A prior term computed from detached latents adds a constant: the fit has no prior at all,
    and table1 reports it as the prior's row."""

    class Detached(Pull):
        name = "detached-prior"

        def prior_term(self, latents):
            return super().prior_term({k: v.detach() for k, v in latents.items()})

    ok, out = _check(Detached, capsys)
    assert not ok, out
    assert "[FAIL] 100 pts / 5 fps: gradients reach the latents" in out
    assert "no gradient of it reaches the latents" in out and "no prior at all" in out


def test_check_prior_fails_a_nan_gradient_at_the_mean_start(capsys):
    """|z| (not squared) as the prior term and mean_latents at its minimum: the gradient there is NaN,
    so table1 (which starts at mean_latents) fails at its first step; check-prior used to fit from
    init_latents only and pass."""

    class Norm(Pull):
        name = "norm-prior"

        def mean_latents(self, batch):
            return {"pose": self.eye6.expand(batch.batch_size, batch.num_observed, 21, 6).clone()}

        def prior_term(self, latents):
            return (latents["pose"] - self.eye6).square().sum((-1, -2, -3)).sqrt()

    ok, out = _check(Norm, capsys)
    assert not ok, out
    assert "[FAIL] 100 pts / 5 fps: gradients at mean_latents" in out
    assert "prior_term's gradient at mean_latents (table1's start) is NaN or inf" in out


def test_nan_latents_are_named_as_a_gradient_problem_not_the_decoder():
    from benchmark.protocols.fit_state import _check_decoded

    rot = torch.full((1, 4, 22, 3, 3), float("nan"))
    with pytest.raises(ValueError, match=r"prior 'pull': its latents \['pose'\] are NaN or inf: a fit step had a NaN"):
        _check_decoded(Pull(), Decoded(rot, None), torch.zeros(1, 4), {"pose": torch.full((1, 4, 21, 6), float("nan"))})


def test_check_prior_fails_rotations_that_leave_so3_during_the_fit(capsys):
    """Raw 3x3 matrices as latents start orthonormal (the identity) and drift off during the fit: the
    mesh is then sheared and scaled to fit the points, a silent wrong number."""

    class RawMatrix(Pull):
        name = "raw-matrix"

        def init_latents(self, batch, generator):
            return {"pose": torch.eye(3).expand(batch.batch_size, batch.num_observed, 21, 3, 3).clone()}

        def decode(self, latents, timestamps, shape=None):
            body = latents["pose"]
            root = torch.eye(3, dtype=body.dtype).expand(*body.shape[:2], 1, 3, 3)
            return Decoded(rotations=torch.cat([root, body], dim=2))

        def prior_term(self, latents):
            return (latents["pose"] - torch.eye(3)).square().sum((-1, -2)).mean((-1, -2))

    ok, out = _check(RawMatrix, capsys)
    assert not ok, out
    assert "[FAIL] 100 pts / 5 fps: finite losses, determinism under a seed" in out
    assert "after 3 steps decode's rotations are not orthonormal" in out


def test_a_plugin_whose_class_name_differs_from_its_entry_point_is_still_identified(tmp_path, monkeypatch, capsys):
    """The units' spec records a plugged-in prior's distribution and version (a new release reruns its
    units) looked up by the name it is registered under, not by the class's ``name``, which used to
    find nothing (or another prior) when the two differ: a new release then reused the old numbers.
    check-prior fails the mismatch in its declaration row."""
    import json

    from tiny_run import tiny_table1, write_motion

    from benchmark.cli import main
    from benchmark.run.registry import register, unregister
    from benchmark.tools.conformance import check_prior

    register("plugged", Pull, origin="my-priors 1.2.0")  # the class says name = "pull"
    try:
        tiny_table1(monkeypatch)
        write_motion(tmp_path / "data" / "walk.npz", seed=0)
        assert main(["run", "table1", "--profile", "smoke", "--prior", "plugged", "--jobs", "1",
                     "--data", str(tmp_path / "data"), "--out", str(tmp_path / "out")]) == 0
        table = json.loads((tmp_path / "out" / "table1.json").read_text())
        info = table["prior_info"]["plugged"]
        assert info["plugin"].startswith("my-priors 1.2.0"), info
        capsys.readouterr()
        assert not check_prior("plugged", steps=1)
        out = capsys.readouterr().out
        assert "[FAIL] declaration" in out and "name = 'pull', but the prior is registered as 'plugged'" in out
    finally:
        unregister("plugged")


class WithConstants(Pull):
    """A window count (integer) and a scale (float) the decoder and prior term read, declared
    ``constant_latents``: "latent entries the decoder reads but the protocol never optimises"."""

    name = "with-constants"
    constant_latents = ("count", "scale")

    def init_latents(self, batch, generator):
        B = batch.batch_size
        return {**super().init_latents(batch, generator), "count": torch.full((B,), batch.num_observed),
                "scale": torch.ones(B, 1)}

    def prior_term(self, latents):
        return super().prior_term(latents) * latents["scale"][:, 0] / latents["count"]


def test_constant_latents_are_never_optimised_and_may_be_integers(capsys, anny_body):
    """An integer latent listed in constant_latents (the remedy docs/adding-a-prior.md gives) crashed
    init_state ("only Tensors of floating point dtype can require gradients"), and a float one was
    handed to the optimiser, which moved it wherever it had a gradient."""
    from benchmark.data.degrade import degrade
    from benchmark.protocols.completion import fit, observation_batch
    from benchmark.protocols.fit_state import init_state
    from benchmark.tools.conformance import toy_observation

    ok, out = _check(WithConstants, capsys)
    assert ok, out
    a = WithConstants()
    out_t = (torch.arange(60, dtype=torch.float64) / 30.0)[None]
    batch = observation_batch(degrade(toy_observation(anny_body), 100, 5, seed=1), 2.0, out_t, "cpu")
    st = init_state(a, anny_body, batch, torch.Generator().manual_seed(0), "cpu")
    assert not st.latents["scale"].requires_grad and not st.latents["count"].requires_grad
    assert all(p is not st.latents["scale"] for p in st.parameters())
    st, _ = fit(a, anny_body, batch, steps=3, lr=0.03, lambda_prior=1.0, loss_vertices=200,
                generator=torch.Generator().manual_seed(0), device="cpu")
    assert torch.equal(st.latents["scale"], torch.ones(1, 1)) and int(st.latents["count"]) == 10


def test_check_prior_fails_a_per_frame_encoder_with_a_latent_per_sequence(capsys):
    """A per-frame prior with encode_motion and one latent per sequence (B, 3) passed check-prior, then
    every table1 unit failed in the limb start search, which picks every latent frame by frame."""
    import roma

    from priors.base import MotionEncoder

    class Lean(MotionEncoder, Pull):
        name = "per-frame-lean"

        def init_latents(self, batch, generator):
            return {**super().init_latents(batch, generator), "lean": torch.zeros(batch.batch_size, 3)}

        def decode(self, latents, timestamps, shape=None):
            rot = super().decode(latents, timestamps, shape).rotations
            spine = (roma.rotvec_to_rotmat(latents["lean"])[:, None] @ rot[:, :, 3])[:, :, None]
            return Decoded(rotations=torch.cat([rot[:, :, :3], spine, rot[:, :, 4:]], 2))

        def prior_term(self, latents):
            return super().prior_term(latents) + latents["lean"].square().sum(-1)

        def encode_motion(self, rotations, trans, timestamps):
            return {"pose": matrix_to_sixd(rotations[:, :, 1:], layout="interleaved"),
                    "lean": rotations.new_zeros(rotations.shape[0], 3)}

    ok, out = _check(Lean, capsys)
    assert not ok, out
    assert "[FAIL] 100 pts / 5 fps: encode_motion keys" in out
    assert "latents ['lean'] are not per observed frame ((B, 10, ...))" in out
