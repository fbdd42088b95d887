"""Partial target clouds: independent resampling, visibility-controlled crops, random pose and noise.

Visibility is measured exactly as the registration pipeline sees it (preprocess.py): the source
is normalized into the unit sphere, the target is centred at its own centroid and scaled by the
source's factor, both are voxelized at 0.04, and visibility = M / N (target over source voxels),
computed on the final target (after rotation, translation and noise).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import minimum_filter
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.phantom.artifacts import (
    DENSITY_MODES,
    Artifacts,
    background_patch,
    clustered_vertices,
    depth_falloff,
    flying_pixels,
    instrument_holes,
    mesh_vertex_view,
    virtual_eye,
)
from liver_p2p_reg.registration.visibility import VisibilityMeter

CROP_MODES = ("random", "camera")
VISIBILITY_TOLERANCE = 0.03
MIN_VISIBILITY = 0.05
TRANSLATION_RANGE_MM = 100.0


def sample_surface(vertices: np.ndarray, triangles: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """`n` area-uniform random points on a triangle mesh (independent of its vertices)."""
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    face = rng.choice(len(triangles), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w0, w1, w2 = 1 - s, s * (1 - r2), s * r2
    return w0[:, None] * a[face] + w1[:, None] * b[face] + w2[:, None] * c[face]


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted outward vertex normals."""
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    fn = np.cross(b - a, c - a)
    vn = np.zeros_like(vertices)
    for i in range(3):
        np.add.at(vn, triangles[:, i], fn)
    return vn / (np.linalg.norm(vn, axis=1, keepdims=True) + 1e-12)


def geodesic_order(points: np.ndarray, rng: np.random.Generator, k: int = 8) -> np.ndarray:
    """Point indices sorted by graph-geodesic distance (kNN graph) from a random seed point."""
    tree = cKDTree(points)
    dist, nbr = tree.query(points, k=k + 1)
    rows = np.repeat(np.arange(len(points)), k)
    graph = coo_matrix((dist[:, 1:].ravel() + 1e-9, (rows, nbr[:, 1:].ravel())), shape=(len(points),) * 2)
    seed_point = int(rng.integers(len(points)))
    geo = dijkstra(graph.tocsr(), directed=False, indices=seed_point)
    # Points the graph cannot reach (rare: disconnected sampling) go last, by Euclidean distance.
    eucl = np.linalg.norm(points - points[seed_point], axis=1)
    geo = np.where(np.isfinite(geo), geo, 1e6 + eucl)
    return np.argsort(geo, kind="stable")


def camera_order(
    points: np.ndarray, normals: np.ndarray, rng: np.random.Generator, pixel_rad: float = 0.02
) -> tuple[np.ndarray, dict]:
    """Indices of the points a laparoscope on the anterior side sees, nearest the optical axis first.

    The camera looks at a random anterior-facing surface point from 80-150 mm, its axis
    tilted up to ~25 degrees from the anterior direction (ports sit in the abdominal wall), a
    70-degree field of view (`visible_from`).
    """
    anterior = np.flatnonzero(normals[:, 1] > 0.5)
    if len(anterior) == 0:
        anterior = np.arange(len(points))
    look_at = points[rng.choice(anterior)]
    view = np.array([rng.uniform(-0.45, 0.45), 1.0, rng.uniform(-0.45, 0.2)])
    view /= np.linalg.norm(view)
    distance = rng.uniform(80.0, 150.0)
    eye = look_at + distance * view
    info = {"eye_mm": eye, "look_at_mm": look_at, "distance_mm": distance}
    return visible_from(points, eye, -view, pixel_rad=pixel_rad), info


def camera_axes(z_axis: np.ndarray) -> np.ndarray:
    """(3, 3) columns x, y, z of a camera looking along `z_axis` (unit), x level with the world's xy plane."""
    x_axis = np.cross([0.0, 0.0, 1.0], z_axis)
    x_axis /= np.linalg.norm(x_axis)
    return np.stack([x_axis, np.cross(z_axis, x_axis), z_axis], axis=1)


