"""FPFH features (Open3D) as a feature provider, with outward-oriented normals."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # only `describe` needs torch; the Open3D baselines use `raw`
    import torch

from liver_p2p_reg.o3d import o3d_module
from liver_p2p_reg.registration.context import remember_latest

# Clouds this large get their normals from a child process: Open3D holds the GIL while it estimates them
# (~0.5 s per 100 k points here), which would stall a node's signal handling and callbacks (prefetch.py).
OFF_PROCESS_POINTS = 100_000


def outward_normals(points: np.ndarray, radius: float, max_nn: int = 30) -> np.ndarray:
    """Unit normals by local PCA, flipped to point away from the cloud's centroid (`local_outward_normals`).

    A one-shot command may have had them computed by a child process already, and a cloud of
    OFF_PROCESS_POINTS or more is handed to one (prefetch.py): the same function on the same points,
    the same normals; if the child fails they are computed here.
    """
    from liver_p2p_reg.registration.prefetch import normals_in_child, take_prefetched

    ready = take_prefetched(points, radius, max_nn)
    if ready is None and len(points) >= OFF_PROCESS_POINTS:
        ready = normals_in_child(points, radius, max_nn)
    return ready if ready is not None else local_outward_normals(points, radius, max_nn)


def local_outward_normals(points: np.ndarray, radius: float, max_nn: int = 30) -> np.ndarray:
    """Unit normals by local PCA in this process, flipped to point away from the cloud's centroid.

    A liver surface is mostly convex, so "away from the centroid" is outward for the whole
    source and for a partial cap (its centroid lies on the concave side). This makes the
    normals — and so FPFH — independent of the cloud's pose.
    """
    o3d = o3d_module()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
    normals = np.asarray(cloud.normals)
    flip = np.einsum("ij,ij->i", normals, points - points.mean(axis=0)) < 0
    normals[flip] *= -1
    return normals


def fpfh(points: np.ndarray, normal_radius: float, feature_radius: float) -> np.ndarray:
    """(N, 33) FPFH histograms of points (normalized units)."""
    o3d = o3d_module()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.normals = o3d.utility.Vector3dVector(outward_normals(points, normal_radius))
    feature = o3d.pipelines.registration.compute_fpfh_feature(
        cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=feature_radius, max_nn=100)
    )
    return np.asarray(feature.data, dtype=np.float64).T.copy()


def hellinger_normalize(histograms: np.ndarray) -> np.ndarray:
    """sqrt of L1-normalized histograms: their dot product is the Bhattacharyya similarity."""
    h = np.sqrt(np.clip(histograms, 0, None))
    norm = np.linalg.norm(h, axis=1, keepdims=True)
    return h / np.where(norm > 0, norm, 1.0)


class FPFHProvider:
    """FPFH descriptors, Hellinger-normalized so cosine similarity compares histograms well."""

    name = "fpfh"

    def __init__(self, normal_radius_norm: float, feature_radius_norm: float) -> None:
        self.normal_radius = normal_radius_norm
        self.feature_radius = feature_radius_norm

    def raw(self, points: np.ndarray, cache: dict[str, Any] | None = None) -> np.ndarray:
        """(N, 33) FPFH, cached by content (the preoperative source is described once)."""
        if cache is None:
            return fpfh(points, self.normal_radius, self.feature_radius)
        params = (self.normal_radius, self.feature_radius)
        return remember_latest(cache, "fpfh", points, params, lambda: fpfh(points, *params))

    def describe(
        self, source_norm: torch.Tensor, target_norm: torch.Tensor, cache: dict[str, Any]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        src = self.raw(source_norm.detach().cpu().numpy().astype(np.float64), cache)
        tgt = self.raw(target_norm.detach().cpu().numpy().astype(np.float64), None)
        import torch

        to_t = lambda a: torch.as_tensor(hellinger_normalize(a), dtype=source_norm.dtype, device=source_norm.device)  # noqa: E731
        return to_t(src), to_t(tgt)
