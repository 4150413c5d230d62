"""The documentation a clone holds is all it needs (issue 29, items 9 and 10).

The design lives in ``docs/design.md``: no file of the repository points to design notes
outside it, which a clone does not have. Every relative link of the README and of the
guides in ``docs/`` reaches a file that exists, and an anchor (``#section``) a heading of
that file, so that moving a section from one page to another cannot leave a dead link.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

# Spelled in two parts so that this file does not mention them itself.
OUTSIDE_NOTES = ("../" + "shared", "DESIGN" + ".md")

SKIPPED_DIRS = {".git", ".venv", "node_modules", "var", "__pycache__", ".mypy_cache"}
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)")
HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$")
FENCE = re.compile(r"^\s*(```|~~~)")


def repository_files() -> list[Path]:
    """The files a clone has: git's list when there is one, else the tree less what is built."""
    try:
        listed = subprocess.run(
            ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True
        ).stdout
        return [ROOT / name for name in listed.decode().split("\0") if name]
    except (OSError, subprocess.CalledProcessError):
        return [
            path
            for path in ROOT.rglob("*")
            if path.is_file() and not SKIPPED_DIRS.intersection(path.relative_to(ROOT).parts)
        ]


def documentation() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def outside_fences(text: str) -> list[str]:
    """The lines of a Markdown text that are not inside a fenced code block."""
    lines, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
        elif not fenced:
            lines.append(line)
    return lines


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    found: set[str] = set()
    seen: dict[str, int] = {}
    for line in outside_fences(page.read_text(encoding="utf-8")):
        match = HEADING.match(line)
        if match:
            base = slug(match.group(1))
            count = seen.get(base, 0)
            seen[base] = count + 1
            found.add(base if count == 0 else f"{base}-{count}")
    return found


def relative_links(page: Path) -> list[str]:
    links = []
    for line in outside_fences(page.read_text(encoding="utf-8")):
        for target in LINK.findall(line):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:, opc.tcp:
                continue
            links.append(target)
    return links


def test_no_file_points_to_design_notes_outside_the_repository() -> None:
    offenders = []
    for path in repository_files():
        if not path.is_file():
            continue
        data = path.read_bytes()
        for needle in OUTSIDE_NOTES:
            if needle.encode() in data:
                offenders.append(f"{path.relative_to(ROOT)}: {needle}")
    assert offenders == []


def test_the_design_is_in_the_repository() -> None:
    design = ROOT / "docs" / "design.md"
    assert design.is_file()
    cited = {"One scan", "Safety", "Publishing", "Recipes", "Tags"}
    assert {slug(name) for name in cited} <= anchors(design)


@pytest.mark.parametrize("page", documentation(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_reaches_a_file_and_its_heading(page: Path) -> None:
    dead = []
    for target in relative_links(page):
        file_part, _, anchor = target.partition("#")
        linked = (page.parent / file_part).resolve() if file_part else page
        if not linked.exists():
            dead.append(f"{target}: no such file")
        elif anchor and linked.suffix == ".md" and anchor not in anchors(linked):
            dead.append(f"{target}: no heading #{anchor} in {linked.relative_to(ROOT)}")
    assert dead == []


def test_the_readme_opens_with_its_two_commands() -> None:
    """A newcomer reads ``make run`` and ``make test`` before anything else (.ci/run runs the
    second on a clean clone)."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    first_block = readme.split("```sh\n", 1)[1].split("```", 1)[0]
    commands = [line.split("#", 1)[0].strip() for line in first_block.splitlines()]
    assert commands[:2] == ["make run", "make test"]


def test_the_adr_index_lists_every_decision() -> None:
    adr = ROOT / "docs" / "adr"
    index = (adr / "README.md").read_text(encoding="utf-8")
    records = sorted(path.name for path in adr.glob("[0-9][0-9][0-9][0-9]-*.md"))
    assert [name for name in records if f"]({name})" not in index] == []


SECTION_REFERENCE = re.compile(r'(README\.md|README|docs/[\w/.-]+\.md),? "([^"\n]+)"')


def named_sections(page: Path) -> set[str]:
    """What a reference may name in a page: its headings and its bold terms, lower case."""
    text = page.read_text(encoding="utf-8")
    lines = outside_fences(text)
    names = {m.group(1) for line in lines if (m := HEADING.match(line))}
    names |= set(re.findall(r"\*\*([^*\n]+)\*\*", text))
    return {name.replace("`", "").lower() for name in names}


def test_every_section_a_file_cites_is_in_the_page_it_names() -> None:
    """``docs/design.md "Safety"`` in a comment: that page has that heading (or bold term)."""
    dead = []
    for path in repository_files():
        if path.suffix not in {".py", ".md", ".yaml", ".yml", ".js", ".service", ""}:
            continue
        if not path.is_file():
            continue
        text = path.read_text(encoding="utf-8", errors="replace")
        for page_name, section in SECTION_REFERENCE.findall(text):
            page = ROOT / ("README.md" if page_name.startswith("README") else page_name)
            if not page.is_file():
                continue  # a README of another folder, named alone: not a section reference
            wanted = section.replace("`", "").lower()
            if not any(name.startswith(wanted) for name in named_sections(page)):
                dead.append(f"{path.relative_to(ROOT)}: {page_name} {section!r}")
    assert dead == []


TOP_FOLDERS = "supervisor|tests|deploy|io_maps|recipes|hmi|benchmarks|docs"
NAMED_PATH = re.compile(rf"`((?:{TOP_FOLDERS})/[^`\s]*)`")


def test_every_path_the_guides_name_exists() -> None:
    """A file or folder the README or a guide names in code style exists: a move (a package
    split, a renamed module) updates the page that describes it. The ADRs are records of
    their time and keep the names they had; a path with a placeholder (``<kind>``, ``*``)
    names no one file; ``tests/artifacts/`` is made by the tests; the design's "Target
    layout" names what is still to come."""
    missing = []
    for page in documentation():
        if "adr" in page.relative_to(ROOT).parts:
            continue
        text = page.read_text(encoding="utf-8").split("\n## Target layout", 1)[0]
        for named in NAMED_PATH.findall(text):
            path = named.split("::", 1)[0].rstrip(".,;:")
            if any(mark in path for mark in "*<{…") or "node_modules" in path:
                continue
            if path.startswith("tests/artifacts/"):
                continue
            if not (ROOT / path).exists():
                missing.append(f"{page.relative_to(ROOT)}: {path}")
    assert missing == []
