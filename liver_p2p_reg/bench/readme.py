"""The generated blocks of a README: the marker lines around a block, replacing one, links relative to the README."""

from __future__ import annotations

import os
from pathlib import Path

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.files import write_text_atomic


def readme_markers(name: str = "BENCHMARK") -> tuple[str, str]:
    """The comment lines around a generated README block."""
    return f"<!-- {name}:START -->", f"<!-- {name}:END -->"


def _block_span(readme: Path, name: str) -> tuple[str, int, int]:
    """The README's text and where its `name` block's markers start; InputError when unreadable or unmarked."""
    start_marker, end_marker = readme_markers(name)
    if not readme.exists():
        raise InputError(f"README {readme} does not exist")
    try:
        text = readme.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read {readme}: {getattr(exc, 'strerror', None) or exc}") from None
    start, end = text.find(start_marker), text.find(end_marker)
    if start < 0 or end < 0 or end < start:
        raise InputError(f"{readme} lacks the {start_marker} ... {end_marker} markers")
    return text, start, end


def check_readme(readme: str | Path, name: str = "BENCHMARK") -> None:
    """Before the work: the README exists and holds the `name` block (not an error after hours of registrations)."""
    _block_span(Path(readme), name)


def replace_readme_block(readme: Path, block: str, name: str = "BENCHMARK") -> None:
    """Replace the text between the `name` markers of `readme` with `block`."""
    start_marker, _ = readme_markers(name)
    text, start, end = _block_span(readme, name)
    new = text[: start + len(start_marker)] + "\n" + block.strip() + "\n" + text[end:]
    write_text_atomic(readme, new)


def relative_link(target: Path, start_dir: Path) -> str:
    """A POSIX relative link from `start_dir` to `target` (for the README)."""
    return Path(os.path.relpath(target.resolve(), start_dir.resolve())).as_posix()


def write_headline(caption: str, lines: list[str], readme: str | None, name: str) -> str:
    """A headline block (caption, blank line, table lines): printed, and written into `readme`'s `name` block
    when a README is given; returns its text."""
    text = "\n".join([caption, "", *lines])
    print(text)
    if readme:
        replace_readme_block(Path(readme), text, name)
    return text
