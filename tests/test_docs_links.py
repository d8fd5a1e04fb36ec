"""Relative links and #anchors in README.md and docs/*.md point at files and
headings that exist."""

from __future__ import annotations

import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parent.parent
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^(```|~~~)")


def _prose_lines(text: str):
    """The lines outside fenced code blocks."""
    fenced = False
    for line in text.splitlines():
        if FENCE.match(line.lstrip()):
            fenced = not fenced
            continue
        if not fenced:
            yield line


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces
    to hyphens."""
    text = heading.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(text: str) -> set[str]:
    """The anchors of a markdown text's ATX headings (repeated ones get -1, -2, ...)."""
    seen: dict[str, int] = {}
    found = set()
    for line in _prose_lines(text):
        match = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not match:
            continue
        base = slug(match.group(1))
        count = seen.get(base, 0)
        seen[base] = count + 1
        found.add(base if count == 0 else f"{base}-{count}")
    return found


def broken_links(path: pathlib.Path) -> list[str]:
    """Relative links of ``path`` whose file or #anchor does not exist."""
    prose = "\n".join(_prose_lines(path.read_text(encoding="utf-8")))
    problems = []
    for target in LINK.findall(prose):  # a link's text may run over a line break
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        file_part, _, anchor = target.partition("#")
        linked = (path.parent / file_part).resolve() if file_part else path
        if not linked.exists():
            problems.append(f"{path.name}: {target} (no file {file_part})")
        elif anchor and linked.suffix == ".md":
            if anchor not in anchors(linked.read_text(encoding="utf-8")):
                problems.append(f"{path.name}: {target} (no heading #{anchor})")
    return problems


def test_links_in_readme_and_docs_resolve():
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    problems = [p for page in pages for p in broken_links(page)]
    assert not problems, "\n".join(problems)


def test_the_check_finds_a_missing_file_and_a_missing_anchor(tmp_path):
    """The check itself can fail: a wrong anchor, a missing file, a code
    block ignored."""
    (tmp_path / "other.md").write_text("# Title\n\n## The paper's `G_z`, 2x2?\n")
    page = tmp_path / "page.md"
    page.write_text(
        "[ok](other.md#the-papers-g_z-2x2) [ok](#here) [web](https://example.org/#x)\n"
        "## Here\n"
        "[bad anchor](other.md#the-paper) [bad file](missing.md#title) [bad\n"
        "over two lines](#nowhere)\n"
        "```\n[in code](missing.md)\n```\n"
    )
    problems = broken_links(page)
    assert len(problems) == 3, problems
    assert any("#the-paper " in p for p in problems)
    assert any("no file missing.md" in p for p in problems)
    assert any("#nowhere" in p for p in problems)
