"""Every relative link of the user docs (README.md, docs/*.md, deploy/k8s/README.md) reaches a file of the repository
and, when it names one, a heading of that page (GitHub's anchors)."""

from __future__ import annotations

import re
from pathlib import Path

from tests.docs.blocks import PAGES, REPO, anchor_of

_LINK = re.compile(r"\]\(([^)\s]+)\)")


def anchors(page: Path) -> set:
    """The anchors of a page's headings (outside code fences), GitHub's de-duplication included."""
    seen: dict = {}
    out = set()
    fenced = False
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and re.match(r"^#{1,6} ", line):
            a = anchor_of(line.lstrip("#"))
            n = seen.get(a, 0)
            seen[a] = n + 1
            out.add(a if n == 0 else f"{a}-{n}")
    return out


def broken_links(page: str) -> list:
    """``(link, why)`` of every relative link of ``page`` that does not resolve."""
    src = REPO / page
    text = re.sub(r"```.*?```", "", src.read_text(encoding="utf-8"), flags=re.S)
    bad = []
    for link in _LINK.findall(text):
        if re.match(r"^[a-z]+:", link):  # http:, https:, mailto:
            continue
        path, _, anchor = link.partition("#")
        target = (src.parent / path).resolve() if path else src
        if not target.exists():
            bad.append((link, "no such file"))
        elif anchor and target.suffix == ".md" and anchor not in anchors(target):
            bad.append((link, "no such heading"))
    return bad


def test_anchors_follow_github():
    assert anchor_of("Quick start (fresh machine, Python ≥ 3.10)") == "quick-start-fresh-machine-python--310"
    assert anchor_of("4. Delta pushes") == "4-delta-pushes"


def test_every_relative_link_of_the_docs_resolves():
    bad = {page: broken_links(page) for page in PAGES}
    assert not {p: b for p, b in bad.items() if b}
