"""Links in the documentation stay inside the repository and point at something that exists.

Checks README.md, CHANGELOG.md, docs/*.md and policies/*.md: every relative Markdown link names an
existing file or folder inside the repository (never ``../shared`` or beyond the root), and a
``#anchor`` into a Markdown file names one of its headings (GitHub's slug rule).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", ROOT / "CHANGELOG.md", *(ROOT / "docs").glob("*.md"), *(ROOT / "policies").glob("*.md")])
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
OPTIONAL = {"docs/ros2.md"}  # written by another change; the link is kept (see docs/deployment.md)


def slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*_]{2,}|`", "", heading.strip().lower())
    text = "".join(ch for ch in text if ch.isalnum() or ch in " -_")
    return text.replace(" ", "-")


def anchors(md: Path) -> set[str]:
    out, in_code = set(), False
    for line in md.read_text().splitlines():
        if line.startswith("```"):
            in_code = not in_code
        elif not in_code and line.startswith("#"):
            out.add(slug(line.lstrip("#")))
    return out


def links(page: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    return [m.group(1) for m in LINK.finditer(text)]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_links_stay_inside_the_repository_and_resolve(page):
    bad = []
    for target in links(page):
        if re.match(r"^[a-z]+:", target):  # http(s), mailto: outside links are allowed only to public sites
            continue
        path_part, _, anchor = target.partition("#")
        dest = (page.parent / path_part).resolve() if path_part else page
        try:
            rel = dest.relative_to(ROOT).as_posix()
        except ValueError:
            bad.append(f"{target}: outside the repository")
            continue
        if not dest.exists():
            if rel not in OPTIONAL:
                bad.append(f"{target}: {rel} does not exist")
            continue
        if anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            bad.append(f"{target}: no heading #{anchor} in {rel}")
    assert not bad, f"{page.relative_to(ROOT)}:\n" + "\n".join(bad)


def test_readme_is_short_and_names_the_two_set_up_commands():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 150
    assert "pip install -e . && slinger up" in text and "bash tests/run.sh" in text
    assert "tests/run.sh" in (ROOT / ".ci" / "run").read_text()


def test_architecture_lists_every_module():
    """docs/architecture.md names every Python module of runtime/, sim_twin/ and server/ (add a row
    to its "Modules" tables when you add or move a module)."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    modules = [p.relative_to(ROOT).as_posix() for pkg in ("runtime", "sim_twin", "server") for p in (ROOT / pkg).rglob("*.py")
               if not (p.name == "__init__.py" and p.stat().st_size < 50) and "__pycache__" not in p.parts]
    missing = [m for m in sorted(modules) if f"`{m}`" not in text]
    assert not missing, "modules missing from docs/architecture.md: " + ", ".join(missing)
