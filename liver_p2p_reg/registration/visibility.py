"""Visibility (M/N): a target's voxel count over its source's, with the pipeline's normalization; one
implementation for the survey's fused surface and the generator's crops."""

from __future__ import annotations

import numpy as np

from liver_p2p_reg.registration.preprocess import (
    source_normalization,
    target_normalization,
    voxel_downsample,
    voxel_keys,
)

VOXEL_SIZE_NORM = 0.04  # the paper's voxel (normalized units), Config.voxel_size_norm's default


def count_voxels(points: np.ndarray, voxel_size: float) -> int:
    """Number of occupied voxels = len(preprocess.voxel_downsample(points, voxel_size)), without
    the per-voxel means: the crop bisection calls it often."""
    if len(points) == 0:
        return 0
    return int(np.unique(voxel_keys(points, voxel_size)).size)


class VisibilityMeter:
    """M/N of target clouds against one fixed source, with the pipeline's normalization."""

    def __init__(self, source_mm: np.ndarray, voxel_size_norm: float = VOXEL_SIZE_NORM) -> None:
        self.norm = source_normalization(source_mm)
        self.voxel = voxel_size_norm
        self.n_source = len(voxel_downsample(self.norm.apply(source_mm), voxel_size_norm))

    def __call__(self, target_mm: np.ndarray) -> float:
        if len(target_mm) == 0:
            return 0.0
        tnorm = target_normalization(target_mm, self.norm)
        return count_voxels(tnorm.apply(target_mm), self.voxel) / self.n_source
