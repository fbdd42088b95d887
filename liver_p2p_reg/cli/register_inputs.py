"""The register command's optional inputs: a prior pose (--initial-transform), a sensor origin, structure files."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from liver_p2p_reg.errors import InputError


def load_initial_transform(path: Path) -> Any:
    """A 4x4 pose from a JSON result (its "transform"), a JSON/NPY matrix or a whitespace text matrix."""
    import numpy as np

    if not path.is_file():
        raise InputError(f"file not found: {path}")
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(path.read_text())
            matrix = np.asarray(data["transform"] if isinstance(data, dict) else data, dtype=np.float64)
        elif path.suffix.lower() == ".npy":
            matrix = np.load(path, allow_pickle=False)
        else:
            matrix = np.loadtxt(path, dtype=np.float64, ndmin=2, delimiter=None, comments="#")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"cannot read --initial-transform {path}: {str(exc).splitlines()[0]}") from None
    if matrix.shape != (4, 4):
        raise InputError(f"--initial-transform {path}: expected a 4x4 matrix, got shape {matrix.shape}")
    return matrix


def sensor_origin(text: str | None) -> list[float] | None:
    """`X,Y,Z` in mm -> three numbers; a bad value is one InputError line."""
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not all(abs(v) < float("inf") for v in values):
        raise InputError(f"--sensor-origin must be three finite numbers X,Y,Z in mm, got {text!r}")
    return values
