"""table1 protocol v3: the priors whose start is a random prior sample start at the prior's mean."""

import pytest
import torch

from benchmark.run.catalog import load_table_spec
from benchmark.protocols.fit_state import LATENT_INITS, initial_latents
from benchmark.protocols.completion_unit import latent_init_rule
from priors.base import FitBatch

MEAN_STARTS = ["vposer-slerp", "frequency-guided", "hmvae", "hmvae-trajectory", "structured-latent", "motion-dvae"]
OWN_STARTS = ["no-prior", "sequential-primitives"]  # deterministic already: unchanged by the rule


def _batch(B=2, n=5, points=64, window_s=2.0):
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(B, n, points, 3, generator=g) * 0.3 + torch.tensor([0.0, 1.0, 0.0])
    t = (torch.arange(n, dtype=torch.float64) / n * window_s)[None].expand(B, -1).clone()
    out_t = (torch.arange(12, dtype=torch.float64) / 6.0)[None].expand(B, -1).clone()
    return FitBatch(points=pts, lengths=torch.full((B, n), points), timestamps=t, window_s=window_s, output_timestamps=out_t)


def test_table1_starts_at_the_prior_mean():
    spec = load_table_spec("table1")
    assert spec["protocol_version"] >= 3 and latent_init_rule(spec) == "mean"
    assert latent_init_rule({"objective": {}}) == "sample"  # versions 1-2


@pytest.mark.parametrize("prior", MEAN_STARTS + OWN_STARTS)
def test_mean_latents_fit_the_adapter(prior):
    """The mean start has the keys and shapes of the adapter's own start, decodes, draws nothing
    from the generator, and is deterministic; deterministic starts are left as they are."""
    from benchmark.run.registry import make_adapter

    adapter = make_adapter(prior)
    batch = _batch()
    sample = adapter.init_latents(batch, torch.Generator().manual_seed(1))
    g = torch.Generator().manual_seed(1)
    before = g.get_state()
    mean = initial_latents(adapter, batch, g, "mean")
    assert set(mean) == set(sample) and all(mean[k].shape == sample[k].shape for k in sample)
    if prior in OWN_STARTS:
        assert adapter.mean_latents(batch) is None
        assert all(torch.equal(mean[k], sample[k]) for k in sample)
        return
    assert torch.equal(g.get_state(), before)
    again = initial_latents(adapter, batch, torch.Generator().manual_seed(7), "mean")
    assert all(torch.equal(mean[k], again[k]) for k in mean)
    assert not all(torch.equal(mean[k], sample[k]) for k in sample)
    if "z" in mean and prior != "motion-dvae":
        assert torch.count_nonzero(mean["z"]) == 0
    # it decodes like a sample does (the window kinds' own timestamps)
    kind = adapter.window.kind
    if kind == "per-frame":
        ts = batch.timestamps
    elif kind == "fixed":
        from benchmark.protocols.fit_state import decode_grid

        ts = decode_grid(adapter, batch.window_s, batch.batch_size, "cpu")
    else:
        ts = batch.output_timestamps
    with torch.no_grad():
        dec = adapter.decode(mean, ts, None)
    assert torch.isfinite(dec.rotations).all()


def test_unknown_latent_init_is_refused():
    from benchmark.run.registry import make_adapter

    with pytest.raises(ValueError, match="latent_init 'mode'"):
        initial_latents(make_adapter("no-prior"), _batch(), torch.Generator(), "mode")
    assert LATENT_INITS == ("sample", "mean")
