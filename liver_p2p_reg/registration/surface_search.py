"""A search of the whole preop surface for where a small view fits: poses anchored at surface points, scored
on a distance field of the preop surface.

Why: where the default is far off on a view below 10-15 % visibility, most often no candidate it screens is in
the true basin at all (docs/results/failure_sources.md, "search"): the matcher's wrong matches mislead every P2P
candidate alike and FPFH + RANSAC finds only some. This search uses no matches. It puts the view's centre on
each of a few hundred surface points with the view's normal along the surface's normal there (the surface's
normal taken over a neighbourhood the view's size, so a bumpy patch does not mislead it), turns it about that
normal in even steps, and scores every such pose by the view's mean distance to the preop surface (looked up in
a distance field, truncated so a few points off the surface do not dominate). The best distinct poses join the
screened candidates; the screening's short ICP and its residual decide among all, as for RANSAC's pose.

Built once per preop model (`SearchModel`, cached with the Registrar's other per-source data; the node builds it
at warm-up): the distance field and the anchors' normals at a few neighbourhood radii (0.2-0.5 s in all).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.ndimage import distance_transform_edt

from liver_p2p_reg.registration.context import remember_latest
from liver_p2p_reg.registration.nearest import NearestIndex
from liver_p2p_reg.registration.preprocess import PreprocessedPair, voxel_downsample
from liver_p2p_reg.registration.refine import rotation_about

CELL_NORM = 0.025  # the distance field's cell edge (normalized units, ~3 mm on a liver)
PAD_NORM = 0.3  # the field reaches this far beyond the source's box (a pose's points beyond it score TRUNCATE)
TRUNCATE_NORM = 0.08  # a view point's distance counts at most this much (robust to the deformation and outliers)
ANCHOR_VOXEL_NORM = 0.1  # anchors: one surface point per cell of this edge (a few hundred on a liver)
NORMAL_RADII_NORM = (0.08, 0.12, 0.18, 0.27)  # the anchors' normals over neighbourhoods of these radii
ANGLES = 24  # turns of the view about the anchor's normal (15 degrees apart)
VIEW_POINTS = 64  # the view's points a pose is scored on (an even subsample)
KEEP = 16  # the best-scoring distinct poses handed to the screening
AXIS_POINTS = 8  # the view's points nearest its normal axis give the height of its centre above the surface
DISTINCT_ROTATION = 0.5  # Frobenius distance of rotations (~20 deg) ...
DISTINCT_OFFSET_NORM = 0.1  # ... or origin distance (anchor lowered to the view's centre) beyond which two kept
# poses count as distinct
# The screening takes a searched pose only where its residual after the short ICP is below this share of every
# other candidate's (a pose no match supports must fit clearly better; 0.93 from the look in RULE_surface_search.md)
SEARCH_MARGIN = 0.93


@dataclass(frozen=True)
class SearchModel:
    """What the search needs of one preop model: its truncated distance field and its anchors with normals."""

    lower: np.ndarray  # (3,) the field's first cell centre, normalized
    shape: np.ndarray  # (3,) cells per axis
    distance: np.ndarray  # (cells,) float32, C order, each at most TRUNCATE_NORM
    anchors: np.ndarray  # (A, 3) surface points the view's centre is put on
    normals: tuple[np.ndarray, ...]  # per radius of NORMAL_RADII_NORM: (A, 3) outward unit normals


def build_search_model(source_full: np.ndarray, source: np.ndarray) -> SearchModel:
    """The distance field of the full (not voxelized) source and the anchors' normals over the voxelized one."""
    lower = source_full.min(axis=0) - PAD_NORM
    shape = np.ceil((source_full.max(axis=0) + PAD_NORM - lower) / CELL_NORM).astype(np.int64) + 1
    free = np.ones(tuple(shape), dtype=bool)
    cells = np.floor((source_full - lower) / CELL_NORM + 0.5).astype(np.int64)
    free[cells[:, 0], cells[:, 1], cells[:, 2]] = False
    field = np.minimum(distance_transform_edt(free) * CELL_NORM, TRUNCATE_NORM).astype(np.float32)
    index = NearestIndex(source)
    anchors = source[index.query(voxel_downsample(source, ANCHOR_VOXEL_NORM))[1]]
    centroid = source.mean(axis=0)
    from scipy.spatial import cKDTree  # ball queries (pykdtree has none)

    balls = cKDTree(source)
    normals = tuple(_patch_normals(source, balls, anchors, centroid, radius) for radius in NORMAL_RADII_NORM)
    return SearchModel(lower, shape, field.reshape(-1), anchors, normals)


def _patch_normals(
    source: np.ndarray, balls: Any, anchors: np.ndarray, centroid: np.ndarray, radius: float
) -> np.ndarray:
    """Each anchor's normal by PCA of the source points within `radius`, turned away from the centroid."""
    normals = np.empty_like(anchors)
    for k, near in enumerate(balls.query_ball_point(anchors, radius)):
        points = source[near] if len(near) >= 3 else source
        normal = np.linalg.eigh(np.cov(points.T))[1][:, 0]
        normals[k] = normal if normal @ (anchors[k] - centroid) >= 0 else -normal
    return normals


