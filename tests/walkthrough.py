"""The walkthroughs in docs/ (adding-a-prior.md, adding-a-table.md), read as the package they
describe: every fenced code block whose first line is ``# file: PATH`` is one file of it."""

from __future__ import annotations

import re
import subprocess
import sys
from contextlib import contextmanager
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


@contextmanager
def pip_installed(package: Path, distribution: str):
    """``pip install -e package`` (no dependencies, no build isolation) for the ``with`` block, then
    ``pip uninstall distribution``, whatever the block's outcome."""
    pip = [sys.executable, "-m", "pip"]
    subprocess.run(pip + ["install", "--no-deps", "--no-build-isolation", "-e", str(package)], check=True,
                   capture_output=True, text=True)
    try:
        yield
    finally:
        subprocess.run(pip + ["uninstall", "-y", distribution], check=True, capture_output=True, text=True)


def cli_in(cwd: Path):
    """A function running ``python ARGS...`` in a fresh interpreter in ``cwd``: it asserts exit 0 and
    returns the standard output."""
    def cli(*args) -> str:
        done = subprocess.run([sys.executable, *args], cwd=cwd, capture_output=True, text=True)
        assert done.returncode == 0, done.stdout + done.stderr
        return done.stdout

    return cli