def visible_from(
    points: np.ndarray, eye: np.ndarray, z_axis: np.ndarray, half_fov_deg: float = 35.0, pixel_rad: float = 0.02
) -> np.ndarray:
    """Indices of the points a camera at `eye` looking along `z_axis` (unit) sees, nearest its axis first.

    A square field of view of 2 x `half_fov_deg`; hidden points are removed with a z-buffer
    (splatted by a 3x3 minimum filter so the far side cannot shine through gaps between samples).
    """
    cam = (points - eye) @ camera_axes(z_axis)
    depth = cam[:, 2]
    half_fov = np.radians(half_fov_deg)
    in_front = depth > 1.0
    u = np.where(in_front, cam[:, 0] / np.maximum(depth, 1e-6), np.inf)
    v = np.where(in_front, cam[:, 1] / np.maximum(depth, 1e-6), np.inf)
    in_fov = in_front & (np.abs(u) <= np.tan(half_fov)) & (np.abs(v) <= np.tan(half_fov))
    idx = np.flatnonzero(in_fov)
    if len(idx) == 0:
        return idx
    n_pix = int(np.ceil(2 * np.tan(half_fov) / pixel_rad)) + 1
    pu = np.clip(((u[idx] + np.tan(half_fov)) / pixel_rad).astype(np.int64), 0, n_pix - 1)
    pv = np.clip(((v[idx] + np.tan(half_fov)) / pixel_rad).astype(np.int64), 0, n_pix - 1)
    zbuf = np.full((n_pix, n_pix), np.inf)
    np.minimum.at(zbuf, (pu, pv), depth[idx])
    zbuf = minimum_filter(zbuf, size=3, mode="nearest")
    tolerance_mm = 4.0 + 0.03 * depth[idx]  # a pixel's footprint grows with depth
    visible = idx[depth[idx] <= zbuf[pu, pv] + tolerance_mm]
    radius = np.hypot(u[visible], v[visible])
    return visible[np.argsort(radius, kind="stable")]


def _prefix_for_visibility(ordered_final: np.ndarray, meter: VisibilityMeter, visibility: float) -> tuple[int, float]:
    """Shortest prefix of the ordered points whose visibility reaches the request (bisection)."""
    lo, hi = 1, len(ordered_final)
    if meter(ordered_final) < visibility:
        return hi, meter(ordered_final)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if meter(ordered_final[:mid]) >= visibility:
            hi = mid
        else:
            lo = mid
    # Take whichever side of the threshold is closer to the request.
    v_hi, v_lo = meter(ordered_final[:hi]), meter(ordered_final[:lo])
    return (hi, v_hi) if abs(v_hi - visibility) <= abs(v_lo - visibility) else (lo, v_lo)