def search_model(prep: PreprocessedPair, cache: dict[str, Any]) -> SearchModel:
    """`build_search_model` of this pair's source, once per preop model (the Registrar's cache)."""
    return remember_latest(
        cache,
        "surface-search",
        prep.source_full,
        (prep.source.shape, CELL_NORM, PAD_NORM, TRUNCATE_NORM, ANCHOR_VOXEL_NORM, NORMAL_RADII_NORM),
        lambda: build_search_model(prep.source_full, prep.source),
    )


def aligning_rotations(vectors: np.ndarray, to: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations taking each unit row of `vectors` onto the unit vector `to` (the shortest turn)."""
    cross = np.cross(vectors, to)
    cos = vectors @ to
    skew = np.zeros((len(vectors), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -cross[:, 2], cross[:, 1], -cross[:, 0]
    skew -= skew.transpose(0, 2, 1)
    opposite = cos < -1 + 1e-9
    rotations = np.eye(3) + skew + skew @ skew / np.where(opposite, 1.0, 1.0 + cos)[:, None, None]
    if opposite.any():  # a half turn about any axis normal to `to`
        axis = np.cross(to, [1.0, 0.0, 0.0] if abs(to[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        rotations[opposite] = 2.0 * np.outer(axis, axis) - np.eye(3)
    return rotations


def search_poses(prep: PreprocessedPair, model: SearchModel) -> list[np.ndarray]:
    """Up to KEEP distinct normalized poses (source -> target), best-scoring first.

    The target is centred at its own centroid (normalization), so a pose puts the anchor (lowered by the view's
    centre height) at the origin. Both signs of the view's normal are tried: a view alone does not say which side
    the sensor was on.
    """
    view = prep.target
    points = view[:: max(1, len(view) // VIEW_POINTS)][:VIEW_POINTS]
    normal = np.linalg.eigh(np.cov(view.T))[1][:, 0]
    radius = float(np.sqrt(np.mean(np.sum(view**2, axis=1))))
    level = int(np.argmin(np.abs(np.log(np.asarray(NORMAL_RADII_NORM) / max(radius, 1e-6)))))
    anchors, normals = model.anchors, model.normals[level]
    limit = (model.shape - 1).astype(np.float32)
    angles = np.arange(ANGLES) * (2.0 * np.pi / ANGLES)
    scores, rotations, origins = [], [], []
    for side in (1.0, -1.0):
        axis = side * normal
        height = points @ axis
        off_axis = np.linalg.norm(points - np.outer(height, axis), axis=1)
        centre = float(np.mean(height[np.argsort(off_axis, kind="stable")[:AXIS_POINTS]]))
        onto = aligning_rotations(normals, axis)  # (A, 3, 3): each anchor's normal onto the view's
        turns = [rotation_about(axis, a) for a in angles]
        # a view point x goes to R^T x + o in the source frame, R = turn @ onto, o = anchor - centre * normal;
        # computed in field cells, float32 (a coarse score: ~1e-7 relative rounding is far below a cell)
        origin = anchors - centre * normals
        turned = (np.concatenate([points @ turn for turn in turns]) / CELL_NORM).astype(np.float32)
        moved = np.matmul(turned[None], onto.astype(np.float32))  # (A, ANGLES * m, 3)
        moved += ((origin - model.lower) / CELL_NORM + 0.5).astype(np.float32)[:, None, :]
        np.clip(moved, 0.0, limit, out=moved)  # beyond the padded box the field is TRUNCATE already
        cells = moved.astype(np.int32)  # floor: all >= 0 now
        flat = (cells[..., 0] * int(model.shape[1]) + cells[..., 1]) * int(model.shape[2]) + cells[..., 2]
        score = model.distance[flat].reshape(len(anchors), ANGLES, -1).mean(axis=2)
        scores.append(score.T.reshape(-1))  # turn-major, as `rotations` below
        rotations += [turn @ onto for turn in turns]
        origins += [origin] * ANGLES
    score = np.concatenate(scores)
    rotation = np.concatenate(rotations)  # (2 * ANGLES * A, 3, 3)
    origin = np.concatenate(origins)
    kept: list[int] = []
    for j in np.argsort(score, kind="stable")[: 50 * KEEP]:
        if all(
            np.linalg.norm(rotation[j] - rotation[i]) >= DISTINCT_ROTATION
            or np.linalg.norm(origin[j] - origin[i]) >= DISTINCT_OFFSET_NORM
            for i in kept
        ):
            kept.append(int(j))
            if len(kept) == KEEP:
                break
    poses = []
    for j in kept:
        T = np.eye(4)
        T[:3, :3] = rotation[j]
        T[:3, 3] = -rotation[j] @ origin[j]
        poses.append(T)
    return poses
