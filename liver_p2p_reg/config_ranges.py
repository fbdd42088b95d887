"""The numeric ranges and choices `Config.validate` checks: one table per kind of range."""

from __future__ import annotations

# Choices validated in `Config.validate`; kept here so the CLI can list them in --help.
SELECTION_RULES = ("closest-point", "inlier-count")
NODE_MODES = ("continuous", "once", "on_demand", "survey")
DEVICES = ("cpu", "cuda")

# Lower bounds of the numeric fields that have nothing but a lower bound.
MINIMUMS: dict[str, float] = {
    "min_points": 3,
    "max_patch_rows": 0,
    "icp_max_points": 100,
    "screen_icp_points": 100,
    "track_residual_ratio": 1,
    "track_max_frames": 1,
    "survey_max_points": 1000,
    "residual_warn_mm": 0,
    "uncertainty_warn_mm": 0,
    "structure_error_warn_mm": 0,
    "free_space_band_mm": 0,
    "free_space_weight": 0,
    "free_space_warn": 0,
    "record_max_mb": 0,
    "stale_after_s": 0.1,
    "deform_regularization": 0,
    "deform_min_points": 3,
    "deform_max_residual_mm": 0,
    "deform_max_displacement_mm": 0,
    "seed": 0,  # NumPy generators (mesh sampling, crops) refuse negative seeds
    "outlier_std_ratio": 0,  # 0 disables the outlier filter
    "max_input_points": 1000,
    "ambiguity_pose_mm": 0,
    "ambiguity_residual_ratio": 1,
    # a fused-surface voxel far below the sensors' noise fuses nothing: 1e-300 passed `> 0` and survey mode then
    # blamed tracking (each voxel a lone point); 0.1 mm is 20x finer than the default 2 mm
    "survey_voxel_mm": 0.1,
}
# Open3D's random.seed() (RANSAC, FGR) takes a C int: a larger seed would pass NumPy and fail mid-registration.
MAX_SEED = 2**31 - 1
# [low, high] of integer settings: threads per registration (torch, Open3D), P2P patches (the default 5)
CLOSED: dict[str, tuple[int, int]] = {
    "num_threads": (0, 256),
    "open3d_threads": (1, 256),
    "k": (1, 64),
    # counts of work per registration: a huge one held the node's worker for minutes (deform_target_tets 1e6:
    # 3 GB and no answer to ~/reregister) or ran out of memory (outlier_neighbors: a k-NN table of k per point)
    "outlier_neighbors": (3, 256),
    "consensus_seeds": (0, 4096),
    "refit_iterations": (0, 100),
    "refine_candidates": (1, 256),
    "screen_icp_iterations": (1, 1000),
    "icp_max_iterations": (1, 1000),
    "ransac_max_iterations": (1, 10_000_000),
    "deform_modes": (1, 256),
    "deform_target_tets": (60, 50_000),  # 60000: 43 s to build here; the target is <= 10 s at 20k vertices
    "deform_iterations": (1, 1000),
}
# (low, high] of fractions, and of lengths in normalized units (the organ fits in the unit sphere; a voxel above
# 0.5 leaves a handful of points)
HALF_OPEN: dict[str, tuple[float, float]] = {
    **dict.fromkeys(("ransac_confidence", "icp_trim_ratio", "error_coverage"), (0, 1)),
    **dict.fromkeys(("normal_radius_norm", "fpfh_radius_norm", "icp_max_corr_norm", "ransac_max_corr_norm"), (0, 2)),
    "voxel_size_norm": (0, 0.5),
}
# Numbers that must be finite: a scale, radius or weight of inf turns the arithmetic into NaN or takes every point.
# (inf stays allowed where it means "no limit": the warning thresholds, gates, rates and sizes.)
FINITE = (
    "temperature",
    "inlier_radius_norm",
    "refit_radius_start_norm",
    "consensus_sigma_norm",
    "free_space_band_mm",
    "free_space_weight",
    "deform_regularization",
    "survey_voxel_mm",
)
