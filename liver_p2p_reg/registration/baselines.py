"""Classical baselines: Procrustes oracle, ICP from identity, FPFH + RANSAC, Fast Global Registration."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import RegistrationError
from liver_p2p_reg.o3d import o3d_module
from liver_p2p_reg.registration.features.fpfh import FPFHProvider, outward_normals
from liver_p2p_reg.registration.procrustes import rigid_fit_np


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
    with on_open3d_threads(config):
        result = reg.registration_icp(
            _cloud(source),
            _cloud(target, config.normal_radius_norm),
            config.icp_max_corr_norm,
            T_init,
            reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(max_iteration=config.icp_max_iterations),
        )
    return _checked(result, "ICP")


def icp_from_identity(source: np.ndarray, target: np.ndarray, config: Config, cache: dict) -> np.ndarray:
    """Point-to-plane ICP from identity (the preprocessing has aligned the centroids): method `icp`."""
    return icp_point_to_plane(source, target, np.eye(4), config)


def _fpfh_features(source: np.ndarray, target: np.ndarray, config: Config, cache: dict):
    o3d = o3d_module()
    feats = []
    for raw in _fpfh_raw(source, target, config, cache):
        f = o3d.pipelines.registration.Feature()
        f.data = raw.T.copy()
        feats.append(f)
    return feats


def _fpfh_raw(source: np.ndarray, target: np.ndarray, config: Config, cache: dict) -> tuple[np.ndarray, np.ndarray]:
    provider = FPFHProvider(config.normal_radius_norm, config.fpfh_radius_norm)
    return provider.raw(source, cache), provider.raw(target, None)


# Fewer mutual feature matches than this: RANSAC draws from every target point's nearest match.
MIN_MUTUAL_MATCHES = 30


def feature_correspondences(f_source: np.ndarray, f_target: np.ndarray) -> np.ndarray:
    """(C, 2) [source, target] index pairs: mutual nearest neighbours in feature space.

    Falls back to each target point's nearest source feature when fewer than
    MIN_MUTUAL_MATCHES pairs are mutual (as Open3D's own mutual filter does).
    """
    _, src_of_tgt = cKDTree(f_source).query(f_target, k=1)
    _, tgt_of_src = cKDTree(f_target).query(f_source, k=1)
    tgt_idx = np.arange(len(f_target))
    mutual = tgt_of_src[src_of_tgt] == tgt_idx
    if mutual.sum() < MIN_MUTUAL_MATCHES:
        mutual[:] = True
    return np.stack([src_of_tgt[mutual], tgt_idx[mutual]], axis=1).astype(np.int32)


_OPENMP = None  # the process's OpenMP runtimes (a threadpoolctl controller), found at the first Open3D call


def on_open3d_threads(config: Config):
    """Run an Open3D registration call on `config.open3d_threads` OpenMP threads, then restore the count.

    Why: Open3D's RANSAC threads draw their samples from one mutex-guarded generator, so on two
    threads the interleaving (the scheduler's, not the seed's) decides which thread gets which
    sample, and a hard case can end on another pose run to run; its ICP sums per-thread partial
    results in whichever order the threads finish. torch's count is set per registration and
    Open3D shares its OpenMP runtime, so without this the count would be torch's.
    """
    global _OPENMP
    if _OPENMP is None:  # found once, after Open3D is loaded: a fresh search costs ~4 ms a call
        from threadpoolctl import ThreadpoolController  # ~30 ms to import: only where Open3D runs

        _OPENMP = ThreadpoolController().select(user_api="openmp")  # BLAS pools are process-wide: left alone
    return _OPENMP.limit(limits=config.open3d_threads)


def fpfh_ransac(source: np.ndarray, target: np.ndarray, config: Config, cache: dict) -> np.ndarray:
    """FPFH + RANSAC (Open3D) on mutual feature matches, max correspondence distance 0.05 normalized (paper).

    The matches are computed here (k-d trees over the 33-D histograms) and handed to Open3D's
    correspondence RANSAC: the same hypotheses as its feature-matching variant, several
    times faster on these cloud sizes. A one-shot command's child process may have computed it already
    (prefetch.py): the same function on the same bits, taken instead.
    """
    from liver_p2p_reg.registration.prefetch import take_prefetched_ransac

    ready = take_prefetched_ransac(source, target, config)
    if isinstance(ready, str):
        raise RegistrationError(ready)
    if ready is not None:
        return ready
    o3d = o3d_module()
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(config.seed)  # Open3D's RANSAC draws from its own generator
    corres = feature_correspondences(*_fpfh_raw(source, target, config, cache))
    dist = config.ransac_max_corr_norm
    with on_open3d_threads(config):
        result = reg.registration_ransac_based_on_correspondence(
            _cloud(source),
            _cloud(target),
            o3d.utility.Vector2iVector(corres),
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
    o3d.utility.random.seed(config.seed)  # FGR's tuple test samples from Open3D's generator too
    f_src, f_tgt = _fpfh_features(source, target, config, cache)
    option = reg.FastGlobalRegistrationOption(maximum_correspondence_distance=config.ransac_max_corr_norm)
    with on_open3d_threads(config):
        result = reg.registration_fgr_based_on_feature_matching(_cloud(source), _cloud(target), f_src, f_tgt, option)
        # FGR reports no fitness of its own: measure it at the same distance threshold.
        evaluation = reg.evaluate_registration(
            _cloud(source), _cloud(target), config.ransac_max_corr_norm, result.transformation
        )
    return _checked(evaluation, "FGR")
