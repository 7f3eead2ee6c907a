"""The walkthroughs in docs/ (adding-a-prior.md, adding-a-table.md), read as the package they
describe: every fenced code block whose first line is ``# file: PATH`` is one file of it."""

from __future__ import annotations

import re
import sys
from pathlib import Path


def doc_files(doc: Path) -> dict[str, str]:
    """{path: text} of ``doc``'s fenced blocks that start with ``# file: PATH``."""
    files = {}
    for body in re.findall(r"^```[a-z]*\n(.*?)^```", doc.read_text(), flags=re.S | re.M):
        m = re.match(r"# file: (\S+)\n", body)
        if m:
            assert m.group(1) not in files, f"{m.group(1)} appears twice in {doc.name}"
            files[m.group(1)] = body[m.end():]
    return files


def build_package(doc: Path, root: Path) -> Path:
    """Write ``doc``'s files under ``root``; returns ``root``."""
    for rel, text in doc_files(doc).items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    return root


def forget_module(module: str) -> None:
    """Drop ``module`` and its submodules from ``sys.modules`` (the next import reads the files again)."""
    for mod in [m for m in sys.modules if m == module or m.startswith(module + ".")]:
        del sys.modules[mod]
