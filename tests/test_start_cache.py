"""The prior-free searches on disk (benchmark.protocols.start_cache): a stored start is served back
bit for bit, a fit from it equals a fit from a fresh search, and a damaged, foreign or unwritable
cache costs a search again, never a unit."""

from __future__ import annotations

import logging
import math

import pytest
import torch

from benchmark.data.observations import make_scans
from benchmark.protocols import facing as facing_module
from benchmark.protocols import start_cache, start_search
from benchmark.protocols.completion import fit, observation_batch
from benchmark.protocols.start_cache import use_start_cache
from benchmark.protocols.start_search import prior_free_start
from benchmark.run.registry import make_adapter

ARGS = dict(device="cpu", lr=0.03, lambda_prior=0.01)


def _walker_batch(anny_body, frames: int = 3, points: int = 60):
    from tests.test_facing import _turned_walker

    scans, _ = make_scans(anny_body, [_turned_walker(math.pi, frames=frames)], fps=10.0, num_points=points, seed=0)
    out_t = (torch.arange(frames, dtype=torch.float64) / 10.0)[None]
    return observation_batch(scans, frames / 10.0, out_t, "cpu")


@pytest.fixture
def empty_memory(monkeypatch, brief_searches):
    """Empty per-process caches, and a count of the searches run (the searches cut short: these
    tests are about where a start is kept, not what it is)."""
    monkeypatch.setattr(start_search, "_START_CACHE", start_search.OrderedDict())
    monkeypatch.setattr(facing_module, "_FACING_CACHE", facing_module.OrderedDict())
    calls = {"limbs": 0, "facing": 0}
    real_limbs, real_facing = start_search.limb_start_search, facing_module.facing_search

    def limbs(*a, **k):
        calls["limbs"] += 1
        return real_limbs(*a, **k)

    def facing(*a, **k):
        calls["facing"] += 1
        return real_facing(*a, **k)

    monkeypatch.setattr(start_search, "limb_start_search", limbs)
    monkeypatch.setattr(facing_module, "facing_search", facing)
    return calls


def _forget(monkeypatch):
    """A new worker process: nothing in memory."""
    monkeypatch.setattr(start_search, "_START_CACHE", start_search.OrderedDict())
    monkeypatch.setattr(facing_module, "_FACING_CACHE", facing_module.OrderedDict())


