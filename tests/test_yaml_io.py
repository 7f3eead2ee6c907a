"""The project reads its YAML (table specs, profiles, the AMASS frame-rate table) through
benchmark.core.yaml_io: a key repeated within one mapping is an error naming the file and the
line, not a silent last-wins."""

import pytest

from benchmark.core.yaml_io import DuplicateKeyError, load_yaml
from benchmark.run import catalog


def test_plain_documents_read_as_safe_load_does():
    text = "a: 1\nb: {c: [1, 2], d: x}\nanchors: &base {k: 1}\nmerged: {<<: *base, k: 2}\n"
    assert load_yaml(text, "t.yaml") == {"a": 1, "b": {"c": [1, 2], "d": "x"}, "anchors": {"k": 1},
                                         "merged": {"k": 2}}


def test_a_repeated_key_names_the_file_the_key_and_both_lines():
    text = "objective:\n  lr: 0.03\nmetrics: []\nobjective:\n  lr: 0.1\n"
    with pytest.raises(DuplicateKeyError, match=r"t\.yaml: line 4: key 'objective' appears twice .*first at line 1"):
        load_yaml(text, "t.yaml")


def test_a_repeated_key_in_a_nested_flow_mapping_is_refused():
    with pytest.raises(DuplicateKeyError, match="key 'steps'"):
        load_yaml("quick:\n  tables:\n    sls: {steps: 3000, steps: 60}\n", "p.yaml")


def test_malformed_yaml_names_the_file():
    with pytest.raises(ValueError, match=r"bad\.yaml: not valid YAML"):
        load_yaml("a: [1, 2\n", "bad.yaml")


def test_only_plain_data_is_constructed():
    with pytest.raises(ValueError, match="not valid YAML"):
        load_yaml("!!python/object/apply:os.system ['true']\n", "evil.yaml")


def test_the_shipped_profiles_and_table_specs_have_no_repeated_key():
    catalog.load_profiles.cache_clear()
    profiles = catalog.load_profiles()
    assert {"smoke", "quick", "full"} <= set(profiles)
    for name in catalog.table_names():
        assert catalog.load_table_spec(name)["name"] == name


def test_a_plug_in_spec_with_a_repeated_key_is_refused_with_its_path(tmp_path):
    spec = tmp_path / "dup.yaml"
    spec.write_text("name: dup-table\nprotocol: completion\nname: dup-table\n")
    catalog.register_table("dup-table", spec)
    try:
        with pytest.raises(DuplicateKeyError, match=rf"{spec}: line 3: key 'name'"):
            catalog.load_table_spec("dup-table")
    finally:
        catalog.unregister_table("dup-table")
