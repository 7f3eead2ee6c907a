"""No tracked text file refers to a path outside the repository.

A user who clones the repository has only what git tracks, so the code, the docs, the table specs
and the tests must not send a reader to files that live elsewhere: the team's shared folder next
to the checkout, the upper-case protocol brief that used to live there (the project's own
protocol is ``docs/protocol.md``), or an absolute path on a development machine. Every file
``git ls-files`` lists is read once; binary files (a NUL byte, or not UTF-8) are skipped.

One recorded field is exempt: ``provenance.command`` of the committed tables ``results/*.json``
(and of each run in ``provenance.rows_replaced``), the command line that made the table as the
machine wrote it (the tables are reference data that the regression tests guard bit for bit, so
they are not edited).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Each pattern is built from pieces so that this file does not match itself.
PATTERNS = {
    "the shared folder beside the checkout": re.compile(re.escape(".." + "/shared")),
    "the upper-case protocol brief (use docs/protocol.md)": re.compile(re.escape("PROTOCOL" + ".md")),
    "an absolute path of a development machine": re.compile(r"(?<![\w./-])/" + "work/"),
}


def tracked_files() -> list[str]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout: no tracked files to check")
    out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    return [name for name in out.decode("utf-8", "surrogateescape").split("\0") if name]


def text_of(rel: str) -> str | None:
    """The file's text, or None for a binary (or missing) file."""
    path = ROOT / rel
    if not path.is_file():
        return None
    with path.open("rb") as fh:
        if b"\0" in fh.read(8192):
            return None
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        return None
    if rel.startswith("results/") and rel.endswith(".json"):
        table = json.loads(text)
        if isinstance(table.get("provenance"), dict):
            table["provenance"].pop("command", None)
            for replaced in table["provenance"].get("rows_replaced", []):  # the run a replaced row came from
                replaced.get("provenance", {}).pop("command", None)
        text = json.dumps(table, ensure_ascii=False)
    return text


def outside_references(text: str) -> list[str]:
    """``what: line`` for each line of ``text`` that matches a pattern."""
    found = []
    for what, pattern in PATTERNS.items():
        for line in text.splitlines():
            if pattern.search(line):
                found.append(f"{what}: {line.strip()[:160]}")
    return found


def test_doc_patterns_catch_what_they_should():
    assert outside_references("see .." + "/shared/priors.md section 2")
    assert outside_references("the contract (" + "PROTOCOL" + ".md)")
    assert outside_references("weights in /" + "work/shared/seeds")
    assert outside_references('"command": "/' + 'work/venv/bin/python"')
    for fine in ("docs/protocol.md", "a shared/ folder", "network/work/x", "framework/", "../work_units.py"):
        assert not outside_references(fine), fine


def test_no_tracked_doc_or_file_refers_outside_the_repository():
    problems = []
    for rel in tracked_files():
        text = text_of(rel)
        if text is None:
            continue
        problems += [f"{rel}: {hit}" for hit in outside_references(text)]
    assert not problems, "references to paths outside the repository:\n" + "\n".join(problems)
