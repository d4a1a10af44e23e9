"""The README stays short and keeps its two commands; every relative link of the docs resolves."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from conftest import REPO

README = REPO / "README.md"
PAGES = [README, *sorted((REPO / "docs").rglob("*.md"))]

#: The project's contract with a new user and with CI (.ci/run runs the second command).
TWO_COMMANDS = """```bash
# 1. install, and run the main job on the built-in synthetic case (writes demo_out/)
python -m pip install . && plenopiv demo --out demo_out

# 2. install, and run the test suite
python -m pip install ".[test]" && python -m pytest
```"""


def test_readme_is_short_with_short_lines():
    lines = README.read_text().splitlines()
    assert len(lines) <= 250, f"README.md has {len(lines)} lines: at most 250"
    long = [i + 1 for i, line in enumerate(lines) if len(line) > 300]
    assert not long, f"README.md lines over 300 characters: {long}"


def test_readme_keeps_the_two_commands():
    text = README.read_text()
    assert "## The two commands" in text and TWO_COMMANDS in text


def _prose(text: str) -> str:
    """The text outside fenced code blocks and inline code."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)
    return re.sub(r"`[^`\n]*`", "", text)


def links(page: Path) -> list[str]:
    """The targets of the Markdown links and images of a page."""
    found = re.findall(r"!?\[[^\]]*\]\(([^)\s]+)\)", _prose(page.read_text()))
    return [m.strip("<>") for m in found]


def anchors(page: Path) -> set[str]:
    """The anchors of a page's headings, as GitHub makes them."""
    out = set()
    for heading in re.findall(r"^#{1,6} (.+)$", re.sub(r"^```.*?^```", "", page.read_text(),
                                                          flags=re.M | re.S), re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
        out.add(slug)
    return out


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(page):
    broken = []
    for target in links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):       # https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        dest = page if not path else (page.parent / path).resolve()
        if not dest.exists():
            broken.append(target)
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(target)
        elif dest.is_dir():
            broken.append(f"{target} (a folder: link its index.md)")
    assert not broken, f"{page.relative_to(REPO)}: links that do not resolve: {broken}"


def test_docs_index_links_every_page():
    index = REPO / "docs" / "index.md"
    linked = {(index.parent / t.partition("#")[0]).resolve() for t in links(index)}
    pages = {p.resolve() for p in (REPO / "docs").glob("*.md")} - {index.resolve()}
    pages.add((REPO / "docs" / "validation" / "index.md").resolve())
    missing = sorted(str(p.relative_to(REPO)) for p in pages - linked)
    assert not missing, f"docs/index.md does not link: {missing}"
