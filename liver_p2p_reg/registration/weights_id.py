"""Which matcher weights a configuration reads, and their SHA-256 (what a recording and a calibration were made with)."""

from __future__ import annotations

import hashlib
from pathlib import Path

from liver_p2p_reg.config import Config

_HASHES: dict[tuple[str, int, int], str] = {}


def weights_file(config: Config) -> Path | None:
    """The matcher weights a config's method reads (None: the method uses none)."""
    if config.weights_path:
        return Path(config.weights_path)
    if not config.method.startswith("learned"):
        return None
    from liver_p2p_reg.registration.features.learned.weights import BUNDLED_WEIGHTS

    return BUNDLED_WEIGHTS


def weights_sha256(config: Config) -> str:
    """sha256 of the weights file the config's method reads ("" when none; "missing: PATH" if absent)."""
    path = weights_file(config)
    if path is None:
        return ""
    try:
        stat = path.stat()
    except OSError:
        return f"missing: {path}"
    key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    if key not in _HASHES:
        digest = hashlib.sha256()
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
        _HASHES[key] = digest.hexdigest()
    return _HASHES[key]
