"""Opening a file never runs code from it (issue 33).

Every loader of a user's file gets a pickle whose ``__reduce__`` would create a marker file when
unpickled: the marker must not appear, and the error must name the file and the refused global.
Official-style files (Lightning checkpoints with bookkeeping, SMPL ``.pkl`` with chumpy objects)
still load: tests/test_vposer.py, tests/test_smpl_body.py and tests/test_frequency_guided.py cover
them; a few are repeated here next to their evil twins.
"""

from __future__ import annotations

import builtins
import io
import os
import pickle
import re
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmark.cli import main
from benchmark.core.safe_loading import (
    InertStandIn,
    UnsafeFileError,
    is_lightning_bookkeeping,
    torch_load_weights,
    torch_load_with_stand_ins,
)

ROOT = Path(__file__).resolve().parents[1]


# -- evil payloads -------------------------------------------------------------------------------
class _System:
    """Unpickling it runs ``touch MARKER`` through os.system (pickled as ``posix.system``)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


class _Exec:
    """Unpickling it creates MARKER through ``builtins.exec``."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return builtins.exec, (f"open({str(self.marker)!r}, 'w').close()",)


PAYLOADS = {"os.system": (_System, "posix.system"), "builtins.exec": (_Exec, "builtins.exec")}


def _tensors() -> dict:
    return {"layer.weight": torch.ones(2, 3), "layer.bias": torch.zeros(2)}


def evil_checkpoint(path: Path, marker: Path, payload: str = "os.system", fmt: str = "zip", **extra) -> Path:
    """A torch checkpoint that looks like weights ({'state_dict', 'config'}) plus a payload.
    ``fmt``: "zip" (torch's format), "legacy" (before torch 1.6) or "zip-protocol-4"."""
    cls, _ = PAYLOADS[payload]
    path.parent.mkdir(parents=True, exist_ok=True)
    ckpt = {"state_dict": _tensors(), "config": {"hidden": 32}, "epoch": cls(marker), **extra}
    torch.save(ckpt, path, _use_new_zipfile_serialization=fmt != "legacy", pickle_protocol=4 if fmt.endswith("4") else 2)
    return path


def evil_pickle(path: Path, marker: Path, payload: str = "os.system", protocol: int = 2) -> Path:
    """A plain pickle of a dict (as an SMPL .pkl is) that holds a payload."""
    cls, _ = PAYLOADS[payload]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps({"v_template": np.zeros((4, 3)), "f": cls(marker)}, protocol=protocol))
    return path


def assert_refused(exc: BaseException, file: Path, marker: Path, global_name: str = "posix.system") -> None:
    msg = str(exc)
    assert not marker.exists(), f"the payload ran: {marker} exists"
    assert str(file) in msg, msg
    assert "will not unpickle" in msg and global_name in msg, msg
    assert "fix:" in msg, msg


@pytest.fixture
def marker(tmp_path) -> Path:
    m = tmp_path / "PWNED"
    yield m
    assert not m.exists(), f"the payload ran: {m} exists"


# -- the shared torch loader --------------------------------------------------------------------
@pytest.mark.parametrize("payload", sorted(PAYLOADS))
@pytest.mark.parametrize("fmt", ["zip", "legacy", "zip-protocol-4"])
@pytest.mark.filterwarnings("ignore:Detected pickle protocol 4")
def test_torch_load_weights_refuses_a_payload(tmp_path, marker, payload, fmt):
    f = evil_checkpoint(tmp_path / "evil.pt", marker, payload, fmt=fmt)
    with pytest.raises(UnsafeFileError) as err:
        torch_load_weights(f)
    assert_refused(err.value, f, marker, PAYLOADS[payload][1])
    assert "torch.save(model.state_dict()" in str(err.value)


def test_a_plain_pickle_given_as_weights_is_refused(tmp_path, marker):
    f = evil_pickle(tmp_path / "evil.pt", marker, protocol=2)
    with pytest.raises(UnsafeFileError) as err:
        torch_load_weights(f)
    assert_refused(err.value, f, marker)


def test_an_allow_list_does_not_open_the_door(tmp_path, marker):
    """Lightning bookkeeping is allowed as stand-ins; a payload beside it is still refused, and the
    allow-list never covers what could run code."""
    f = evil_checkpoint(tmp_path / "evil.ckpt", marker, hyper_parameters=argparse_namespace(lr=1e-3))
    with pytest.raises(UnsafeFileError) as err:
        torch_load_with_stand_ins(f, is_lightning_bookkeeping)
    assert_refused(err.value, f, marker)
    assert "argparse.Namespace" not in str(err.value)  # allowed: not listed as refused
    for name in ("posix.system", "os.system", "builtins.eval", "builtins.exec", "builtins.getattr", "builtins.__import__",
                 "subprocess.Popen", "subprocess.call", "importlib.import_module", "pickle.loads", "torch.load",
                 "runpy.run_path", "shutil.rmtree", "pathlib.Path.touch", "functools.partial", "sys.exit"):
        assert not is_lightning_bookkeeping(name), name