def random_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Uniform rotation in SO(3) and a translation uniform in [-100, 100] mm per axis."""
    R = Rotation.random(random_state=rng).as_matrix()
    t = rng.uniform(-TRANSLATION_RANGE_MM, TRANSLATION_RANGE_MM, size=3)
    return R, t


def make_target(
    source_mm: np.ndarray,
    deformed_vertices_mm: np.ndarray,
    triangles: np.ndarray,
    visibility: float,
    crop_mode: str,
    noise_mm: float,
    rng: np.random.Generator,
    n_samples: int | None = None,
    meter: VisibilityMeter | None = None,
    camera_attempts: int = 24,
    density: str = "uniform",
    coarse_mm: np.ndarray | None = None,
    artifacts: Artifacts | None = None,
) -> dict:
    """Resample, crop, move and perturb a deformed surface into a partial target cloud.

    Returns tgt_pcd (M, 3), R_gt, t_gt (tgt = R_gt @ deformed + t_gt, before noise), the achieved
    visibility and crop details. Raises LiverP2PError when the request cannot be met within
    +-0.03 (camera views cannot see much more than the anterior half).

    `density` other than uniform, or `artifacts`, then turn the crop into a realistic view
    (artifacts.py): `coarse_mm` are the deformed vertices of the coarser mesh whose vertices
    make a `mesh-vertices` view (default: a vertex clustering of `deformed_vertices_mm`). The
    crop's own visibility is then returned as `visibility_uniform`, and `visibility` is measured
    on the final view. The uniform, artifact-free path draws exactly what it always drew.
    """
    if crop_mode not in CROP_MODES:
        raise InputError(f"crop mode must be one of {CROP_MODES}, got {crop_mode!r}")
    if density not in DENSITY_MODES:
        raise InputError(f"density must be one of {DENSITY_MODES}, got {density!r}")
    if not MIN_VISIBILITY <= visibility <= 1.0:
        raise InputError(f"visibility must be in [{MIN_VISIBILITY}, 1.0], got {visibility}")
    if not 0.0 <= noise_mm <= 50.0:
        raise InputError(f"noise level must be in [0, 50] mm, got {noise_mm}")
    meter = meter if meter is not None else VisibilityMeter(source_mm)
    n = int(n_samples if n_samples is not None else len(source_mm))
    points = sample_surface(deformed_vertices_mm, triangles, n, rng)
    R, t = random_pose(rng)
    noise = rng.uniform(-0.5, 0.5, size=points.shape) * noise_mm
    final = np.asarray(points @ R.T + t + noise, dtype=np.float32).astype(np.float64)  # = stored values
    info: dict = {}
    if crop_mode == "random":
        order = geodesic_order(points, rng)
        k, achieved = _prefix_for_visibility(final[order], meter, visibility)
    else:
        # Normals of the sampled points from the nearest deformed vertex.
        vn = vertex_normals(deformed_vertices_mm, triangles)
        normals = vn[cKDTree(deformed_vertices_mm).query(points)[1]]
        best = None
        for _ in range(camera_attempts):
            cand, cinfo = camera_order(points, normals, rng)
            if len(cand) == 0:
                continue
            ck, cv = _prefix_for_visibility(final[cand], meter, visibility)
            if best is None or abs(cv - visibility) < abs(best[2] - visibility):
                best = (cand, ck, cv, cinfo)
            if abs(cv - visibility) <= 0.004:  # as close as the random crops get; then stop
                break
        if best is None:
            raise LiverP2PError("camera crop: the camera saw no surface")
        order, k, achieved, info = best
    if abs(achieved - visibility) > VISIBILITY_TOLERANCE:
        raise LiverP2PError(f"{crop_mode} crop cannot reach visibility {visibility:.2f} (got {achieved:.2f})")
    keep = order[:k]
    if density != "uniform" or (artifacts is not None and artifacts.any):
        view = realistic_view(points, keep, deformed_vertices_mm, triangles, info, density, coarse_mm, artifacts, rng)
        view_final = np.asarray(
            view @ R.T + t + rng.uniform(-0.5, 0.5, size=view.shape) * noise_mm, dtype=np.float32
        ).astype(np.float64)
        return {
            "tgt_pcd": view_final[rng.permutation(len(view_final))],
            "R_gt": R,
            "t_gt": t,
            "visibility": float(meter(view_final)),
            "visibility_uniform": float(achieved),
            "visibility_requested": float(visibility),
            "crop_info": info,
        }
    keep = keep[rng.permutation(len(keep))]  # no ordering cue for learned matchers
    return {
        "tgt_pcd": final[keep],
        "R_gt": R,
        "t_gt": t,
        "visibility": float(achieved),
        "visibility_requested": float(visibility),
        "crop_info": info,
    }


MIN_VIEW_POINTS = 30


def realistic_view(
    points: np.ndarray,
    keep: np.ndarray,
    deformed_vertices_mm: np.ndarray,
    triangles: np.ndarray,
    info: dict,
    density: str,
    coarse_mm: np.ndarray | None,
    artifacts: Artifacts | None,
    rng: np.random.Generator,
) -> np.ndarray:
    """The cropped region as a real view would sample it (deformed liver frame, before pose and noise)."""
    vn = vertex_normals(deformed_vertices_mm, triangles)
    vertex_tree = cKDTree(deformed_vertices_mm)
    view = points[keep]
    normals = vn[vertex_tree.query(view)[1]]
    eye = info.get("eye_mm")
    if eye is None:
        eye = virtual_eye(view, normals, rng)
    if density == "mesh-vertices":
        if coarse_mm is None:
            coarse_mm = deformed_vertices_mm[clustered_vertices(deformed_vertices_mm, rng)]
        view = mesh_vertex_view(points, keep, np.asarray(coarse_mm, dtype=np.float64))
        normals = vn[vertex_tree.query(view)[1]]
    elif density == "depth-falloff":
        sel = depth_falloff(view, normals, eye, rng)
        view, normals = view[sel], normals[sel]
    if artifacts is not None and len(view) >= MIN_VIEW_POINTS:
        if rng.random() < artifacts.hole_probability:
            sel = instrument_holes(view, rng)
            if len(sel) >= MIN_VIEW_POINTS:
                view, normals = view[sel], normals[sel]
        extra = [
            flying_pixels(view, eye, rng.uniform(0, artifacts.outlier_fraction), rng),
            background_patch(view, normals, rng.uniform(0, artifacts.background_fraction), rng),
        ]
        view = np.concatenate([view, *extra])
    if len(view) < MIN_VIEW_POINTS:
        raise LiverP2PError(f"{density} view kept only {len(view)} points")
    return view