def _same_state(a, b):
    for k in a.latents:
        assert torch.equal(a.latents[k].detach(), b.latents[k].detach()) and b.latents[k].requires_grad, k
    for name in ("shape_param", "root", "trans", "heading", "offset", "obs_t"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert torch.equal(x.detach(), y.detach()) and x.dtype == y.dtype, name
    assert a.window_s == b.window_s and a.bounded_shape == b.bounded_shape


@pytest.mark.parametrize("rule", ["observation", "aligned"])
def test_a_stored_start_is_served_bit_for_bit_to_a_new_worker(anny_body, tmp_path, monkeypatch, empty_memory, rule):
    batch = _walker_batch(anny_body)
    g = torch.Generator().manual_seed(0)
    with use_start_cache(tmp_path, "run"):
        first, log1 = prior_free_start(anny_body, batch, g, facing=rule, **ARGS)
    searched = dict(empty_memory)
    assert searched["limbs"] == 1 and searched["facing"] == (rule == "observation")
    files = sorted(p.name for p in tmp_path.iterdir())
    assert len(files) == 1 + (rule == "observation") and all(f.endswith(".pt") for f in files)  # the start (and the facing)
    _forget(monkeypatch)
    with use_start_cache(tmp_path, "run"):
        second, log2 = prior_free_start(anny_body, batch, g, facing=rule, **ARGS)
    assert empty_memory == searched  # served from disk: no search ran
    _same_state(first, second)
    assert log1 == log2
    _forget(monkeypatch)
    with use_start_cache(tmp_path, "other code or body"):  # another namespace never reads this run's files
        prior_free_start(anny_body, batch, g, facing=rule, **ARGS)
    assert empty_memory["limbs"] == 2
    _forget(monkeypatch)
    prior_free_start(anny_body, batch, g, facing=rule, **ARGS)  # no disk cache outside a table run
    assert empty_memory["limbs"] == 3 and len(list(tmp_path.iterdir())) == 2 * len(files)


def test_a_fit_from_a_stored_start_equals_a_fit_from_a_fresh_search(anny_body, tmp_path, monkeypatch, empty_memory):
    """The unit a resumed run computes from the stored start is the unit a fresh run computes."""
    batch = _walker_batch(anny_body)
    runs = []
    for _ in range(2):
        _forget(monkeypatch)
        with use_start_cache(tmp_path, "run"):
            for prior in ("no-prior", "vposer-slerp"):
                state, info = fit(make_adapter(prior), anny_body, batch, steps=3, generator=torch.Generator().manual_seed(0),
                                  loss_vertices=300, facing="observation", latent_init="mean", start_search="observation",
                                  **ARGS)
                runs.append((state, info))
    # the prior-free start and the facing are searched in the first pass only; vposer's own limb search in each
    assert empty_memory == {"limbs": 1 + 2, "facing": 1}
    for (a, ia), (b, ib) in zip(runs[:2], runs[2:]):
        _same_state(a, b)
        assert torch.equal(ia["data_trace"], ib["data_trace"]) and ia["facing_yaw_rad"] == ib["facing_yaw_rad"]


def test_a_damaged_or_foreign_file_is_searched_again(anny_body, tmp_path, monkeypatch, empty_memory, caplog):
    batch = _walker_batch(anny_body)
    g = torch.Generator().manual_seed(0)
    with use_start_cache(tmp_path, "run"):
        want, _ = prior_free_start(anny_body, batch, g, facing="aligned", **ARGS)
    (path,) = tmp_path.iterdir()
    for damage in (b"not a torch file", None):
        if damage is None:  # a file another key wrote, under this key's name
            blob = torch.load(path, weights_only=True)
            torch.save({**blob, "key": "another key"}, path)
        else:
            path.write_bytes(damage)
        _forget(monkeypatch)
        with caplog.at_level(logging.WARNING, logger="benchmark.protocols.start_cache"), use_start_cache(tmp_path, "run"):
            got, _ = prior_free_start(anny_body, batch, g, facing="aligned", **ARGS)
        assert "cannot be read" in caplog.text and str(path) in caplog.text and "searching again" in caplog.text
        _same_state(want, got)
        caplog.clear()
    assert empty_memory["limbs"] == 3
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".start-")]  # no partial file left behind


def test_an_unwritable_folder_costs_a_warning_not_the_unit(anny_body, tmp_path, monkeypatch, empty_memory, caplog):
    blocker = tmp_path / "file"
    blocker.write_text("mine")
    batch = _walker_batch(anny_body)
    with caplog.at_level(logging.WARNING, logger="benchmark.protocols.start_cache"), use_start_cache(blocker / "starts", "run"):
        state, _ = prior_free_start(anny_body, batch, torch.Generator().manual_seed(0), facing="aligned", **ARGS)
    assert "not stored" in caplog.text and blocker.read_text() == "mine"
    assert state.latents["pose"].requires_grad


def test_a_log_json_would_change_is_not_stored(tmp_path):
    with use_start_cache(tmp_path, "run"):
        assert start_cache.write(("k",), {"stages": (1, 2)}, yaw=torch.zeros(1)) is None  # a tuple comes back a list
        assert start_cache.write(("k",), {"stages": [1, 2]}, yaw=torch.zeros(1)) is not None
        assert start_cache.read(("k",), "cpu")["log"] == {"stages": [1, 2]}
    from benchmark.core.json_io import current_umask

    (stored,) = tmp_path.glob("*.pt")
    assert stored.stat().st_mode & 0o777 == 0o666 & ~current_umask()  # as the run's other files, not mkstemp's 0600
    assert start_cache.write(("k",), {}, yaw=torch.zeros(1)) is None  # no cache in use


