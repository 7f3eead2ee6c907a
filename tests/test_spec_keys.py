"""A table spec's rule sections hold only the keys its protocol accepts (``Protocol.spec_keys``):
a misspelt or unsupported rule is refused before any work, with the file, the key and the fix."""

import copy

import pytest

from benchmark.protocols.base import Protocol, check_spec_keys
from benchmark.run.catalog import load_table_spec
from benchmark.run.table_run import table_protocol

TABLES = ["table1", "sls", "denoise", "inbetween", "reconstruction"]


@pytest.mark.parametrize("name", TABLES)
def test_every_shipped_spec_uses_only_keys_its_protocol_accepts(name):
    spec = load_table_spec(name)
    protocol = table_protocol(copy.deepcopy(spec))  # runs the check
    assert protocol.spec_keys, f"protocol {protocol.name!r} declares no spec_keys"
    for section in ("data", "objective"):
        assert set(spec[section]) <= protocol.spec_keys[section]


def test_a_misspelt_rule_is_refused_with_the_file_the_key_and_a_suggestion():
    spec = copy.deepcopy(load_table_spec("table1"))
    spec["objective"]["lamda_prior"] = 0.1
    with pytest.raises(ValueError) as err:
        table_protocol(spec)
    message = str(err.value)
    assert "benchmark/tables/table1.yaml" in message and "objective.lamda_prior" in message
    assert "did you mean objective.lambda_prior?" in message and "protocol 'completion'" in message


def test_a_rule_of_another_protocol_is_refused():
    """table1's candidate rule objective.multi_start is not an sls rule: an sls spec carrying it
    would run with one start, without a word. (The perturbation probe data.observation_offset_m,
    refused by sls before it had one, is now a rule of both.)"""
    for name in ("table1", "sls"):
        spec = copy.deepcopy(load_table_spec(name))
        spec["data"]["observation_offset_m"] = 1e-6
        table_protocol(spec)
    table1 = copy.deepcopy(load_table_spec("table1"))
    table1["objective"]["multi_start"] = {"starts": 2}
    table_protocol(table1)
    sls = copy.deepcopy(load_table_spec("sls"))
    sls["objective"]["multi_start"] = {"starts": 2}
    with pytest.raises(ValueError, match=r"objective\.multi_start is not a rule of protocol 'sls'"):
        table_protocol(sls)


def test_a_protocol_that_declares_no_keys_is_not_checked():
    class Open(Protocol):
        name = "open"

    check_spec_keys({"name": "t", "data": {"anything": 1}, "objective": {"else": 2}}, Open())


def test_a_plugin_table_names_its_own_file():
    class Strict(Protocol):
        name = "strict"
        spec_keys = {"data": frozenset({"window_s"}), "objective": frozenset({"lr"})}

    with pytest.raises(ValueError, match=r"^/somewhere/t\.yaml: objective\.lrr .*did you mean objective\.lr\?"):
        check_spec_keys({"name": "t", "_source": "/somewhere/t.yaml", "data": {}, "objective": {"lrr": 1}}, Strict())


@pytest.mark.parametrize("name", TABLES)
def test_the_protocol_document_states_each_table_s_current_version(name):
    """docs/protocol.md, the project's contract, names each table's version twice (the index and
    its section); both follow the spec's ``protocol_version``."""
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "protocol.md").read_text(encoding="utf-8")
    version = load_table_spec(name)["protocol_version"]
    index = re.search(rf"^\| `{name}` \|.*\| \*\*(\d+)\*\* \|$", text, re.M)
    section = re.search(rf"Spec: `benchmark/tables/{name}\.yaml`.*?Current version: \*\*(\d+)\*\*", text, re.S)
    assert index and int(index.group(1)) == version, f"docs/protocol.md: the index gives {name} another version than {version}"
    assert section and int(section.group(1)) == version, f"docs/protocol.md: {name}'s section gives another version than {version}"
