"""Free-space consistency: how much a pose puts the preoperative surface where the depth sensor saw none.

A depth sensor sees the first surface along each ray from its origin. So a pose of the
complete preoperative surface is implausible where the moved surface lies *in front of* the
observed points (between the sensor and what it saw: the sensor would have seen it instead),
and where surface lies inside the view's footprint at pixels with no observation at all (the
sensor looked there and saw nothing). A flipped pose that fits a smooth view from the wrong
side does both; the true pose does neither, up to deformation and noise, which the depth band
and the share-of-footprint form of the score tolerate.

Everything here works in the pipeline's normalized units (preprocess.py): the voxelized
source, the voxelized target and the sensor origin moved by the target's normalization.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

PIXEL_VOXELS = 1.5  # pixel footprint at the view's median depth, in voxels: ~every pixel of a surface holds a point
MAX_RAY_ANGLE_DEG = 75.0  # no depth sensor sees wider than this from its axis
OUTSIDE_SHARE_MAX = 0.02  # more target points than this behind / beside the origin: not the sensor's origin
SELF_OCCLUDED_MAX = 0.2  # more target points than this hidden behind other target points: not the sensor's origin
GRID_MARGIN = 2  # pixels around the observed ones in which the moved source is rendered


@dataclass(frozen=True)
class SensorView:
    """The target as its sensor saw it: a small depth image on the plane z = 1 of a camera at `origin`."""

    origin: np.ndarray  # (3,) normalized target units
    axes: np.ndarray  # (3, 3) rows x, y, z of the camera (z: the mean viewing direction)
    pixel: float  # pixel edge on the z = 1 plane (tangent units)
    corner: np.ndarray  # (2,) integer pixel index of grid cell (0, 0)
    depth: np.ndarray  # (H, W) median observed depth per pixel (normalized), inf where nothing was seen
    observed: np.ndarray  # (H, W) bool
    footprint: np.ndarray  # (H, W) bool: the observed pixels, closed and with holes filled
    band: float  # tolerance (normalized) for deformation and noise
    observed_tree: cKDTree  # the observed points in camera coordinates

    @property
    def footprint_pixels(self) -> int:
        return int(self.footprint.sum())


def _project(points: np.ndarray, origin: np.ndarray, axes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera coordinates (..., 3) -> (u, v) on the z = 1 plane and depth z."""
    cam = (points - origin) @ axes.T
    z = cam[..., 2]
    safe = np.where(z > 1e-9, z, 1.0)
    return cam[..., 0] / safe, cam[..., 1] / safe, z


