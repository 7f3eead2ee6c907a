"""docs/adding-a-prior.md, followed to the letter: its example package is written out of the doc's own
code blocks (those whose first line is ``# file: PATH``) into a temporary folder, registered, run
through the conformance kit and a shrunk table1 (tests/tiny_run.py), then removed. The doc cannot
drift from what passes here.

The default test puts the package on ``sys.path`` and registers it at run time
(``benchmark.run.registry.register``); the ``slow`` one really ``pip install``s it (editable, through its
``pyproject.toml`` entry point) and uninstalls it afterwards."""

from __future__ import annotations

import importlib
import json
import math
import re
import sys
from pathlib import Path

import pytest

import walkthrough
from tiny_run import tiny_table1, write_motion

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "adding-a-prior.md"
NAME, TARGET, MODULE = "tiny-pose", "tiny_pose:TinyPosePrior", "tiny_pose"
FILES = {"pyproject.toml", "tiny_pose/__init__.py", "tiny_pose/model.py", "tiny_pose/checkpoint.py",
         "tiny_pose/adapter.py", "tiny_pose/train.py"}


def doc_files() -> dict[str, str]:
    return walkthrough.doc_files(DOC)


def build_package(root: Path) -> Path:
    return walkthrough.build_package(DOC, root)


def forget_module():
    walkthrough.forget_module(MODULE)


def check_and_run_table1(tmp_path, monkeypatch, capsys):
    """check-prior passes; a tiny table1 has a finite row for the prior."""
    from benchmark.cli import main
    from benchmark.tools.conformance import check_prior

    assert check_prior(NAME, steps=2, verbose=True), capsys.readouterr().out
    assert capsys.readouterr().out.rstrip().endswith("PASS")

    tiny_table1(monkeypatch)
    data, out = tmp_path / "data", tmp_path / "out"
    write_motion(data / "walk.npz", seed=0)
    assert main(["run", "table1", "--profile", "smoke", "--prior", NAME, "--jobs", "1",
                 "--data", str(data), "--out", str(out)]) == 0
    table = json.loads((out / "table1.json").read_text())
    rows = [r for r in table["rows"] if r["prior"] == NAME]
    assert len(rows) == 1 and rows[0]["cells"], table["rows"]
    numbers = [v for cell in rows[0]["cells"] for v in cell.values() if isinstance(v, float)]
    assert numbers and all(math.isfinite(v) for v in numbers), rows[0]["cells"]
    assert "mpjpe_mm" in rows[0]["cells"][0]
    assert NAME in (out / "table1.md").read_text()


def test_the_doc_holds_the_whole_package():
    files = doc_files()
    assert set(files) == FILES
    assert f'{NAME} = "{TARGET}"' in files["pyproject.toml"]
    assert '[project.entry-points."benchmark.priors"]' in files["pyproject.toml"]
    readme = (ROOT / "README.md").read_text()
    assert "docs/adding-a-prior.md" in readme.split("## Adding a prior", 1)[1].split("\n## ", 1)[0]


def test_walkthrough_registered_at_run_time(tmp_path, monkeypatch, capsys):
    from benchmark.run import registry

    pkg = build_package(tmp_path / "tiny-pose-prior")
    monkeypatch.syspath_prepend(str(pkg))
    forget_module()
    registry.register(NAME, TARGET)
    try:
        check_and_run_table1(tmp_path, monkeypatch, capsys)
        # the optional pieces of the example work too: encode_motion round trip shapes, the recipe
        import torch

        from benchmark.run.registry import make_adapter

        from priors.base import MotionEncoder, Trainable, interfaces_of

        a = make_adapter(NAME)
        assert isinstance(a, MotionEncoder) and isinstance(a, Trainable) and a.has_encoder
        assert interfaces_of(a) == ["MotionEncoder", "Trainable"]
        rot = torch.eye(3).expand(2, 5, 22, 3, 3)
        z = a.encode_motion(rot, torch.zeros(2, 5, 3), torch.zeros(2, 5))["z"]
        assert z.shape == (2, 5, 8)
        train = importlib.import_module("tiny_pose.train")
        record = train.train(tmp_path / "w", steps=3, poses=torch.randn(64, 22, 3) * 0.2)
        assert math.isfinite(record["final_loss"])
        trained = make_adapter(NAME, weights=record["weights"])
        assert trained.weights_path == record["weights"]
        assert trained.checkpoint.format == "project" and trained.checkpoint.file == Path(record["weights"])
    finally:
        registry.unregister(NAME)
        forget_module()
    assert NAME not in registry.prior_names()


