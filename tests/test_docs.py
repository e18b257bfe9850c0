"""The README is a first screen; the reference is in docs/, reachable from its index.

* README.md is at most 8 KB; its first screen shows what the tool does, the install
  and demo command, the two commands (``calibrate``, ``run``) and one table, and it
  keeps the section ``## Accuracy on real images`` with a table;
* docs/README.md links every page below docs/;
* every relative link of the README and of docs/ names a file that exists.
"""

from __future__ import annotations

import re
from pathlib import Path

from conftest import PROJECT_ROOT

README = PROJECT_ROOT / "README.md"
DOCS = PROJECT_ROOT / "docs"
#: Lines of a first screen (a terminal or a browser window, about).
FIRST_SCREEN = 60
#: README command 1: install the core (no extra) and run the demo.
COMMAND_ONE = (
    "python3 -m venv .venv && .venv/bin/pip install -e . && .venv/bin/colmap-trifocal demo"
)


def _links(path: Path) -> list[str]:
    """The relative link targets of a Markdown file (no URLs, no anchors alone)."""
    targets = re.findall(r"\]\(([^)\s]+)\)", path.read_text())
    return [t.split("#")[0] for t in targets if "://" not in t and not t.startswith("#")]


def test_readme_is_a_first_screen() -> None:
    assert README.stat().st_size <= 8 * 1024
    text = README.read_text()
    first = "\n".join(text.splitlines()[:FIRST_SCREEN])
    assert COMMAND_ONE in first
    assert "colmap-trifocal calibrate database.db" in first
    assert "colmap-trifocal run IMAGES WORKSPACE" in first
    assert re.search(r"^\|---\|", first, flags=re.MULTILINE), "no table on the first screen"
    section = text.split("\n## Accuracy on real images\n", 1)[1].split("\n## ", 1)[0]
    assert re.search(r"^\| .* \|$", section, flags=re.MULTILINE), "the section has no table"


def test_the_docs_index_links_every_page() -> None:
    index = DOCS / "README.md"
    linked = {(index.parent / target).resolve() for target in _links(index)}
    pages = {p.resolve() for p in DOCS.rglob("*.md")} - {index.resolve()}
    assert pages - linked == set(), "docs/README.md does not link these pages"
    assert (DOCS / "README.md").relative_to(PROJECT_ROOT).as_posix() in _links(README)


def test_relative_links_resolve() -> None:
    broken = [
        f"{path.relative_to(PROJECT_ROOT)} -> {target}"
        for path in [README, PROJECT_ROOT / "CONTRIBUTING.md", *sorted(DOCS.rglob("*.md"))]
        for target in _links(path)
        if target and not (path.parent / target).exists()
    ]
    assert broken == []
