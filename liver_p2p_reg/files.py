"""File-system helpers every layer uses: a text file written whole or not at all, and whether a path lies in a folder."""

from __future__ import annotations

import os
from pathlib import Path


def write_text_atomic(path: Path, text: str) -> None:
    """Write `text` to `path` through a temporary file beside it and a rename: a run cut short leaves the old file
    (or none), never half of the new one."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def path_inside(inner: Path, outer: Path) -> bool:
    """True when `inner` is `outer` or lies under it (both resolved; a path that cannot be resolved: False)."""
    try:
        return Path(inner).resolve().is_relative_to(Path(outer).resolve())
    except (OSError, RuntimeError):  # RuntimeError: a symlink loop (Python 3.11)
        return False