def argparse_namespace(**kw):
    import argparse

    return argparse.Namespace(**kw)


def test_stand_ins_are_inert_and_plain_weights_still_load(tmp_path):
    f = tmp_path / "ok.ckpt"
    torch.save({"state_dict": _tensors(), "hyper_parameters": argparse_namespace(lr=1e-3, name="x")}, f)
    ckpt, stand_ins = torch_load_with_stand_ins(f, is_lightning_bookkeeping)
    assert stand_ins == ["argparse.Namespace"]
    hp = ckpt["hyper_parameters"]
    assert isinstance(hp, InertStandIn) and not isinstance(hp, __import__("argparse").Namespace)
    assert hp.state == {"lr": 1e-3, "name": "x"} and "argparse.Namespace" in repr(hp)
    torch.testing.assert_close(ckpt["state_dict"]["layer.weight"], torch.ones(2, 3))
    # without the allow-list the same file is refused, naming the class
    with pytest.raises(UnsafeFileError, match=r"argparse\.Namespace"):
        torch_load_weights(f)
    plain = tmp_path / "plain.pt"
    torch.save(_tensors(), plain)
    assert set(torch_load_weights(plain)) == {"layer.weight", "layer.bias"}


def test_an_unreadable_file_is_not_called_unsafe(tmp_path):
    """Truncated or text files keep torch's own error (the registry reports them as unreadable)."""
    text = tmp_path / "notes.pt"
    text.write_text("hello, not a checkpoint\n")
    with pytest.raises(Exception) as err:
        torch_load_weights(text)
    assert not isinstance(err.value, UnsafeFileError)


# -- each prior's loaders ----------------------------------------------------------------------
def _load(prior: str, size: str, **kw):
    """The prior's ``checkpoint.load(path, size)``."""
    import importlib

    return lambda f: importlib.import_module(f"priors.{prior}.checkpoint").load(f, size, **kw)


LOADERS = {
    "vposer official (.ckpt)": (_load("vposer", "paper"), "V02_05_epoch=13_val_loss=0.03.ckpt"),
    "vposer project": (_load("vposer", "embedded"), "vposer.pt"),
    "frequency-guided official pair": (lambda f: _load("frequency_guided", "paper")(f"{f},{f}"), "TR00_E096.pt"),
    "frequency-guided project": (_load("frequency_guided", "embedded"), "frequency_guided.pt"),
    "hmvae official": (_load("hmvae", "paper"), "gen_00250000.pt"),
    "hmvae project": (_load("hmvae", "embedded"), "hmvae.pt"),
    "hmvae project trajectory": (lambda f: _load("hmvae", "embedded", trajectory=True)(f"{f},{f}"), "hmvae_trajectory.pt"),
    "motion-dvae project": (_load("motion_dvae", "embedded"), "motion_dvae.pt"),
    "motion-dvae official": (_load("motion_dvae", "paper"), "official.pt"),
    "structured-latent": (_load("structured_latent", "embedded"), "structured_latent.pt"),
    "sequential-primitives": (_load("sequential_primitives", "embedded"), "sequential_primitives.pt"),
}


@pytest.mark.parametrize("name", sorted(LOADERS))
def test_every_checkpoint_loader_refuses_a_payload(tmp_path, marker, name):
    load, filename = LOADERS[name]
    f = evil_checkpoint(tmp_path / filename, marker)
    with pytest.raises(UnsafeFileError) as err:
        load(f)
    assert_refused(err.value, f, marker)


def test_frequency_guided_official_pair_refuses_a_payload_in_either_file(tmp_path, marker):
    from priors.frequency_guided import checkpoint

    plain = tmp_path / "ok" / "pretrained_priorD.pth"
    plain.parent.mkdir()
    torch.save({"module.dct_att.weight": torch.zeros(2, 2)}, plain)
    evil = evil_checkpoint(tmp_path / "evil" / "TR00_E096.pt", marker, payload="builtins.exec")
    for pair in (f"{plain},{evil}", f"{evil},{plain}"):
        with pytest.raises(UnsafeFileError) as err:
            checkpoint.load(pair, "paper")  # refused before the network is built
        assert_refused(err.value, evil, marker, "builtins.exec")