_TINY_TABLE1 = """
import sys
sys.path[:0] = [{root!r}, {tests!r}]
import pytest
from tiny_run import tiny_table1, write_motion
from benchmark.cli import main

tiny_table1(pytest.MonkeyPatch())
write_motion({data!r} + "/walk.npz")
sys.exit(main(["run", "table1", "--profile", "smoke", "--prior", {name!r}, "--jobs", "1",
               "--data", {data!r}, "--out", {out!r}]))
"""


@pytest.mark.slow
def test_walkthrough_pip_installed(tmp_path):
    """``pip install -e .`` of the doc's package, then fresh interpreters as a user would run them:
    the entry point alone registers it (``list priors``, ``check-prior``, a shrunk ``run table1``)."""
    pkg = build_package(tmp_path / "tiny-pose-prior")
    cli = walkthrough.cli_in(ROOT)
    with walkthrough.pip_installed(pkg, "tiny-pose-prior"):
        assert re.search(rf"^\s*{NAME}\b", cli("-m", "benchmark", "list", "priors"), flags=re.M)
        assert cli("-m", "benchmark", "check-prior", NAME).rstrip().endswith("PASS")
        data, out = tmp_path / "data", tmp_path / "out"
        cli("-c", _TINY_TABLE1.format(root=str(ROOT), tests=str(ROOT / "tests"), data=str(data), out=str(out), name=NAME))
        rows = [r for r in json.loads((out / "table1.json").read_text())["rows"] if r["prior"] == NAME]
        numbers = [v for cell in rows[0]["cells"] for v in cell.values() if isinstance(v, float)]
        assert len(rows) == 1 and numbers and all(math.isfinite(v) for v in numbers)
    assert NAME not in cli("-m", "benchmark", "list", "priors")

def test_the_base_docstring_example_passes_check_prior(tmp_path, monkeypatch, capsys):
    """The one-module example in the ``priors.base`` docstring is complete: check-prior passes."""
    import textwrap

    import priors.base
    from benchmark.run import registry
    from benchmark.tools.conformance import check_prior

    doc = priors.base.__doc__
    code = doc.split("Minimal example", 1)[1].split("::\n", 1)[1].split("\nand in your package's", 1)[0]
    (tmp_path / "tpose_pull_example.py").write_text(textwrap.dedent(code))
    entry = re.search(r'(\S+) = "my_package\.my_module:(\w+)"', doc)
    monkeypatch.syspath_prepend(str(tmp_path))
    registry.register(entry.group(1), f"tpose_pull_example:{entry.group(2)}")
    try:
        assert check_prior(entry.group(1), steps=2), capsys.readouterr().out
    finally:
        registry.unregister(entry.group(1))
        sys.modules.pop("tpose_pull_example", None)


def test_the_example_s_random_start_has_its_mean(tmp_path, monkeypatch):
    """The page says a prior whose ``init_latents`` is a random sample of the prior gives
    ``mean_latents`` (table1 starts there); its own example drew N(0, I) and left it out."""
    import torch

    from priors.base import FitBatch

    pkg = build_package(tmp_path / "tiny-pose-prior")
    monkeypatch.syspath_prepend(str(pkg))
    forget_module()
    try:
        prior = importlib.import_module(MODULE).TinyPosePrior()
        batch = FitBatch(points=torch.zeros(2, 5, 10, 3), lengths=torch.full((2, 5), 10), timestamps=torch.arange(5.0).expand(2, 5) / 10,
                         window_s=0.5, output_timestamps=torch.arange(15.0).expand(2, 15) / 30)
        draws = [prior.init_latents(batch, torch.Generator().manual_seed(s)) for s in (0, 1)]
        assert not torch.equal(draws[0]["z"], draws[1]["z"])  # a random start...
        mean = prior.mean_latents(batch)  # ...so the prior's mean, with the same keys and shapes
        assert mean is not None and {k: v.shape for k, v in mean.items()} == {k: v.shape for k, v in draws[0].items()}
        assert torch.equal(mean["z"], torch.zeros_like(draws[0]["z"]))
    finally:
        forget_module()
