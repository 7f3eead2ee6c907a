"""The prior contract in one place (``priors/base.py``) and one checkpoint API (``priors/checkpoints.py``).

Every registered prior is a concrete :class:`~priors.base.PriorAdapter`; the optional capabilities
each shipped prior declares are the interfaces it subclasses (a table of expectations below); the
harness asks ``isinstance``, never ``getattr``/``hasattr`` (a source scan); every learned prior's
checkpoint module offers ``load(path, size) -> (network, CheckpointReport)`` on the shared strict
loader.
"""

from __future__ import annotations

import importlib
import inspect
import re
from pathlib import Path

import pytest
import torch

from benchmark.run.registry import get_prior_class, make_adapter, prior_names
from priors.base import (
    INTERFACES, Decoded, MotionEncoder, PriorAdapter, WindowSpec, has_motion_encoder, interfaces_of,
)
from priors.checkpoints import CheckpointMismatchError, CheckpointReport, load_state_strict

ROOT = Path(__file__).resolve().parents[1]

# prior -> (interfaces, has_encoder): read from the adapters; a change here is a change of what the
# tables and commands do with the prior
EXPECTED = {
    "frequency-guided": ({"MotionEncoder", "Trainable", "ExportableDecoder", "PaperNetwork"}, True),
    "hmvae": ({"MotionEncoder", "Trainable", "ExportableDecoder", "PaperNetwork"}, True),
    "hmvae-trajectory": ({"MotionEncoder", "Trainable", "ExportableDecoder", "PaperNetwork"}, True),
    "motion-dvae": ({"MotionEncoder", "MotionDenoiser", "Trainable", "ExportableDecoder", "PaperNetwork"}, True),
    "no-prior": ({"MotionEncoder"}, False),  # an exact change of representation, not a learned encoder
    "sequential-primitives": ({"MotionEncoder", "Trainable", "ExportableDecoder", "PaperNetwork"}, True),
    "slerp": ({"MotionEncoder", "Trainable", "InterpolationBaseline"}, True),
    "structured-latent": ({"MotionEncoder", "AnchorDecoder", "Trainable", "ExportableDecoder", "PaperNetwork"}, True),
    "vposer-slerp": ({"MotionEncoder", "Trainable", "ExportableDecoder", "PaperNetwork"}, True),
}

# the packages of the learned priors and their checkpoint modules
PACKAGES = ["vposer", "frequency_guided", "hmvae", "motion_dvae", "sequential_primitives", "structured_latent"]

# the loaders the one API replaced: none may come back
OLD_LOADERS = ["load_project_checkpoint", "load_project_vae", "load_project_trajectory", "load_official_vae",
               "load_official_trajectory", "read_project_checkpoint", "load_state_strict", "read_checkpoint",
               "load_into", "network_from_checkpoint", "load_checkpoint", "load_vposer_checkpoint",
               "load_paper_weights", "read_project_config", "LoadReport", "CheckpointReport", "load_strict"]

# hooks of a prior that the harness must reach through the contract, never by probing
HOOKS = ["init_latents", "decode", "prior_term", "mean_latents", "encode_motion", "denoise_motion", "decode_anchors",
         "train_embedded", "export_decoder", "paper_network", "interpolation_baseline", "constant_latents",
         "has_encoder", "weights_path", "weights_sha256", "DEFAULT_WEIGHTS", "default_weights", "frozen_network",
         "trained_network", "checkpoint"]


@pytest.mark.parametrize("name", prior_names())
def test_every_registered_prior_is_a_concrete_prior_adapter(name):
    cls = get_prior_class(name)
    assert isinstance(cls, type) and issubclass(cls, PriorAdapter), cls
    assert not inspect.isabstract(cls), f"{name}: abstract methods left: {sorted(cls.__abstractmethods__)}"


def test_the_expectations_cover_every_shipped_prior():
    shipped = {n for n in prior_names() if get_prior_class(n).__module__.startswith("priors.")}
    assert shipped == set(EXPECTED)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_interfaces_each_shipped_prior_declares(name):
    interfaces, encoder = EXPECTED[name]
    assert set(interfaces_of(get_prior_class(name))) == interfaces
    a = make_adapter(name)
    assert set(interfaces_of(a)) == interfaces
    assert a.has_encoder is encoder and has_motion_encoder(a) is encoder
    assert a.device == torch.device("cpu") and a.size == "embedded" and a.name == name
    assert isinstance(a.constant_latents, tuple)
    if a.trained_network is not None:  # a learned prior: its weights went through the one checkpoint API
        assert a.frozen_network is not None and not a.trained_network.training
        assert isinstance(a.checkpoint, CheckpointReport) and a.checkpoint.format == "project"
        assert a.weights_path == a.checkpoint.weights_path
        assert a.default_weights is not None and Path(a.checkpoint.file) == Path(a.default_weights)
    else:
        assert a.weights_path is None and a.checkpoint is None


