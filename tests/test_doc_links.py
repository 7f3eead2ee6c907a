"""Every relative Markdown link of the documentation points at a file that exists and, with
``#anchor``, at a heading of that file, as GitHub derives anchors from headings (lower case,
punctuation other than ``-`` and ``_`` dropped, each space a ``-``, ``-1``, ``-2`` ... for repeats).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted({ROOT / "README.md", ROOT / "tests" / "README.md", *(ROOT / "docs").glob("*.md"),
               *(ROOT / "datasets").glob("*.md")})
LINK = re.compile(r"\]\(([^)\s]+)\)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")


def slug(heading: str) -> str:
    """GitHub's anchor for a heading's text."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip().lower())  # a link's text only
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    found, seen, fence = set(), {}, False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.lstrip().startswith("```"):
            fence = not fence
        match = None if fence else HEADING.match(line)
        if match:
            base = slug(match.group(2))
            n = seen.get(base, 0)
            seen[base] = n + 1
            found.add(base if n == 0 else f"{base}-{n}")
    return found


def broken_links(doc: Path) -> list[str]:
    bad = []
    for target in LINK.findall(doc.read_text(encoding="utf-8")):
        if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
            continue
        name, _, anchor = target.partition("#")
        path = (doc.parent / name) if name else doc
        if not path.exists():
            bad.append(f"{target}: no such file")
        elif anchor and path.suffix == ".md" and anchor not in anchors(path):
            bad.append(f"{target}: no heading with that anchor in {os.path.relpath(path, ROOT)}")
    return bad


def test_slug_is_githubs():
    assert slug("Why three learned priors stay above no-prior at 100 / 5") == \
        "why-three-learned-priors-stay-above-no-prior-at-100--5"
    assert slug("The step cap raised to 3,000 (2026-12-06)") == "the-step-cap-raised-to-3000-2026-12-06"
    assert slug("`data make-scans`: a captured-like test set") == "data-make-scans-a-captured-like-test-set"
    assert slug("The report's browser test") == "the-reports-browser-test"


def test_broken_links_are_found(tmp_path):
    (tmp_path / "b.md").write_text("# Title\n## Title\n```\n# not a heading\n```\n", encoding="utf-8")
    doc = tmp_path / "a.md"
    doc.write_text("[ok](b.md#title) [ok](b.md#title-1) [x](b.md#not-a-heading) [y](c.md) "
                   "[web](https://example.org/x#y)", encoding="utf-8")
    assert [b.split(":")[0] for b in broken_links(doc)] == ["b.md#not-a-heading", "c.md"]


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_doc_links_resolve(doc):
    assert not broken_links(doc), f"{doc.relative_to(ROOT)}: " + "; ".join(broken_links(doc))
