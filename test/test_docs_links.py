"""The documentation's relative links resolve to files that exist, and the README stays a front door (<= 300 lines)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README_MAX_LINES = 300

# [text](target) and ![alt](target), with an optional "title"; [label]: target reference definitions.
INLINE_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE_LINK = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+\"[^\"]*\")?\s*$", re.MULTILINE)
EXTERNAL = re.compile(r"^(?:[a-z][a-z0-9+.-]*:|//)", re.IGNORECASE)  # http:, https:, mailto:, ...


def documentation_files() -> list[Path]:
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), *sorted((ROOT / "msg_docs").glob("*.md"))]
    files.append(ROOT / "bags" / "README.md")
    return [f for f in files if f.is_file()]


def without_code(text: str) -> str:
    """The text with fenced code blocks and inline code spans removed (links in code are not links)."""
    text = re.sub(r"^(```|~~~).*?^\1[^\n]*$", "", text, flags=re.MULTILINE | re.DOTALL)
    return re.sub(r"(`+)(?:(?!\1).)+?\1", "", text, flags=re.DOTALL)


def relative_links(text: str) -> list[str]:
    """The relative link targets of a Markdown text, anchors stripped; external and in-page links left out."""
    text = without_code(text)
    targets = INLINE_LINK.findall(text) + REFERENCE_LINK.findall(text)
    out = []
    for target in targets:
        if EXTERNAL.match(target) or target.startswith("#"):
            continue
        path = target.split("#", 1)[0].split("?", 1)[0]
        if path:
            out.append(path)
    return out


def test_the_link_finder_sees_links_and_skips_code_anchors_and_urls() -> None:
    text = (
        'See [a](docs/a.md#part), ![pic](img/p.png "title"), [b](https://x.org/b.md), [c](mailto:me@x.org),\n'
        "[d](#local), `[e](in/code.md)`.\n\n```bash\n[f](in/fence.md)\n```\n[g]: ref/target.md\n"
    )
    assert relative_links(text) == ["docs/a.md", "img/p.png", "ref/target.md"]


def test_there_are_documentation_files() -> None:
    names = {f.relative_to(ROOT).as_posix() for f in documentation_files()}
    assert {"README.md", "docs/results/README.md", "msg_docs/README.md", "bags/README.md"} <= names


@pytest.mark.parametrize("doc", documentation_files(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_relative_link_resolves(doc: Path) -> None:
    broken = [link for link in relative_links(doc.read_text()) if not (doc.parent / link).exists()]
    assert not broken, f"{doc.relative_to(ROOT)}: links to missing files: {broken}"


def test_readme_is_at_most_300_lines() -> None:
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines (at most {README_MAX_LINES})"