def test_training_resume_state_refuses_a_payload(tmp_path, marker):
    from priors import training, training_state

    state_dir = tmp_path / ".train_state" / "tiny"
    f = evil_checkpoint(state_dir / "loop0.pt", marker, steps=3, seed=0, samples=8)
    data = torch.randn(8, 2)
    with pytest.raises(UnsafeFileError) as err:
        with training_state.training_session(state_dir, resume=True):
            training.train_loop(torch.nn.Linear(1, 1), lambda m, b: {"loss": m(b[:, :1]).square().mean()}, data,
                                steps=3, batch_size=4, seed=0)
    assert_refused(err.value, f, marker)
    assert "rerun without --resume" in str(err.value)


def test_training_state_is_read_with_weights_only(tmp_path):
    """The resumable state holds only what weights_only=True reads (tensors, numbers, lists, dicts,
    optimiser and schedule state dicts)."""
    from priors import training, training_state

    data = torch.randn(16, 2)
    with training_state.training_session(tmp_path, checkpoint_every=2):
        training.train_loop(torch.nn.Sequential(torch.nn.Linear(1, 4), torch.nn.Linear(4, 1)),
                            lambda m, b: {"loss": (m(b[:, :1]) - b[:, 1:]).square().mean()}, data,
                            steps=4, batch_size=4, seed=0, log_every=2)
    state_file = tmp_path / "loop0.pt"
    assert torch.serialization.get_unsafe_globals_in_checkpoint(state_file) == []
    state = torch.load(state_file, weights_only=True)
    assert state["step"] == 4 and set(state["optimiser"]) == {"state", "param_groups"}


# -- SMPL .pkl --------------------------------------------------------------------------------
@pytest.mark.parametrize("protocol", [0, 2, 4])
@pytest.mark.parametrize("payload", sorted(PAYLOADS))
def test_smpl_pkl_refuses_a_payload(tmp_path, marker, protocol, payload):
    from benchmark.body.smpl_files import load_pickle_without_chumpy

    f = evil_pickle(tmp_path / "SMPL_NEUTRAL.pkl", marker, payload, protocol)
    with pytest.raises(UnsafeFileError) as err:
        load_pickle_without_chumpy(f)
    assert_refused(err.value, f, marker, PAYLOADS[payload][1])
    assert ".npz" in str(err.value)


def test_smpl_pkl_refuses_python2_names_that_run_code(tmp_path, marker):
    """A Python-2 pickle naming ``__builtin__.eval`` is mapped to ``builtins.eval`` and refused."""
    from benchmark.body.smpl_files import load_pickle_without_chumpy

    f = tmp_path / "SMPL_NEUTRAL.pkl"
    f.write_bytes(b"c__builtin__\neval\n(S'open(\"" + str(marker).encode() + b"\", \"w\").close()'\ntR.")
    with pytest.raises(UnsafeFileError) as err:
        load_pickle_without_chumpy(f)
    assert_refused(err.value, f, marker, "builtins.eval")


def test_smpl_pkl_with_numpy_and_sparse_still_loads(tmp_path):
    import scipy.sparse

    from benchmark.body.smpl_files import load_pickle_without_chumpy, to_numpy

    f = tmp_path / "SMPL_NEUTRAL.pkl"
    dense = np.arange(6.0).reshape(2, 3)
    f.write_bytes(pickle.dumps({"J_regressor": scipy.sparse.csc_matrix(dense), "v_template": np.ones((4, 3)),
                                "bs_style": "lbs", "extra": {"a": (1, 2.0, [3])}}, protocol=2))
    raw = load_pickle_without_chumpy(f)
    np.testing.assert_array_equal(to_numpy(raw["J_regressor"]), dense)
    np.testing.assert_array_equal(raw["v_template"], np.ones((4, 3)))


# -- the CLI, end to end ----------------------------------------------------------------------
def _cli(argv, capsys) -> tuple[int, str]:
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    return rc, err


def _one_error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_cli_describe_vposer_paper_with_evil_weights(tmp_path, marker, capsys):
    f = evil_checkpoint(tmp_path / "EVIL.ckpt", marker)
    rc, err = _cli(["describe", "vposer-slerp", "--size", "paper", "--weights", str(f)], capsys)
    assert rc == 2
    assert_refused(_one_error_line(err), f, marker)


def test_cli_describe_vposer_embedded_with_evil_weights(tmp_path, marker, capsys):
    f = evil_checkpoint(tmp_path / "EVIL.pt", marker, payload="builtins.exec")
    rc, err = _cli(["describe", "vposer-slerp", "--weights", str(f)], capsys)
    assert rc == 2
    assert_refused(_one_error_line(err), f, marker, "builtins.exec")


