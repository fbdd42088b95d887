"""The paper's preprocessing: unit-sphere normalization by the source's scale and voxelization."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .errors import InputError


@dataclass(frozen=True)
class Normalization:
    """Maps mm to normalized units: p_norm = (p_mm - centroid_mm) / scale_mm."""

    centroid_mm: np.ndarray  # (3,)
    scale_mm: float  # the source's maximum radius about its centroid

    def apply(self, points_mm: np.ndarray) -> np.ndarray:
        return (np.asarray(points_mm, dtype=np.float64) - self.centroid_mm) / self.scale_mm

    def invert(self, points_norm: np.ndarray) -> np.ndarray:
        return np.asarray(points_norm, dtype=np.float64) * self.scale_mm + self.centroid_mm


def source_normalization(source_mm: np.ndarray) -> Normalization:
    """Centre at the centroid and scale into the unit sphere by the maximum radius."""
    centroid = np.asarray(source_mm, dtype=np.float64).mean(axis=0)
    scale = float(np.max(np.linalg.norm(source_mm - centroid, axis=1)))
    if not np.isfinite(scale) or scale <= 0:
        raise InputError("source: all points coincide; cannot normalize")
    return Normalization(centroid, scale)


def target_normalization(target_mm: np.ndarray, source_norm: Normalization) -> Normalization:
    """Centre the target at its own centroid, scaled by the source's factor (paper)."""
    return Normalization(np.asarray(target_mm, dtype=np.float64).mean(axis=0), source_norm.scale_mm)


def voxel_keys(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """One int64 key per point naming its floor(p / voxel) cell; keys sort like the cells (x, y, z).

    A 1-D key makes np.unique several times faster than unique rows. When the cells span too
    much for one int64 (far outliers), the cells' rank among the unique rows is the key instead.
    """
    cells = np.floor(np.asarray(points, dtype=np.float64) / voxel_size).astype(np.int64)
    cells -= cells.min(axis=0)
    span = [int(v) + 1 for v in cells.max(axis=0)]
    if span[0] * span[1] * span[2] < 2**62:
        return (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    return np.unique(cells, axis=0, return_inverse=True)[1].reshape(-1)


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Replace the points of each occupied voxel by their mean (deterministic, sorted by voxel)."""
    if voxel_size <= 0:
        raise InputError(f"voxel size must be > 0, got {voxel_size}")
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0:
        return points.reshape(0, 3)
    _, inverse, counts = np.unique(voxel_keys(points, voxel_size), return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(inverse, weights=points[:, i], minlength=len(counts)) for i in range(3)], axis=1)
    return sums / counts[:, None]


def denormalize_transform(T_norm: np.ndarray, source: Normalization, target: Normalization) -> np.ndarray:
    """Turn a transform between normalized clouds into T_target_source in mm, original frames.

    p_t_norm = R p_s_norm + t  with p_norm = (p_mm - c) / s (same s for both) gives
    p_t_mm = R p_s_mm + (s t + c_t - R c_s).
    """
    R = np.asarray(T_norm, dtype=np.float64)[:3, :3]
    t = np.asarray(T_norm, dtype=np.float64)[:3, 3]
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = source.scale_mm * t + target.centroid_mm - R @ source.centroid_mm
    return T


def statistical_inliers(points: np.ndarray, neighbors: int, std_ratio: float) -> np.ndarray:
    """Boolean mask of points whose mean distance to their k neighbours is within
    mean + std_ratio * std over the cloud (drops depth-sensor flying pixels and specks).

    Keeps everything when the cloud is too small to judge or the rule would drop most of it.
    """
    points = np.asarray(points, dtype=np.float64)
    k = min(neighbors, len(points) - 1)
    if k < 3 or std_ratio <= 0:
        return np.ones(len(points), dtype=bool)
    dist, _ = cKDTree(points).query(points, k=k + 1, workers=-1)
    mean_dist = dist[:, 1:].mean(axis=1)
    keep = mean_dist <= mean_dist.mean() + std_ratio * mean_dist.std()
    return keep if keep.sum() >= 0.5 * len(points) else np.ones(len(points), dtype=bool)