def test_an_adapter_without_the_three_methods_cannot_be_built():
    class NoPriorTerm(PriorAdapter):
        name = "incomplete"
        window = WindowSpec(kind="per-frame")

        def init_latents(self, batch, generator):
            return {}

        def decode(self, latents, timestamps, shape=None):
            return Decoded(rotations=torch.eye(3).expand(1, 1, 22, 3, 3))

    with pytest.raises(TypeError, match="prior_term"):
        NoPriorTerm()
    assert interfaces_of(NoPriorTerm) == []

    class Encoder(MotionEncoder, NoPriorTerm):
        def prior_term(self, latents):
            return torch.zeros(1)

    with pytest.raises(TypeError, match="encode_motion"):
        Encoder()  # an interface's method is abstract too


def test_interfaces_are_small_abstract_classes():
    for i in INTERFACES:
        assert inspect.isabstract(i) or i.__name__ == "InterpolationBaseline", i
        assert not issubclass(i, torch.nn.Module), i


@pytest.mark.parametrize("package", PACKAGES)
def test_every_checkpoint_module_offers_load_path_size(package):
    module = importlib.import_module(f"priors.{package}.checkpoint")
    params = list(inspect.signature(module.load).parameters)
    assert params[:2] == ["path", "size"], params
    assert inspect.signature(module.load).parameters["size"].default == "embedded"
    left = [n for n in OLD_LOADERS if n in vars(module) and vars(module)[n].__module__ == module.__name__]
    assert not left, f"priors.{package}.checkpoint still defines {left}"


@pytest.mark.parametrize("package", PACKAGES)
def test_embedded_checkpoints_load_through_the_one_api(package):
    module = importlib.import_module(f"priors.{package}.checkpoint")
    network, report = module.load(module.DEFAULT_WEIGHTS, "embedded")
    assert isinstance(network, torch.nn.Module) and isinstance(report, CheckpointReport)
    assert report.format == "project" and report.file == module.DEFAULT_WEIGHTS and report.loaded
    with pytest.raises(ValueError, match="unknown size"):
        module.load(module.DEFAULT_WEIGHTS, "huge")


def test_the_checkpoint_modules_share_one_strict_loader():
    """No checkpoint module copies tensors itself: ``load_state_dict`` is called in priors/checkpoints.py only."""
    for package in PACKAGES:
        text = (ROOT / "priors" / package / "checkpoint.py").read_text()
        assert "load_state_dict(" not in text, package
        assert "load_state_strict" in text, package


def test_the_strict_loader_names_the_file_and_keys():
    net = torch.nn.Sequential(torch.nn.Linear(2, 3), torch.nn.BatchNorm1d(3))
    good = {k: v.clone() + 1 for k, v in net.state_dict().items()}
    target = torch.nn.Sequential(torch.nn.Linear(2, 3), torch.nn.BatchNorm1d(3))
    loaded, ignored = load_state_strict(target, {"p." + k: v for k, v in good.items()} | {"other": torch.zeros(1)},
                                        "f.pt", "toy", prefix="p.", ignore_unexpected=True)
    assert loaded == sorted(good) and ignored == ["other"]
    assert torch.equal(target[0].weight, good["0.weight"])
    missing = {k: v for k, v in good.items() if k != "0.bias"}
    with pytest.raises(CheckpointMismatchError, match=r"f\.pt: .*missing keys \['0\.bias'\] \(expected shapes \[\(3,\)\]\)") as err:
        load_state_strict(target, missing, "f.pt", "toy")
    assert isinstance(err.value, KeyError) and isinstance(err.value, ValueError) and not str(err.value).startswith("'")
    load_state_strict(target, {k: v for k, v in good.items() if "num_batches" not in k}, "f.pt", "toy",
                      optional=lambda k: k.endswith("num_batches_tracked"))
    with pytest.raises(KeyError, match=r"unexpected keys \['extra'\]"):
        load_state_strict(target, good | {"extra": torch.zeros(1)}, "f.pt", "toy")
    with pytest.raises(ValueError, match=r"0\.weight: file \(3, 4\), expected \(3, 2\)"):
        load_state_strict(target, good | {"0.weight": torch.zeros(3, 4)}, "f.pt", "toy")
    with pytest.raises(ValueError, match=r"fixed tensor '1\.running_mean'.*rebuilt"):
        load_state_strict(target, good | {"1.running_mean": good["1.running_mean"] + 1}, "f.pt", "toy",
                          fixed=["1.running_mean"], fixed_note="rebuilt")


