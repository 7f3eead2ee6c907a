"""docs/adding-a-table.md, followed to the letter: its example package (a spec plus a protocol
class, the ``mean-decode`` table) is written out of the doc's own code blocks (those whose first
line is ``# file: PATH``) into a temporary folder, registered, listed and run through the CLI, then
removed. The doc cannot drift from what passes here.

The default test puts the package on ``sys.path`` and registers the protocol and the table at run
time (``benchmark.protocols.registry.register``, ``benchmark.run.catalog.register_table``); the
``slow`` one really ``pip install``s it (editable, through its ``pyproject.toml`` entry points) and
uninstalls it afterwards.

Also here: the protocol registry itself (the project's own protocols, the entry points in
``pyproject.toml``, the stale-metadata fallback, unknown names)."""

from __future__ import annotations

import json
import math
import re
import sys
from pathlib import Path

import pytest

import walkthrough
from tiny_run import write_motion

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "adding-a-table.md"
NAME, MODULE = "mean-decode", "mean_decode"
PROTOCOL_TARGET, SPEC_TARGET = "mean_decode.protocol:MeanDecodeProtocol", "mean_decode:mean_decode.yaml"
FILES = {"pyproject.toml", "mean_decode/__init__.py", "mean_decode/mean_decode.yaml", "mean_decode/protocol.py"}


def doc_files() -> dict[str, str]:
    return walkthrough.doc_files(DOC)


def build_package(root: Path) -> Path:
    return walkthrough.build_package(DOC, root)


def forget_module():
    walkthrough.forget_module(MODULE)


def check_table(out: Path, priors: list[str], na: tuple = ()) -> dict:
    """The written table: one row per prior, every cell of a served prior finite, n/a rows for ``na``."""
    table = json.loads((out / f"{NAME}.json").read_text())
    assert table["table"] == NAME and table["protocol"] == NAME and table["protocol_version"] == 1
    assert [r["prior"] for r in table["rows"]] == priors
    for row in table["rows"]:
        assert [c["fps"] for c in row["cells"]] == [5, 30]
        for cell in row["cells"]:
            if row["prior"] in na:
                assert "fixed-window" in cell["na_reason"], cell
            else:
                assert math.isfinite(cell["pose_angle_deg"]) and 0 <= cell["pose_angle_deg"] < 180, cell
    assert NAME in (out / f"{NAME}.md").read_text()
    return table


def test_the_doc_holds_the_whole_package():
    files = doc_files()
    assert set(files) == FILES
    assert f'{NAME} = "{PROTOCOL_TARGET}"' in files["pyproject.toml"]
    assert f'{NAME} = "{SPEC_TARGET}"' in files["pyproject.toml"]
    assert '[project.entry-points."benchmark.protocols"]' in files["pyproject.toml"]
    assert '[project.entry-points."benchmark.tables"]' in files["pyproject.toml"]
    assert re.search(rf"^name: {NAME}$", files["mean_decode/mean_decode.yaml"], flags=re.M)
    assert re.search(rf"^protocol: {NAME}$", files["mean_decode/mean_decode.yaml"], flags=re.M)


def test_walkthrough_registered_at_run_time(tmp_path, monkeypatch, capsys):
    from benchmark.run import catalog
    from benchmark.cli import main
    from benchmark.protocols import registry

    pkg = build_package(tmp_path / "mean-decode-table")
    monkeypatch.syspath_prepend(str(pkg))
    forget_module()
    registry.register(NAME, PROTOCOL_TARGET)
    catalog.register_table(NAME, SPEC_TARGET)
    try:
        assert main(["list", "tables"]) == 0
        assert re.search(rf"^\s*{NAME}\s+Mean decode: .*\[runtime: {SPEC_TARGET}\]", capsys.readouterr().out, flags=re.M)
        assert "mean_decode.protocol" not in sys.modules  # listing tables reads the spec, never imports the protocol
        assert main(["list", "protocols"]) == 0
        assert re.search(rf"^\s*{NAME}\s+Mean decode .*\[runtime: {PROTOCOL_TARGET}\]", capsys.readouterr().out, flags=re.M)

        data, out = tmp_path / "data", tmp_path / "out"
        write_motion(data / "walk.npz", seed=0, seconds=1.5)
        args = ["run", NAME, "--profile", "smoke", "--jobs", "1", "--data", str(data), "--out", str(out)]
        assert main(args + ["--prior", "no-prior", "--prior", "vposer-slerp", "--prior", "frequency-guided"]) == 0
        first = check_table(out, ["no-prior", "vposer-slerp", "frequency-guided"], na=("frequency-guided",))
        # a rerun reuses every unit (the same numbers, nothing computed)
        assert main(args + ["--prior", "no-prior", "--prior", "vposer-slerp", "--prior", "frequency-guided"]) == 0
        again = check_table(out, ["no-prior", "vposer-slerp", "frequency-guided"], na=("frequency-guided",))
        assert again["rows"] == first["rows"]
        assert again["provenance"]["resume"]["reused"] == first["counts"]["units_planned"], again["provenance"]["resume"]
        # a spec registered by path works the same; the spec's name must be the registered name
        catalog.unregister_table(NAME)
        catalog.register_table(NAME, pkg / "mean_decode" / "mean_decode.yaml")
        assert catalog.load_table_spec(NAME)["protocol"] == NAME
        catalog.unregister_table(NAME)
        catalog.register_table("other-name", pkg / "mean_decode" / "mean_decode.yaml")
        with pytest.raises(ValueError, match="the spec's 'name' field must be 'other-name'"):
            catalog.load_table_spec("other-name")
    finally:
        catalog.unregister_table(NAME)
        catalog.unregister_table("other-name")
        registry.unregister(NAME)
        forget_module()
    assert NAME not in catalog.table_names() and NAME not in registry.protocol_names()
    with pytest.raises(KeyError, match="unknown table"):
        catalog.load_table_spec(NAME)


