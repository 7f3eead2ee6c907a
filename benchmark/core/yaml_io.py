"""YAML reading for the project's specs, profiles and data cards: PyYAML's safe loader, except that a
key repeated in one mapping is an error. PyYAML keeps the last of them silently, so a spec with two
``objective:`` blocks would run on the second alone, and a profile's second ``denoise:`` entry would
replace the first without a word."""

from __future__ import annotations

import yaml


class DuplicateKeyError(ValueError):
    """A mapping of a YAML document names the same key twice."""


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a key repeated within one mapping."""


def _construct_mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    first_line: dict = {}
    for key_node, _ in node.value:  # the keys written in this mapping (a merged key (<<) may be overridden)
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node, deep=True)
        try:
            hash(key)
        except TypeError:
            continue  # an unhashable key: the base constructor reports it
        line = key_node.start_mark.line + 1
        if key in first_line:
            raise DuplicateKeyError(f"line {line}: key {key!r} appears twice in the same mapping "
                                    f"(first at line {first_line[key]}); keep one of them")
        first_line[key] = line
    return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def load_yaml(text: str, source: str):
    """The document in ``text`` (read from ``source``, named in errors). Raises ValueError naming
    ``source`` and the line for a repeated key or malformed YAML."""
    loader = _UniqueKeyLoader(text)  # a SafeLoader: plain data only
    try:
        return loader.get_single_data()
    except DuplicateKeyError as exc:
        raise DuplicateKeyError(f"{source}: {exc}") from None
    except yaml.YAMLError as exc:
        raise ValueError(f"{source}: not valid YAML ({exc})") from None
    finally:
        loader.dispose()