def _nan_floats(obj):
    if torch.is_tensor(obj):
        return torch.full_like(obj, float("nan")) if obj.is_floating_point() else obj
    if isinstance(obj, dict):
        return {k: _nan_floats(v) for k, v in obj.items()}
    return obj


@pytest.mark.parametrize("package", PACKAGES)
def test_a_checkpoint_of_nan_weights_is_refused_by_name(package, tmp_path):
    """A diverged training's checkpoint (NaN weights) is refused when it loads, naming the file, not
    later inside a fit or the Chamfer loss."""
    module = importlib.import_module(f"priors.{package}.checkpoint")
    bad = tmp_path / Path(module.DEFAULT_WEIGHTS).name
    torch.save(_nan_floats(torch.load(module.DEFAULT_WEIGHTS, weights_only=True)), bad)
    with pytest.raises(CheckpointMismatchError, match=rf"{re.escape(str(bad))}: .*hold NaN or inf values.*retrain"):
        module.load(bad, "embedded")


def test_the_strict_loader_refuses_nan_but_keeps_an_inf_mask_buffer():
    net = torch.nn.Linear(2, 3)
    net.register_buffer("mask", torch.tensor([0.0, float("-inf")]))
    good = {k: v.clone() for k, v in net.state_dict().items()}
    load_state_strict(net, good, "f.pt", "toy")  # -inf in a buffer: a mask, loaded
    with pytest.raises(CheckpointMismatchError, match=r"f\.pt: 1 tensor\(s\) .*\['weight'\]"):
        load_state_strict(net, good | {"weight": torch.full((3, 2), float("inf"))}, "f.pt", "toy")
    with pytest.raises(CheckpointMismatchError, match=r"\['mask'\]"):
        load_state_strict(net, good | {"mask": torch.tensor([0.0, float("nan")])}, "f.pt", "toy")