def test_cli_describe_frequency_guided_paper_with_evil_pair(tmp_path, marker, capsys):
    a = evil_checkpoint(tmp_path / "EVIL.pth", marker)
    b = evil_checkpoint(tmp_path / "EVIL.pt", marker)
    rc, err = _cli(["describe", "frequency-guided", "--size", "paper", "--weights", f"{a},{b}"], capsys)
    assert rc == 2
    assert_refused(_one_error_line(err), a, marker)


def test_cli_describe_with_evil_smpl_pkl(tmp_path, marker, capsys):
    f = evil_pickle(tmp_path / "EVIL.pkl", marker)
    rc, err = _cli(["describe", "no-prior", "--body", f"smpl={f}"], capsys)
    assert rc == 2
    assert_refused(_one_error_line(err), f, marker)


# -- the Anny cache -----------------------------------------------------------------------------
def truncated_anny_cache(tmp: Path, monkeypatch) -> Path:
    """A copy of Anny's cache folder under ``tmp`` whose files are cut to 4 kB; Anny is pointed at it.
    Returns the cache folder. Skips where the real cache has not been built."""
    import anny.paths

    real = Path(anny.paths.get_anny_cache_path())
    files = sorted(real.glob("v*/*.safetensors"))
    if not files:
        pytest.skip(f"Anny's cache {real} is not built")
    cache = tmp / "anny_cache"
    for f in files:
        dst = cache / f.parent.name / f.name
        dst.parent.mkdir(parents=True, exist_ok=True)
        with open(f, "rb") as src:
            dst.write_bytes(src.read(4096))
    monkeypatch.setattr(anny.paths, "_ANNY_CACHE_DIR", [cache])  # what get_anny_cache_path() returns
    return cache


def test_truncated_anny_cache_file_names_the_file_and_the_fix(tmp_path, monkeypatch):
    from benchmark.body.anny_body import AnnyCacheError, _make_anny, damaged_cache_files

    cache = truncated_anny_cache(tmp_path, monkeypatch)
    with pytest.raises(AnnyCacheError) as err:
        _make_anny()
    msg = str(err.value)
    assert isinstance(err.value, ValueError)
    bad = damaged_cache_files(cache)
    assert bad and all(str(f) in msg for f in bad), msg
    assert "rm " in msg and str(cache) in msg and "rebuilds" in msg
    assert re.search(r"\.safetensors \(Error while deserializing header", msg), msg


def test_a_complete_cache_file_is_not_called_damaged(tmp_path):
    from safetensors.torch import save_file

    from benchmark.body.anny_body import damaged_cache_files

    save_file({"a": torch.zeros(3)}, str(tmp_path / "ok.safetensors"))
    data = (tmp_path / "ok.safetensors").read_bytes()
    (tmp_path / "cut.safetensors").write_bytes(data[:-4])
    assert list(damaged_cache_files(tmp_path)) == [tmp_path / "cut.safetensors"]


# -- the code itself ---------------------------------------------------------------------------
def test_no_unsafe_loading_call_in_the_code():
    """benchmark/ and priors/ never unpickle with a full unpickler: torch.load only with
    weights_only=True, np.load never with allow_pickle=True, yaml only through safe_load, no
    eval/exec. The one pickle.load is the process backend's own executor file (benchmark/run/backends/local.py)."""
    bad = []
    patterns = {
        "weights_only=False": re.compile(r"weights_only\s*=\s*False"),
        "torch.load without weights_only=True": re.compile(r"torch\.load\((?![^)]*weights_only\s*=\s*True)"),
        "allow_pickle=True": re.compile(r"allow_pickle\s*=\s*True"),
        "yaml.load / unsafe_load": re.compile(r"yaml\.(load|unsafe_load|full_load)\("),
        "eval/exec": re.compile(r"(?<![\w.])(eval|exec)\("),
        "pickle.load": re.compile(r"pickle\.loads?\("),
    }
    allowed = {("benchmark/run/backends/local.py", "pickle.load")}
    for pkg in ("benchmark", "priors"):
        for f in sorted((ROOT / pkg).rglob("*.py")):
            rel = f.relative_to(ROOT).as_posix()
            for i, line in enumerate(f.read_text().splitlines(), 1):
                code = line.split("#", 1)[0]
                if code.lstrip().startswith(('"', "'", "``", "-")):
                    continue  # docstring lines
                for what, pat in patterns.items():
                    if pat.search(code) and (rel, what) not in allowed:
                        bad.append(f"{rel}:{i}: {what}: {line.strip()}")
    assert not bad, "\n".join(bad)
