"""Slicer's side of the geometry: RAS/LPS, the CTToSensor matrix, clouds decimated and drawn as small triangles.

Slicer's scene is RAS, in millimetres, and the registration's sensor frame is shown as it is
(its x, y, z on Slicer's R, A, S axes). A model file of the CT in LPS (DICOM's convention, and
what Slicer writes) is loaded into Slicer with x and y negated, so the matrix sent maps Slicer's
RAS coordinates of the CT into the sensor frame: M = T_sensor_ct @ C, where C converts Slicer's
RAS into the ct frame's own convention (C = diag(-1, -1, 1, 1) for LPS, the identity for RAS).
Put the CT's nodes (volume, segmentation, models, PreopModel) under that transform in Slicer.
"""

from __future__ import annotations

import numpy as np

from liver_p2p_reg.errors import InputError

_FLIP_XY = np.diag([-1.0, -1.0, 1.0, 1.0])  # RAS <-> LPS, its own inverse (a rotation: keeps triangle winding)
# Each point is drawn as a right triangle in one of three axis planes, in turn, so that from any
# view direction at least two thirds of them face the camera.
_SPLAT_LEGS = np.array(
    [
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]],
    ]
)


def _ras_from_ct(convention: str) -> np.ndarray:
    if convention == "LPS":
        return _FLIP_XY
    if convention == "RAS":
        return np.eye(4)
    raise InputError(f"ct_convention must be LPS or RAS, got {convention!r}")


def slicer_transform(T_sensor_ct_mm: np.ndarray, ct_convention: str) -> np.ndarray:
    """The CTToSensor matrix Slicer applies to RAS coordinates of the CT: T_sensor_ct @ C (mm)."""
    T = np.asarray(T_sensor_ct_mm, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError("the pose must be a finite 4x4 matrix")
    return T @ _ras_from_ct(ct_convention)  # C is its own inverse: RAS -> ct equals ct -> RAS


def ct_to_slicer(points_ct_mm: np.ndarray, ct_convention: str) -> np.ndarray:
    """Points of the ct frame (mm) in Slicer's RAS coordinates of the CT."""
    points = np.asarray(points_ct_mm, dtype=np.float64).reshape(-1, 3)
    return points * np.diag(_ras_from_ct(ct_convention))[:3]


def decimate(points: np.ndarray, max_points: int) -> np.ndarray:
    """At most `max_points` of the points, evenly spread over the array (deterministic)."""
    points = np.asarray(points).reshape(-1, 3)
    if len(points) <= max_points:
        return points
    return points[np.linspace(0, len(points) - 1, max_points).round().astype(np.int64)]


def splat(points_mm: np.ndarray, size_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(3N points, N triangles) drawing each point as a small triangle; the first N points are the cloud.

    Why not vertex cells: Slicer's OpenIGTLink POLYDATA converter writes vertex i's id into slot i
    of a one-id cell (out of bounds from the second vertex on), so a cloud sent as vertices shows
    one point at best; polygons are read correctly.
    """
    points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    legs = _SPLAT_LEGS[np.arange(n) % 3] * size_mm  # (N, 2, 3)
    vertices = np.concatenate([points, points + legs[:, 0], points + legs[:, 1]])
    index = np.arange(n)
    return vertices, np.column_stack([index, index + n, index + 2 * n])
