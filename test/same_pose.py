"""How tests compare poses: bitwise on one machine, within a stated distance on the preop surface across machines."""

from __future__ import annotations

import numpy as np

# Stored references from another machine: other CPUs take other SIMD/FMA paths (torch, Open3D,
# BLAS) and differ in the last bits, ~1e-5 mm on a liver's surface. 1e-3 mm leaves room for that
# and still catches any real change of a pose.
CROSS_MACHINE_MM = 1e-3


def surface_shift_mm(T_a: np.ndarray, T_b: np.ndarray, points_mm: np.ndarray) -> float:
    """The largest distance (mm) between `points_mm` moved by T_a and by T_b (two 4x4 transforms in mm)."""
    T_a, T_b = np.asarray(T_a, dtype=np.float64), np.asarray(T_b, dtype=np.float64)
    moved_a = points_mm @ T_a[:3, :3].T + T_a[:3, 3]
    moved_b = points_mm @ T_b[:3, :3].T + T_b[:3, 3]
    return float(np.max(np.linalg.norm(moved_a - moved_b, axis=1)))
