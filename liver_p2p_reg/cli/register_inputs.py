"""The register command's optional inputs: a prior pose (--initial-transform), a sensor origin, fiducials, weights."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from liver_p2p_reg.errors import InputError

LOG = logging.getLogger("liver_p2p_reg")
# A rigid pose's last row, as written (a text matrix printed with a few decimals still matches).
BOTTOM_ROW_TOL = 1e-6


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
            raw = np.load(path, allow_pickle=False)
            if raw.dtype.kind not in "fiu":  # complex (its imaginary part dropped with a warning), text, bool
                raise ValueError(f"it holds {raw.dtype} values, not real numbers")
            matrix = raw.astype(np.float64)
        else:
            matrix = np.loadtxt(path, dtype=np.float64, ndmin=2, delimiter=None, comments="#")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"cannot read --initial-transform {path}: {str(exc).splitlines()[0]}") from None
    if matrix.shape != (4, 4):
        raise InputError(f"--initial-transform {path}: expected a 4x4 matrix, got shape {matrix.shape}")
    _require_rigid_bottom_row(matrix, path)
    return matrix


def _require_rigid_bottom_row(matrix: Any, path: Path) -> None:
    """InputError unless the last row is 0 0 0 1: a projective row passes the 3x3 rotation check, then skews points."""
    import numpy as np

    if not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=BOTTOM_ROW_TOL):  # NaN fails too
        row = " ".join(f"{v:g}" for v in matrix[3])
        raise InputError(f"--initial-transform {path}: not a rigid transform (bottom row is {row}, expected 0 0 0 1)")


def load_fiducials(path: str | Path, option: str, max_extent_mm: float) -> Any:
    """(F, 3) fiducials in mm from a point file; InputError (one line) when they look like metres.

    The structures' units rule (structures_io): a few fiducials may span less than a liver, so the
    liver's extent minimum does not apply, but every coordinate below 1 mm, or a spread below 1 mm, is metres.
    """
    import numpy as np

    from liver_p2p_reg.cloud_io import extent_mm, implausible_extent, load_points
    from liver_p2p_reg.structures_io import MIN_COORDINATE_MM, MIN_EXTENT_MM

    points = load_points(path)
    finite = points[np.isfinite(points).all(axis=1)]  # NaN pairs are the Registrar's to refuse, with their count
    problem = ""
    if len(finite) and np.max(np.abs(finite)) < MIN_COORDINATE_MM:
        problem = f"every coordinate is below {MIN_COORDINATE_MM:g} mm in magnitude: metres?"
    elif len(finite) > 1:
        problem = implausible_extent(extent_mm(finite), "their", MIN_EXTENT_MM, max_extent_mm)
    if problem:
        raise InputError(f"{option} {path}: {problem} (fiducials are read as millimetres: convert a file in metres)")
    return points


def warn_unused_weights(method: str, weights_path: str) -> None:
    """One warning line when weights are given to a method without the learned matcher (they would be ignored)."""
    from liver_p2p_reg.registration.methods import check_method_name

    row = check_method_name(method)
    if weights_path and row.run is None and row.features != "learned":  # a plug-in may read them: no warning
        LOG.warning("method '%s' does not use weights: --weights %s is ignored", method, weights_path)


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