def test_no_hook_of_a_prior_is_probed_in_the_harness_or_the_priors():
    """benchmark/ and priors/ reach a prior's hooks through the contract (declared attributes with
    defaults, interfaces checked with isinstance), never by getattr / hasattr."""
    names = "|".join(HOOKS)
    probe = re.compile(rf"""(getattr|hasattr)\(\s*[^,()]+,\s*["']({names})["']""")
    dynamic = re.compile(r"getattr\(\s*self\s*,\s*self\.frozen_network")
    by_identity = re.compile(r"\.(encode_motion|export_decoder|denoise_motion|decode_anchors)\s+is\s+(not\s+)?PriorAdapter\.")
    found = []
    for pkg in ("benchmark", "priors"):
        for f in sorted((ROOT / pkg).rglob("*.py")):
            for i, line in enumerate(f.read_text().splitlines(), 1):
                if probe.search(line) or dynamic.search(line) or by_identity.search(line):
                    found.append(f"{f.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not found, "probes of a prior's hooks:\n" + "\n".join(found)


def test_a_mistyped_weights_path_is_named_as_the_users_not_as_missing_training(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"structured-latent weights .*nope\.pt: no such file; check the path given with --weights"):
        make_adapter("structured-latent", weights=str(tmp_path / "nope.pt"))
    from priors.hmvae.checkpoint import DEFAULT_WEIGHTS

    lone = tmp_path / "hmvae.pt"
    lone.write_bytes(Path(DEFAULT_WEIGHTS).read_bytes())
    with pytest.raises(FileNotFoundError, match=r"hmvae-trajectory needs two files.*VAE\.pt,TRAJECTORY\.pt"):
        make_adapter("hmvae-trajectory", weights=str(lone))


def test_missing_default_weights_say_how_to_train_them(tmp_path, monkeypatch):
    from priors.structured_latent.adapter import StructuredLatentPrior

    monkeypatch.setattr(StructuredLatentPrior, "default_weights", tmp_path / "structured_latent.pt")
    with pytest.raises(FileNotFoundError, match=r"embedded structured-latent weights not found: .*python -m benchmark train structured-latent"):
        StructuredLatentPrior()


def test_a_registered_object_that_is_not_a_usable_adapter_is_named_with_its_entry_point():
    from benchmark.run import registry as reg
    from priors.vposer.adapter import VPoserSlerp

    class NoTerm(PriorAdapter):  # prior_term left out
        name = "no-term"

        def init_latents(self, batch, generator):
            return {}

        def decode(self, latents, timestamps, shape=None):
            raise NotImplementedError

    class NoKwargs(VPoserSlerp):
        def __init__(self):
            super().__init__()

    def helper(**kw):
        return None

    cases = ((NoTerm, r"NoTerm does not implement prior_term"),
             (helper, r"names <function .*helper.*>, not a subclass of priors.base.PriorAdapter"),
             (NoKwargs, r"NoKwargs\(size=..., weights=..., device=...\) failed .*takes those three keyword arguments"))
    for target, message in cases:
        reg.register("audit-case", target)
        try:
            with pytest.raises(ValueError, match=rf"prior 'audit-case' \(.*\).*{message}"):
                make_adapter("audit-case")
        finally:
            reg.unregister("audit-case")


def test_a_plugged_in_prior_records_its_distribution_in_the_spec():
    """A prior from another package is identified in its units' spec (so in their hash and in the
    table's prior_info) by its distribution and version: a new version of the package reruns it.
    The project's own priors, and those registered at run time, carry no such key (their stored
    units stay valid)."""
    from benchmark.run import registry as reg
    from benchmark.run.table_run import plugin_origin, prior_identity

    reg.register("plugged", "priors.no_prior:NoPrior", origin="my-priors 1.2.0")
    try:
        assert plugin_origin("plugged") == "my-priors 1.2.0 (priors.no_prior:NoPrior)"
        adapter = make_adapter("plugged")
        adapter.name = "plugged"
        assert prior_identity(adapter, "embedded", None)["plugin"] == "my-priors 1.2.0 (priors.no_prior:NoPrior)"
    finally:
        reg.unregister("plugged")
    assert plugin_origin("vposer-slerp") is None and "plugin" not in prior_identity(make_adapter("no-prior"), "embedded", None)


def test_a_network_that_read_no_weights_file_is_recorded_untrained():
    """A prior with parameters that read no weights file (a plug-in's untrained fallback) is recorded
    as ``untrained`` in its units' spec, so the table can mark its row; the project's priors, which
    read their embedded weights, and no-prior (no parameters) carry no such key."""
    from benchmark.run.table_run import prior_identity

    adapter = make_adapter("hmvae")
    assert "untrained" not in prior_identity(adapter, "embedded", None)
    assert "untrained" not in prior_identity(make_adapter("no-prior"), "embedded", None)
    adapter.weights_path = None  # as an adapter that found no file and kept its initial parameters
    assert prior_identity(adapter, "embedded", None)["untrained"] is True


def test_two_packages_registering_one_prior_name_break_only_that_name(monkeypatch, capsys):
    """A plug-in registering a name another package registers (here 'no-prior') used to stop every
    prior command, ``list priors`` included; now only using that name fails, naming both packages and
    the fix, and ``list priors`` shows the clash beside the other priors."""
    from importlib.metadata import entry_points as real_entry_points
    from types import SimpleNamespace

    from benchmark.cli import main
    from benchmark.core import plugins
    from benchmark.run import registry as reg

    plug = SimpleNamespace(name="no-prior", value="other_priors:Mine", dist=SimpleNamespace(name="other-priors", version="1.0"))
    own = list(real_entry_points(group=reg.GROUP))
    monkeypatch.setattr(plugins, "entry_points", lambda group: own + [plug] if group == reg.GROUP else real_entry_points(group=group))
    monkeypatch.setattr(reg.PRIORS, "entries", None)  # discovered again, restored afterwards
    assert main(["list", "priors"]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.strip().startswith("no-prior"))
    assert "NAME CLASH" in row and "other-priors 1.0 (other_priors:Mine)" in row and "priors.no_prior:NoPrior" in row
    assert re.search(r"^  vposer-slerp +Pavlakos", out, flags=re.M)  # every other prior still listed
    with pytest.raises(ValueError, match=r"'no-prior' is registered by .* and by .*; uninstall all but one") as caught:
        make_adapter("no-prior")
    assert "other-priors 1.0 (other_priors:Mine)" in str(caught.value) and "(priors.no_prior:NoPrior)" in str(caught.value)
    assert type(make_adapter("slerp")).__name__ == "SlerpBaseline"
    assert main(["check-prior", "no-prior"]) == 2
    err = capsys.readouterr().err
    assert "error: prior name collision: 'no-prior'" in err and "Traceback" not in err
