"""Error metrics in millimetres: fiducial TRE and closest-point residual."""

from __future__ import annotations

import numpy as np


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 homogeneous transform to (N, 3) points."""
    T = np.asarray(T, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


def tre_mm(T: np.ndarray, source_fiducials_mm: np.ndarray, target_fiducials_mm: np.ndarray) -> np.ndarray:
    """Per-fiducial target registration error ||T(x_i) - y_i|| in mm, shape (F,)."""
    moved = transform_points(T, source_fiducials_mm)
    return np.linalg.norm(moved - np.asarray(target_fiducials_mm, dtype=np.float64), axis=1)


def rms_tre_mm(T: np.ndarray, source_fiducials_mm: np.ndarray, target_fiducials_mm: np.ndarray) -> float:
    """RMS-TRE = sqrt(mean ||T(x_i) - y_i||^2) over fiducials, as in the paper."""
    err = tre_mm(T, source_fiducials_mm, target_fiducials_mm)
    return float(np.sqrt(np.mean(err**2)))


def mean_closest_point_mm(target_mm: np.ndarray, moved_source_mm: np.ndarray) -> float:
    """Mean distance from each target point to its closest transformed-source point."""
    from scipy.spatial import cKDTree  # here, so importing the metrics costs no scipy

    dist, _ = cKDTree(moved_source_mm).query(target_mm, k=1)
    return float(np.mean(dist))


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Geodesic angle between two rotation matrices in degrees."""
    cos = (np.trace(np.asarray(R_a).T @ np.asarray(R_b)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
