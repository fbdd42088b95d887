"""Classical baselines: Procrustes oracle, ICP from identity, FPFH + RANSAC, Fast Global Registration."""

from __future__ import annotations

import numpy as np

from .config import Config
from .errors import RegistrationError
from .features.fpfh import FPFHProvider, outward_normals
from .o3d import o3d_module
from .procrustes import rigid_fit_np


def kabsch_np(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Least-squares rigid 4x4 transform source -> target from paired points (float64)."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rigid_fit_np(source, target)
    return T


def _checked(result, name: str) -> np.ndarray:
    """The transform of an Open3D registration result; no inlier at all means it failed.

    Open3D then hands back its initial guess (identity), which must not pass as an answer.
    """
    if result.fitness <= 0:
        raise RegistrationError(f"{name}: no correspondence within the distance threshold (no estimate)")
    return np.asarray(result.transformation)


def _cloud(points: np.ndarray, normal_radius: float | None = None):
    o3d = o3d_module()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if normal_radius is not None:
        cloud.normals = o3d.utility.Vector3dVector(outward_normals(points, normal_radius))
    return cloud


def icp_point_to_plane(source: np.ndarray, target: np.ndarray, T_init: np.ndarray, config: Config) -> np.ndarray:
    """Open3D point-to-plane ICP (target normals), normalized units."""
    o3d = o3d_module()
    reg = o3d.pipelines.registration
    result = reg.registration_icp(
        _cloud(source),
        _cloud(target, config.normal_radius_norm),
        config.icp_max_corr_norm,
        T_init,
        reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(max_iteration=config.icp_max_iterations),
    )
    return _checked(result, "ICP")


def _fpfh_features(source: np.ndarray, target: np.ndarray, config: Config, cache: dict):
    o3d = o3d_module()
    provider = FPFHProvider(config.normal_radius_norm, config.fpfh_radius_norm)
    feats = []
    for points, c in ((source, cache), (target, None)):
        f = o3d.pipelines.registration.Feature()
        f.data = provider.raw(points, c).T.copy()
        feats.append(f)
    return feats


def fpfh_ransac(source: np.ndarray, target: np.ndarray, config: Config, cache: dict) -> np.ndarray:
    """FPFH + RANSAC (Open3D), max correspondence distance 0.05 normalized as in the paper."""
    o3d = o3d_module()
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(config.seed)  # Open3D's RANSAC draws from its own generator
    f_src, f_tgt = _fpfh_features(source, target, config, cache)
    dist = config.ransac_max_corr_norm
    result = reg.registration_ransac_based_on_feature_matching(
        _cloud(source),
        _cloud(target),
        f_src,
        f_tgt,
        True,  # mutual filter
        dist,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
        reg.RANSACConvergenceCriteria(config.ransac_max_iterations, config.ransac_confidence),
    )
    return _checked(result, "FPFH + RANSAC")


def fast_global_registration(source: np.ndarray, target: np.ndarray, config: Config, cache: dict) -> np.ndarray:
    """Fast Global Registration (Zhou et al. 2016) on FPFH matches (Open3D)."""
    o3d = o3d_module()
    reg = o3d.pipelines.registration
    f_src, f_tgt = _fpfh_features(source, target, config, cache)
    option = reg.FastGlobalRegistrationOption(maximum_correspondence_distance=config.ransac_max_corr_norm)
    result = reg.registration_fgr_based_on_feature_matching(_cloud(source), _cloud(target), f_src, f_tgt, option)
    # FGR reports no fitness of its own: measure it at the same distance threshold.
    evaluation = reg.evaluate_registration(
        _cloud(source), _cloud(target), config.ransac_max_corr_norm, result.transformation
    )
    return _checked(evaluation, "FGR")