def test_a_local_table_run_keeps_its_starts_in_its_out_folder(tmp_path):
    from benchmark.run.catalog import load_table_spec
    from benchmark.run.table_run import TableExecutor

    class Body:
        name = "anny"

    def namespace(spec, body=Body()):
        execute = TableExecutor(None, spec, {}, {}, body, None, "cpu")
        assert execute.start_cache is None
        execute.use_start_cache(tmp_path / "cache" / "starts")
        folder, name = execute.start_cache
        assert folder == tmp_path / "cache" / "starts" and len(name) == 64
        return name

    spec = load_table_spec("table1")
    same = namespace(spec)
    assert namespace(load_table_spec("table1")) == same
    assert namespace({**spec, "protocol_version": spec["protocol_version"] + 1}) != same
    assert namespace({**spec, "objective": {**spec["objective"], "lr": 0.5}}) != same  # another rule
    assert namespace(spec, type("B", (), {"name": "smpl"})()) != same  # another body


def test_resume_never_forgets_the_stored_starts_and_nothing_else(tmp_path):
    from benchmark.protocols.start_cache import forget_starts

    assert forget_starts(tmp_path / "absent") == 0
    with use_start_cache(tmp_path, "run"):
        stored = start_cache.write(("k",), {}, yaw=torch.zeros(1))
    (tmp_path / "notes.txt").write_text("mine")
    (tmp_path / "mine.pt").write_bytes(b"mine")
    assert stored.exists() and forget_starts(tmp_path) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.pt", "notes.txt"]


def test_the_namespace_ignores_what_only_the_descent_reads(tmp_path):
    """A run that differs from another only in its step rule or its starts per sequence (fit-check's
    longer probe; a raised cap) shares the other's stored prior-free starts: the search never reads
    those keys. Any rule the search reads still separates them."""
    from benchmark.protocols.start_cache import DESCENT_ONLY_KEYS
    from benchmark.run.catalog import load_table_spec
    from benchmark.run.table_run import TableExecutor

    def namespace(spec):
        execute = TableExecutor(None, spec, {}, {}, type("B", (), {"name": "anny"})(), None, "cpu")
        execute.use_start_cache(tmp_path)
        return execute.start_cache[1]

    spec = load_table_spec("table1")
    objective = spec["objective"]
    same = namespace(spec)
    assert "plateau" in DESCENT_ONLY_KEYS and "multi_start" in DESCENT_ONLY_KEYS
    assert namespace({**spec, "objective": {**objective, "plateau": {**objective["plateau"], "min_steps": 900}}}) == same
    assert namespace({**spec, "objective": {**objective, "multi_start": {"starts": 2, "choose": "plateau"}}}) == same
    assert namespace({**spec, "objective": {**objective, "start_fit": "smooth"}}) != same
    assert namespace({**spec, "objective": {**objective, "shape_lr_scale": 1}}) != same


def test_share_starts_copies_stored_starts_and_keeps_what_is_there(tmp_path):
    from benchmark.protocols.start_cache import share_starts

    src, dest = tmp_path / "base" / "cache" / "starts", tmp_path / "longer" / "cache" / "starts"
    src.mkdir(parents=True)
    a, b = "a" * 64 + ".pt", "b" * 64 + ".pt"
    for name in (a, b, "notes.pt", "c" * 64 + ".pt.tmp"):
        (src / name).write_bytes(name.encode())
    dest.mkdir(parents=True)
    (dest / b).write_bytes(b"already here")
    assert share_starts(tmp_path / "base", tmp_path / "longer") == 1
    assert sorted(p.name for p in dest.iterdir()) == [a, b]
    assert (dest / a).read_bytes() == a.encode() and (dest / b).read_bytes() == b"already here"
    assert sorted(p.name for p in src.iterdir()) == sorted([a, b, "notes.pt", "c" * 64 + ".pt.tmp"])  # only read
    assert share_starts(tmp_path / "base", tmp_path / "longer") == 0
    assert share_starts(tmp_path / "nowhere", tmp_path / "longer") == 0
