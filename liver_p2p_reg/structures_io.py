"""Subsurface structures (tumours, vessels, a resection plan): `FILE[:LABEL]` files in mm, and where a pose puts them."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from liver_p2p_reg.cloud_io import check_point_file, extent_mm, implausible_extent, load_points
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.metrics import transform_points

# A structure is small (a tumour 5-40 mm across) and may be a single point, so the liver's extent
# rule does not apply. A file in metres is still recognised: every coordinate of a CT in metres lies
# within 1 of the origin (a CT in mm does not), or several points span less than a millimetre.
MIN_COORDINATE_MM = 1.0  # every |coordinate| below this: the file holds metres
MIN_EXTENT_MM = 1.0  # several points spanning less than this: metres (no structure is that small)
UNITS_HINT = "structure points are read as millimetres in the preop (ct) frame: convert a file in metres"
# Every point is carried through the registration and written to the JSON (~200 bytes each), so a dense vessel
# cloud costs seconds and gigabytes (1M points: 18 s, 2 GB, a 205 MB JSON): refused, with what to do, above this.
MAX_STRUCTURE_POINTS = 200_000


@dataclass(frozen=True, eq=False)  # eq=False: arrays do not compare as one truth value
class Structure:
    """One subsurface structure in the preop frame: its label, its points (mm) and where they came from."""

    label: str
    points_mm: np.ndarray  # (N, 3), preop (ct) frame, all finite
    label_id: int = 0  # its index in the loader's label list (/preop/structure_labels)
    path: str = ""  # the file it was read from ("" when it came from a message)


@dataclass(eq=False)
class PlacedStructure:
    """A structure where one registration puts it, each point with its error bound."""

    label: str
    label_id: int
    position_mm: np.ndarray  # (N, 3): the preop points moved rigidly by the pose, T_target_source
    error_bound_mm: np.ndarray  # (N,): the true position lies within this of position_mm with `coverage`; NaN: no model
    coverage: float  # result.error_coverage (NaN without an error model)
    # Where the non-rigid stage (registration/deform.py) puts the points, sensor frame; None: it did not run or
    # was not applied (its reason is in the result's `deformation`), position_mm is all there is.
    deformed_position_mm: np.ndarray | None = None
    # (N,) the bound of each deformed position (the deformed-position calibration); None with the positions
    deformed_error_bound_mm: np.ndarray | None = None

    @property
    def current_position_mm(self) -> np.ndarray:
        """Where the structure is now: its deformed positions when the non-rigid stage was applied, else rigid."""
        return self.position_mm if self.deformed_position_mm is None else self.deformed_position_mm

    @property
    def current_error_bound_mm(self) -> np.ndarray:
        """The bound of current_position_mm: the deformed positions' when they are given, else the rigid one's."""
        if self.deformed_position_mm is None:
            return self.error_bound_mm
        if self.deformed_error_bound_mm is None:  # no calibration of deformed positions: no bound (NaN)
            return np.full(len(self.deformed_position_mm), np.nan)
        return self.deformed_error_bound_mm

    def to_json_dict(self) -> dict[str, Any]:
        """The `structures` entry of a result JSON: label, position_mm (N x 3), error_bound_mm (N; null: no model)."""
        out: dict[str, Any] = {
            "label": self.label,
            "n_points": len(self.position_mm),
            "position_mm": np.round(self.position_mm, 6).tolist(),
            "error_bound_mm": [_finite_or_none(b) for b in self.error_bound_mm],
            "max_error_bound_mm": _finite_or_none(np.max(self.error_bound_mm)) if len(self.error_bound_mm) else None,
            "error_coverage": _finite_or_none(self.coverage),
        }
        if self.deformed_position_mm is not None:
            out["deformed_position_mm"] = np.round(self.deformed_position_mm, 6).tolist()
        if self.deformed_error_bound_mm is not None:
            out["deformed_error_bound_mm"] = [_finite_or_none(b) for b in self.deformed_error_bound_mm]
        return out


def parse_spec(spec: str) -> tuple[Path, str]:
    """'FILE[:LABEL]' -> (file, label); the label defaults to the file's stem.

    A spec naming an existing file is that file (its name may hold a ':'); else the text after the
    last ':' is the label, unless it holds a '/' (then the colon was part of a folder's name).
    """
    text = str(spec)
    path, sep, label = text.rpartition(":")
    if Path(text).is_file() or not sep or "/" in label:
        path, label = text, Path(text).stem
    if not path:
        raise InputError(f"structure {text!r}: no file before the ':' (expected FILE[:LABEL])")
    if not label or label != label.strip() or not label.isprintable():
        raise InputError(f"structure {text!r}: the label must be printable text without surrounding spaces")
    return Path(path), label


def load_structure(
    path: str | Path,
    label: str,
    *,
    label_id: int = 0,
    to_mm: float = 1.0,
    max_extent_mm: float = Config.expected_extent_max_mm,
) -> Structure:
    """Read one structure file (a mesh gives its vertices, a cloud its points); `to_mm` scales the
    file's units into mm. InputError (one line naming the label and the file) when it cannot be used."""
    where = f"structure '{label}'"
    try:
        path = check_point_file(path)
        points = load_points(path, sample_meshes=False) * float(to_mm)  # a mesh: its vertices, no surface samples
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None
    bad = int((~np.isfinite(points).all(axis=1)).sum())
    if bad:
        raise InputError(f"{where}: {path}: {bad} of {len(points)} points are NaN or infinite")
    _, first = np.unique(points, axis=0, return_index=True)
    points = points[np.sort(first)]  # an STL repeats each vertex per triangle: once each, in file order
    if len(points) > MAX_STRUCTURE_POINTS:
        raise InputError(
            f"{where}: {path}: {len(points)} points, more than the {MAX_STRUCTURE_POINTS} a structure may have: "
            "decimate it (a structure's points are reported one by one)"
        )
    problem = ""
    if np.max(np.abs(points)) < MIN_COORDINATE_MM:
        problem = f"every coordinate is below {MIN_COORDINATE_MM:g} mm in magnitude: metres?"
    elif len(points) > 1:
        problem = implausible_extent(extent_mm(points), "its", MIN_EXTENT_MM, max_extent_mm)
    if problem:
        raise InputError(f"{where}: {path}: {problem} ({UNITS_HINT})")
    return Structure(label, points, int(label_id), str(path))


def read_structures(
    specs: Sequence[str], *, to_mm: float = 1.0, max_extent_mm: float = Config.expected_extent_max_mm
) -> tuple[list[Structure], list[tuple[str, str]]]:
    """(the structures that could be read, [(spec, one-line reason)] of those that could not).

    Label ids are the good structures' indices in order; a label given twice is refused the second time.
    """
    good: list[Structure] = []
    bad: list[tuple[str, str]] = []
    for spec in specs:
        try:
            path, label = parse_spec(spec)
            twin = next((s for s in good if s.label == label), None)
            if twin is not None:
                raise InputError(
                    f"structure label '{label}' given twice ({twin.path} and {path}): name them FILE:LABEL"
                )
            good.append(load_structure(path, label, label_id=len(good), to_mm=to_mm, max_extent_mm=max_extent_mm))
        except InputError as exc:
            bad.append((str(spec), str(exc)))
    return good, bad


def far_from_model(structure: Structure, model_mm: np.ndarray) -> str:
    """Why a structure cannot belong to this preop model ("" when it can): a point farther outside the model's
    bounding box than the model's size (a tumour lies inside the organ; a vessel such as the vena cava may run on
    for ten centimetres or more; farther means another frame or unit)."""
    model = np.asarray(model_mm, dtype=np.float64).reshape(-1, 3)
    lo, hi = model.min(axis=0), model.max(axis=0)
    margin = float(np.linalg.norm(hi - lo))
    outside = np.linalg.norm(np.maximum(lo - structure.points_mm, 0) + np.maximum(structure.points_mm - hi, 0), axis=1)
    worst = float(outside.max()) if len(outside) else 0.0
    if worst <= margin:
        return ""
    return (
        f"structure '{structure.label}': a point lies {worst:.0f} mm outside the preop model's bounding box "
        f"(more than the model's size, {margin:.0f} mm): another frame or unit than the model's?"
    )


def load_structures(specs: Sequence[str], *, to_mm: float = 1.0) -> list[Structure]:
    """Every structure of `specs` ('FILE[:LABEL]' each), or the first one's InputError that cannot be used."""
    good, bad = read_structures(specs, to_mm=to_mm)
    if bad:
        raise InputError(bad[0][1])
    return good


def place_structures(
    result: Any, structures: Sequence[Structure], T_mm: np.ndarray | None = None
) -> list[PlacedStructure]:
    """Where a registration puts each structure: its points moved by T (default result.T_target_source)
    and, per point, `result.error_bound_at` of its preop position (mm); where the non-rigid stage was applied,
    also the deformed positions and their bounds (`result.deformed_error_bound_at`)."""
    T = np.asarray(result.T_target_source if T_mm is None else T_mm, dtype=np.float64)
    coverage = float(getattr(result, "error_coverage", float("nan")))
    deformation = getattr(result, "deformation", None)
    applied = deformation is not None and deformation.applied and T_mm is None
    deformed_bound = getattr(result, "deformed_error_bound_at", lambda _: None) if applied else (lambda _: None)

    def floats(values: Any) -> np.ndarray | None:
        return None if values is None else np.asarray(values, dtype=np.float64).reshape(-1)

    return [
        PlacedStructure(
            s.label,
            s.label_id,
            transform_points(T, s.points_mm),
            floats(result.error_bound_at(s.points_mm)),
            coverage,
            deformation.deformed_position_mm(s.points_mm) if applied else None,
            floats(deformed_bound(s.points_mm)),
        )
        for s in structures
    ]


def stacked_points(structures: Sequence[Structure]) -> tuple[np.ndarray, np.ndarray]:
    """Every structure's points one after the other (N x 3, mm) and each point's label id (N,): a structures cloud."""
    points = np.concatenate([s.points_mm for s in structures]) if structures else np.zeros((0, 3))
    ids = np.concatenate([np.full(len(s.points_mm), s.label_id) for s in structures]) if structures else np.zeros(0)
    return points, ids.astype(np.int64)


def stacked_placement(placed: Sequence[PlacedStructure]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where a pose put every structure, one after the other: each point's label id (N,), its current position
    (N x 3, mm; deformed where the stage was applied) and that position's bound (N,, mm)."""
    if not placed:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0)
    ids = np.concatenate([np.full(len(s.position_mm), s.label_id, dtype=np.int64) for s in placed])
    points = np.concatenate([s.current_position_mm for s in placed])
    return ids, points, np.concatenate([s.current_error_bound_mm for s in placed])


def structure_bounds(placed: Sequence[PlacedStructure]) -> dict[str, np.ndarray]:
    """label -> per-point bounds (mm): what `confidence.result_warnings(..., structure_bounds_mm=)` takes."""
    return {p.label: p.error_bound_mm for p in placed}


def _finite_or_none(value: Any) -> float | None:
    value = float(value)
    return round(value, 6) if np.isfinite(value) else None