_RUN = """
import sys
sys.path[:0] = [{root!r}, {tests!r}]
from tiny_run import write_motion
from benchmark.cli import main

write_motion({data!r} + "/walk.npz", seconds=1.5)
sys.exit(main(["run", {name!r}, "--profile", "smoke", "--prior", "no-prior", "--jobs", "1",
               "--data", {data!r}, "--out", {out!r}]))
"""


@pytest.mark.slow
def test_walkthrough_pip_installed(tmp_path):
    """``pip install -e .`` of the doc's package, then fresh interpreters as a user would run them:
    the entry points alone register it (``list tables``, ``list protocols``, ``run``)."""
    pkg = build_package(tmp_path / "mean-decode-table")
    cli = walkthrough.cli_in(tmp_path)
    with walkthrough.pip_installed(pkg, "mean-decode-table"):
        assert re.search(rf"^\s*{NAME}\b.*\[mean-decode-table 0.1.0: {SPEC_TARGET}\]",
                         cli("-m", "benchmark", "list", "tables"), flags=re.M)
        assert re.search(rf"^\s*{NAME}\b.*\[mean-decode-table 0.1.0: {PROTOCOL_TARGET}\]",
                         cli("-m", "benchmark", "list", "protocols"), flags=re.M)
        data, out = tmp_path / "data", tmp_path / "out"
        cli("-c", _RUN.format(root=str(ROOT), tests=str(ROOT / "tests"), data=str(data), out=str(out), name=NAME))
        check_table(out, ["no-prior"])
    assert NAME not in cli("-m", "benchmark", "list", "tables")


# -- the protocol registry -------------------------------------------------------------------------

def test_the_projects_protocols_are_registered_by_entry_point_and_built_in():
    from benchmark.run.catalog import load_table_spec, table_names
    from benchmark.protocols import registry
    from benchmark.protocols.base import Protocol

    section = (ROOT / "pyproject.toml").read_text().split('[project.entry-points."benchmark.protocols"]\n', 1)[1]
    section = section.split("\n[", 1)[0]  # (tomllib is Python 3.11+; the project supports 3.10)
    declared = dict(re.findall(r'^([\w-]+) = "([^"]+)"$', section, flags=re.M))
    assert declared == registry.BUILTIN  # the fallback cannot drift from pyproject.toml
    for table in table_names():
        if registry.registry()[load_table_spec(table)["protocol"]].origin != "runtime":
            cls = registry.get_protocol_class(load_table_spec(table)["protocol"])
            assert issubclass(cls, Protocol) and cls.name == load_table_spec(table)["protocol"]
    assert {load_table_spec(t)["protocol"] for t in ("table1", "sls", "denoise", "inbetween", "reconstruction")} \
        == set(registry.BUILTIN)


def test_stale_package_metadata_falls_back_to_the_built_in_protocols(monkeypatch):
    """A checkout installed before the group existed (no entry points) still runs its tables."""
    from benchmark.core import plugins
    from benchmark.protocols import registry

    monkeypatch.setattr(plugins, "entry_points", lambda group: [])
    monkeypatch.setattr(registry.PROTOCOLS, "entries", None)  # discovered again, restored afterwards
    assert registry.protocol_names() == sorted(registry.BUILTIN)
    assert {e.origin for e in registry.registry().values()} == {plugins.BUILTIN_ORIGIN}
    assert type(registry.make_protocol("sls")).__name__ == "SlsProtocol"


def test_unknown_protocol_names_the_close_ones(tmp_path):
    from benchmark.protocols import registry
    from benchmark.run.table_run import table_protocol

    with pytest.raises(KeyError, match=r"unknown protocol 'sl'\. Did you mean 'sls'\? Registered: completion,"):
        registry.get_protocol_class("sl")
    with pytest.raises(ValueError, match=r"field 'protocol' is 'denoize': unknown protocol 'denoize'\. Did you mean 'denoise'"):
        table_protocol({"name": "t", "protocol": "denoize"})
    with pytest.raises(ValueError, match="already registered"):
        registry.register("sls", "x:Y")
    registry.register("broken-protocol", "no_such_module_anywhere:Nope")
    try:
        with pytest.raises(ImportError, match="broken-protocol.*failed to load: ModuleNotFoundError"):
            registry.get_protocol_class("broken-protocol")
    finally:
        registry.unregister("broken-protocol")


def test_a_protocol_class_registered_as_a_class_runs_in_the_executor():
    """register(name, cls) with a class object; the executor calls its methods and n/a rule."""
    from benchmark.protocols import registry
    from benchmark.protocols.base import Protocol
    from benchmark.run.table_run import TableExecutor, table_protocol

    class Never(Protocol):
        name = "never"

        def make_source(self, spec, body, motions_by_id, seed):
            return None

        def na_reason(self, spec, adapter):
            return "never serves " + adapter

    class Unit:
        unit_id, spec_hash, prior, cell, sequence_ids = "u", "h", "p", {"a": 1}, ["s"]

    registry.register("never", Never)
    try:
        execute = TableExecutor(table_protocol({"protocol": "never"}), {}, {}, {"p": "p"}, None, None, "cpu")
        assert execute(Unit())["na_reason"] == "never serves p"
    finally:
        registry.unregister("never")
