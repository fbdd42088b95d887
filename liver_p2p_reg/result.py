"""Result objects returned by every registration method (same shape for all methods)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Candidate:
    """One rigid-transform hypothesis (P2P: the complete-to-partial one or a patch)."""

    name: str  # "complete-to-partial", "patch-0", ...
    T_target_source: np.ndarray  # (4, 4) maps source mm into target mm
    residual_mm: float  # mean closest-point distance, target -> transformed source
    n_matches: int
    ok: bool = True  # False when Procrustes failed (too few / degenerate matches)
    inliers: int = 0  # matches within the inlier radius (used by the inlier-count rule)
    # share of the view's footprint this pose contradicts (freespace.py); NaN: sensor origin unknown
    free_space_violation: float = float("nan")
    # a screened contender's key under `contender_judge_ratio` (its residual after the elastic stage's fit from its
    # full ICP, mm; lowest wins); NaN: not judged
    judge_key_mm: float = float("nan")

    def to_json_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "transform": np.asarray(self.T_target_source).tolist(),
            "residual_mm": _finite_or_none(self.residual_mm),
            "n_matches": int(self.n_matches),
            "inliers": int(self.inliers),
            "ok": bool(self.ok),
            "free_space_violation": _finite_or_none(self.free_space_violation),
            "judge_key_mm": _finite_or_none(self.judge_key_mm),
        }


@dataclass
class RegistrationResult:
    """Outcome of one registration: the transform in mm, its quality, candidates, timings."""

    T_target_source: np.ndarray  # (4, 4): p_target = R p_source + t, millimetres
    method: str
    residual_mm: float  # mean closest-point distance target -> transformed source (mm)
    runtime_ms: dict[str, float] = field(default_factory=dict)  # per stage + "total"
    candidates: list[Candidate] = field(default_factory=list)
    chosen: int | None = None  # index into candidates (P2P methods)
    n_matches: int = 0
    visibility: float = float("nan")  # M/N after voxelization
    n_source: int = 0  # points after preprocessing
    n_target: int = 0
    ambiguous: bool = False  # two candidates fit nearly equally well with different poses
    # expected organ-point displacement given the final fit's misfit and the view's shape (mm):
    # large when the visible surface leaves the pose poorly constrained (confidence.py)
    uncertainty_mm: float = float("nan")
    # `-icp` feature methods: each screened candidate after its short ICP (the ambiguity test uses these)
    screened: list[Candidate] = field(default_factory=list)
    # share of the view's footprint the final pose contradicts (freespace.py): NaN when the sensor
    # origin is unknown or was refused; `free_space` says which ("", "on", "off: <why>")
    free_space_violation: float = float("nan")
    free_space: str = ""
    ok: bool = True
    message: str = ""
    # conditions the user must hear about although a pose was found (e.g. prepared weights made
    # for another liver: the general ones were used); the node reports them as WARN
    warnings: list[str] = field(default_factory=list)
    rms_tre_mm: float | None = None  # filled when ground-truth fiducials are given
    max_tre_mm: float | None = None
    # the interior's RMS error lies below this with `error_coverage` (registration/error_bound.py; its scale is
    # taken over the interior's stand-in, the preop surface shrunk halfway to its centroid, fiducials given or not)
    error_bound_mm: float = float("nan")
    error_coverage: float = float("nan")
    error_model: Any = None  # evaluates per-point bounds (registration/error_calibration.ErrorModel)
    error_calibration_note: str = ""  # why the bound's coverage is not known here (another method, other weights)
    # the non-rigid stage (registration/deform.py), when it ran: applied or why not, the displacement of any point
    deformation: Any = None
    deformed_rms_tre_mm: float | None = None  # fiducial RMS error of the deformed positions (ground truth given)
    # the bound of the deformed positions when the stage was applied (calibrated on validation poses where it was)
    deformed_error_model: Any = None
    deformed_error_bound_mm: float = float("nan")
    deformed_error_calibration_note: str = ""

    def error_bound_at(self, points_mm: np.ndarray) -> np.ndarray:
        """Per preop point (mm): the distance within which its true position lies with `error_coverage`."""
        points_mm = np.asarray(points_mm, float).reshape(-1, 3)
        if self.error_model is None:
            return np.full(len(points_mm), np.nan)
        return self.error_model.bounds_mm(points_mm)

    def deformed_error_bound_at(self, points_mm: np.ndarray) -> np.ndarray | None:
        """Per preop point (mm): the bound of its deformed position; None when the stage was not applied."""
        if self.deformed_error_model is None:
            return None
        return self.deformed_error_model.bounds_mm(np.asarray(points_mm, float).reshape(-1, 3))

    @property
    def rotation(self) -> np.ndarray:
        return np.asarray(self.T_target_source)[:3, :3]

    @property
    def translation_mm(self) -> np.ndarray:
        return np.asarray(self.T_target_source)[:3, 3]

    def to_json_dict(self) -> dict[str, Any]:
        """JSON-serializable dict (the CLI's output format)."""
        out: dict[str, Any] = {
            "transform": np.asarray(self.T_target_source).tolist(),
            "method": self.method,
            "ok": bool(self.ok),
            "message": self.message,
            "residual_mm": _finite_or_none(self.residual_mm),
            "runtime_ms": {k: round(float(v), 3) for k, v in self.runtime_ms.items()},
            "n_matches": int(self.n_matches),
            "visibility": _finite_or_none(self.visibility),
            "n_source": int(self.n_source),
            "n_target": int(self.n_target),
            "ambiguous": bool(self.ambiguous),
            "uncertainty_mm": _finite_or_none(self.uncertainty_mm),
            "error_bound_mm": _finite_or_none(self.error_bound_mm),
            "error_coverage": _finite_or_none(self.error_coverage),
            "error_calibration_note": self.error_calibration_note,
            "free_space_violation": _finite_or_none(self.free_space_violation),
            "free_space": self.free_space,
            "chosen_candidate": self.chosen,
            "candidates": [c.to_json_dict() for c in self.candidates],
            "screened": [c.to_json_dict() for c in self.screened],
            "warnings": list(self.warnings),
        }
        if self.rms_tre_mm is not None:
            out["rms_tre_mm"] = _finite_or_none(self.rms_tre_mm)
            out["max_tre_mm"] = _finite_or_none(self.max_tre_mm)
        if self.deformation is not None:
            out["deformation"] = self.deformation.to_json_dict()
        if self.deformed_rms_tre_mm is not None:
            out["deformed_rms_tre_mm"] = _finite_or_none(self.deformed_rms_tre_mm)
        if self.deformed_error_model is not None:
            out["deformed_error_bound_mm"] = _finite_or_none(self.deformed_error_bound_mm)
        if self.deformed_error_model is not None or self.deformed_error_calibration_note:
            out["deformed_error_calibration_note"] = self.deformed_error_calibration_note
        return out

    def __repr__(self) -> str:
        t = self.translation_mm
        tre = "" if self.rms_tre_mm is None else f", rms_tre={self.rms_tre_mm:.2f} mm"
        return (
            f"RegistrationResult(method={self.method!r}, ok={self.ok}, "
            f"residual={self.residual_mm:.2f} mm{tre}, t=[{t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f}] mm, "
            f"candidates={len(self.candidates)}, chosen={self.chosen}, "
            f"total={self.runtime_ms.get('total', float('nan')):.1f} ms)"
        )


def _finite_or_none(value: float | None) -> float | None:
    if value is None:
        return None
    value = float(value)
    return value if np.isfinite(value) else None
