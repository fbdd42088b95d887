"""The paper's preprocessing: unit-sphere normalization by the source's scale and voxelization."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.registration.context import remember_latest
from liver_p2p_reg.registration.nearest import NearestIndex

if TYPE_CHECKING:
    from liver_p2p_reg.config import Config


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
    dist, _ = NearestIndex(points).query_k(points, k + 1)
    mean_dist = dist[:, 1:].mean(axis=1)
    keep = mean_dist <= mean_dist.mean() + std_ratio * mean_dist.std()
    return keep if keep.sum() >= 0.5 * len(points) else np.ones(len(points), dtype=bool)


@dataclass
class PreprocessedPair:
    """Both clouds normalized (full and voxelized) plus the maps back to mm."""

    source_norm: Normalization
    target_norm: Normalization
    source_full: np.ndarray  # (N0, 3) normalized, not voxelized (refinement)
    target_full: np.ndarray
    source: np.ndarray  # (N, 3) voxelized
    target: np.ndarray  # (M, 3) voxelized
    source_tree: NearestIndex  # of `source`, built once per model (residuals are measured against it)
    # What this registration already looked up in the Registrar's cache (the ICP's source index):
    # its key hashes the whole source, and screening refines up to seven poses per registration.
    memo: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def visibility(self) -> float:
        return len(self.target) / len(self.source)


def preprocess_pair(
    source_mm: np.ndarray, target_mm: np.ndarray, config: Config, cache: dict[str, Any] | None = None
) -> PreprocessedPair:
    """The paper's preprocessing; refuses a target much larger than the source after voxelization
    (`max_target_ratio`: a noisy full view may voxelize a few percent larger; swapped files do not).

    With a cache, the source's share (normalization, voxelization) is computed once per model.
    """

    def source_part() -> tuple[Normalization, np.ndarray, np.ndarray, NearestIndex]:
        norm = source_normalization(source_mm)
        full = norm.apply(source_mm)
        voxels = voxel_downsample(full, config.voxel_size_norm)
        return norm, full, voxels, NearestIndex(voxels)

    if cache is None:
        ns, src_full, src, src_tree = source_part()
    else:
        ns, src_full, src, src_tree = remember_latest(
            cache, "prepared-source", source_mm, (config.voxel_size_norm,), source_part
        )
    if config.outlier_std_ratio > 0:
        target_mm = target_mm[statistical_inliers(target_mm, config.outlier_neighbors, config.outlier_std_ratio)]
    nt = target_normalization(target_mm, ns)
    tgt_full = nt.apply(target_mm)
    tgt = voxel_downsample(tgt_full, config.voxel_size_norm)
    if len(src) < 3 or len(tgt) < 3:
        raise InputError(f"too few points after voxelization (source {len(src)}, target {len(tgt)}); need >= 3 each")
    if len(tgt) > config.max_target_ratio * len(src):
        raise InputError(
            f"target ({len(tgt)} voxels) is more than {config.max_target_ratio:g}x the source ({len(src)} voxels): "
            "expected the complete preoperative surface as SOURCE and the partial view as TARGET"
        )
    return PreprocessedPair(ns, nt, src_full, tgt_full, src, tgt, src_tree)


def residual_norm(T_norm: np.ndarray, prep: PreprocessedPair) -> float:
    """Mean closest-point distance target -> transformed voxelized source (normalized units).

    Measured in the source frame (the target moved by the inverse; distances are the same), so
    the source's k-d tree is built once per model, not once per evaluated pose.
    """
    T_inv = np.linalg.inv(T_norm)
    dist, _ = prep.source_tree.query(transform_points(T_inv, prep.target))
    return float(dist.mean())


def norm_to_mm(norm: Normalization) -> np.ndarray:
    """4x4 matrix mapping normalized coordinates to mm: p_mm = s p_norm + c."""
    T = np.eye(4)
    T[:3, :3] *= norm.scale_mm
    T[:3, 3] = norm.centroid_mm
    return T
