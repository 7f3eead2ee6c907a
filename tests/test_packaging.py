"""The install: ``pip install -e .`` must print no deprecation warning of the project's own.

setuptools deprecated ``project.license`` as a TOML table (``{ text = ... }``); builds that use it
stop working after 2027-02-18. The license is an SPDX expression string (PEP 639), which needs
setuptools >= 77 in the build requirements."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_license_is_an_spdx_string_and_the_build_backend_reads_it():
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert meta["project"]["license"] == "Apache-2.0"
    (setuptools,) = [r for r in meta["build-system"]["requires"] if r.startswith("setuptools")]
    minimum = re.fullmatch(r"setuptools>=(\d+)(\.\d+)*", setuptools)
    assert minimum and int(minimum.group(1)) >= 77, setuptools
    assert not any(c.startswith("License ::") for c in meta["project"].get("classifiers", ())), \
        "a license classifier beside an SPDX license is an error for setuptools >= 77"