def sensor_view(target: np.ndarray, origin: np.ndarray, voxel: float, band: float) -> SensorView | str:
    """The depth image of the (voxelized, normalized) target seen from `origin`, or why `origin` cannot be its sensor.

    The origin is refused when target points lie behind or far beside it, or when many target
    points hide behind other target points (a sensor sees one surface per ray): a cloud in
    another frame than its sensor's, whose origin then means nothing.
    """
    rays = target - origin
    dist = np.linalg.norm(rays, axis=1)
    if not np.all(dist > 0):
        return "the sensor origin lies on the observed surface"
    z_axis = (rays / dist[:, None]).mean(axis=0)
    norm = float(np.linalg.norm(z_axis))
    if norm < 1e-6:
        return "the observed points surround the sensor origin"
    z_axis /= norm
    helper = np.eye(3)[int(np.argmin(np.abs(z_axis)))]
    x_axis = np.cross(helper, z_axis)
    x_axis /= np.linalg.norm(x_axis)
    axes = np.stack([x_axis, np.cross(z_axis, x_axis), z_axis])
    u, v, z = _project(target, origin, axes)
    inside = z > dist * np.cos(np.radians(MAX_RAY_ANGLE_DEG))
    if np.mean(~inside) > OUTSIDE_SHARE_MAX:
        return f"{np.mean(~inside):.0%} of the observed points lie behind or beside the sensor origin"
    u, v, z = u[inside], v[inside], z[inside]
    pixel = PIXEL_VOXELS * voxel / float(np.median(z))
    iu, iv = np.floor(u / pixel).astype(np.int64), np.floor(v / pixel).astype(np.int64)
    corner = np.array([iu.min() - GRID_MARGIN, iv.min() - GRID_MARGIN])
    shape = (int(iu.max() - corner[0]) + GRID_MARGIN + 1, int(iv.max() - corner[1]) + GRID_MARGIN + 1)
    cell = (iu - corner[0]) * shape[1] + (iv - corner[1])
    order = np.lexsort((z, cell))  # by cell, then by depth
    cells, start, count = np.unique(cell[order], return_index=True, return_counts=True)
    depth = np.full(shape[0] * shape[1], np.inf)
    depth[cells] = z[order][start + count // 2]  # the median: robust to flying pixels either way
    nearest = np.full(shape[0] * shape[1], np.inf)
    nearest[cells] = z[order][start]
    hidden = float(np.mean(z > nearest[cell] + band))
    if hidden > SELF_OCCLUDED_MAX:
        return f"{hidden:.0%} of the observed points hide behind other observed points from the sensor origin"
    depth = depth.reshape(shape)
    observed = np.isfinite(depth)
    footprint = ndimage.binary_fill_holes(ndimage.binary_closing(observed, iterations=1)) | observed
    tree = cKDTree(np.stack([u * z, v * z, z], axis=1))
    return SensorView(origin, axes, pixel, corner, depth, observed, footprint, band, tree)


def violations(view: SensorView, source: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Free-space violation of each pose (R (C, 3, 3), t (C, 3)) of the voxelized source: (C,) shares of the footprint.

    A footprint pixel violates when the moved source's nearest point along its ray lies more
    than `band` in front of the observed depth, or when the pixel saw nothing and the moved
    source has surface there (the nearest surface along a ray of a closed surface faces the
    sensor) -- and in both cases that source point is more than `band` away from every observed
    point: a surface seen obliquely, shifted sideways by a few mm, moves far along the rays but
    not in 3D, and deformation or a hole's rim must not count as a contradiction.
    """
    R, t = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
    n_poses = len(R)
    h, w = view.depth.shape
    # Each pose's source moved straight into camera coordinates: cam = axes (R s + t - o).
    rot = view.axes @ R  # (C, 3, 3)
    shift = (t - view.origin) @ view.axes.T  # (C, 3)
    # One (N, C) matrix product per camera axis: contiguous arrays, ~5x faster than a (C, N, 3) batch.
    x, y, z = (source @ rot[:, i, :].T + shift[:, i] for i in range(3))
    # The grid's window on the z = 1 plane, tested without dividing (most points fall outside it).
    u_lo, v_lo = view.corner * view.pixel
    u_hi, v_hi = u_lo + h * view.pixel, v_lo + w * view.pixel
    keep = (z > 1e-9) & (x >= u_lo * z) & (x < u_hi * z) & (y >= v_lo * z) & (y < v_hi * z)
    point, pose = np.nonzero(keep)
    x, y, z = x[point, pose], y[point, pose], z[point, pose]
    iu = np.clip(np.floor(x / z / view.pixel).astype(np.int64) - view.corner[0], 0, h - 1)
    iv = np.clip(np.floor(y / z / view.pixel).astype(np.int64) - view.corner[1], 0, w - 1)
    flat = pose * (h * w) + iu * w + iv
    rendered = np.full(n_poses * h * w, np.inf)
    np.minimum.at(rendered, flat, z)  # the moved source's z-buffer, one image per pose
    front = view.observed & (rendered.reshape(n_poses, h, w) < view.depth - view.band)
    unseen = (view.footprint & ~view.observed) & np.isfinite(rendered.reshape(n_poses, h, w))
    suspect = (front | unseen).reshape(-1)
    # The point that won each suspect pixel, and whether it lies within the band of an observed point.
    winner = np.flatnonzero(suspect[flat] & (z == rendered[flat]))
    near, _ = view.observed_tree.query(
        np.stack([x[winner], y[winner], z[winner]], axis=1), distance_upper_bound=view.band
    )
    suspect[flat[winner[np.isfinite(near)]]] = False
    return suspect.reshape(n_poses, -1).sum(axis=1) / max(view.footprint_pixels, 1)


def penalized(value: float, violation: float, weight: float) -> float:
    """A residual made worse by a free-space violation: residual x (1 + weight x violation); unchanged when unknown."""
    if not np.isfinite(violation):
        return value
    return value * (1.0 + weight * violation)


class Scorer:
    """Free-space violations of the poses (normalized 4x4) of one registration; its time in `ms`.

    `status` is "on", or "off: <why>" when the origin cannot be the target's sensor (then every
    score is NaN and nothing downstream changes).
    """

    def __init__(self, source: np.ndarray, target: np.ndarray, origin: np.ndarray, voxel: float, band: float) -> None:
        start = time.perf_counter()
        self.source = source
        view = sensor_view(target, np.asarray(origin, dtype=np.float64), voxel, band)
        self.view = view if isinstance(view, SensorView) else None
        self.status = "on" if self.view is not None else f"off: {view}"
        self.ms = (time.perf_counter() - start) * 1e3

    def __call__(self, poses: Sequence[np.ndarray]) -> np.ndarray:
        if self.view is None or not len(poses):
            return np.full(len(poses), np.nan)
        start = time.perf_counter()
        T = np.asarray(poses, dtype=np.float64)
        out = violations(self.view, self.source, T[:, :3, :3], T[:, :3, 3])
        self.ms += (time.perf_counter() - start) * 1e3
        return out
