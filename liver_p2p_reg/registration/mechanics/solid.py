"""The closed solid a preop model encloses, from its triangles or from its points alone (voxel shell + fill).

Why one path for both: a tetrahedral mesher needs only "inside or not" and the volume. Marking the voxels a
dense sample of the surface touches, closing one-voxel gaps and filling the enclosed cavity gives that for a
CT mesh (sampled on its triangles) and for a model that arrives as points (its points), with no native
reconstruction library; a surface with a hole larger than the closing cannot be filled and is refused.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.mechanics.surface import edge_face_counts

MIN_FILL_SHARE = 0.2  # the filled solid must hold at least this share of the shell's bounding box volume x 0.1


@dataclass
class VoxelSolid:
    """A solid on a voxel grid (mm) with a signed distance (< 0 inside), trilinearly interpolated."""

    vertices_mm: np.ndarray  # (V, 3) the surface points the tetrahedral mesh must embed
    triangles: np.ndarray  # (F, 3) the model's triangles (empty when it came as points)
    origin_mm: np.ndarray  # (3,) centre of voxel [0, 0, 0]
    voxel_mm: float
    sdf_mm: np.ndarray  # (nx, ny, nz) signed distance at voxel centres
    volume_mm3: float

    def implicit_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """Approximate signed distance at points (outside the grid: its border value, > 0)."""
        from scipy.ndimage import map_coordinates

        pts = np.asarray(points_mm, dtype=np.float64)
        coords = ((pts.reshape(-1, 3) - self.origin_mm) / self.voxel_mm).T
        return map_coordinates(self.sdf_mm, coords, order=1, mode="nearest").reshape(pts.shape[:-1])


MAX_SURFACE_SAMPLES = 4_000_000  # lattice points on a mesh's triangles (a CT liver mesh needs ~1M)
MAX_LATTICE_STEPS = 16  # the first pass's steps along a triangle's longest edge


def surface_samples_mm(vertices_mm: np.ndarray, triangles: np.ndarray, spacing_mm: float) -> np.ndarray:
    """The vertices plus points on every triangle no further apart than `spacing_mm` (deterministic)."""
    if len(triangles) == 0:
        return vertices_mm
    a, b, c = (vertices_mm[triangles[:, i]] for i in range(3))
    longest = np.max([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1)])
    n = int(min(max(np.ceil(longest / spacing_mm), 1), MAX_LATTICE_STEPS))
    # at most MAX_SURFACE_SAMPLES in all: one sliver set n for all of 300k triangles (46M points, 3 GB); a mesh
    # sampled coarser than the voxels leaves holes, and the solid then says it encloses no volume
    while n > 1 and len(triangles) * (n + 1) * (n + 2) // 2 > MAX_SURFACE_SAMPLES:
        n -= 1
    return np.concatenate([vertices_mm, _lattice(a, b, c, n)])


def _lattice(a: np.ndarray, b: np.ndarray, c: np.ndarray, n: int) -> np.ndarray:
    """The points of an `n`-step barycentric lattice on each triangle (a, b, c), (T * P, 3)."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = i + j <= n
    u, v = i[keep] / n, j[keep] / n
    pts = a[:, None, :] + u[None, :, None] * (b - a)[:, None, :] + v[None, :, None] * (c - a)[:, None, :]
    return pts.reshape(-1, 3)


def dense_surface_samples_mm(vertices_mm: np.ndarray, triangles: np.ndarray, spacing_mm: float) -> np.ndarray | None:
    """Like `surface_samples_mm`, but each triangle with as many steps as its own longest edge needs (no cap):
    None when that needs no more points than the first pass had (nothing to retry), or more than
    MAX_SURFACE_SAMPLES (a sliver-ridden mesh is not sampled without bound)."""
    a, b, c = (vertices_mm[triangles[:, i]] for i in range(3))
    longest = np.max([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1)], 0)
    steps = np.maximum(np.ceil(longest / spacing_mm), 1).astype(np.int64)
    if steps.max() <= MAX_LATTICE_STEPS or np.sum((steps + 1) * (steps + 2) // 2) > MAX_SURFACE_SAMPLES:
        return None
    sets = [steps == n for n in np.unique(steps)]  # one barycentric lattice per step count
    return np.concatenate([vertices_mm, *(_lattice(a[s], b[s], c[s], int(steps[s][0])) for s in sets)])


def _median_spacing(points_mm: np.ndarray) -> float:
    """The median distance from (up to 2000 evenly taken) points to their nearest other point, mm."""
    from scipy.spatial import cKDTree

    step = points_mm[:: max(len(points_mm) // 2000, 1)]
    return float(np.median(cKDTree(points_mm).query(step, k=2)[0][:, 1]))


def closed_solid(vertices_mm: np.ndarray, triangles: np.ndarray | None) -> VoxelSolid:
    """The solid of a preop model: voxels of 1/96 of its extent for a mesh; for points, the finest voxel
    (2-6x the median point spacing) whose shell encloses a volume."""

    vertices_mm = np.asarray(vertices_mm, dtype=np.float64)
    fine_mm = max(float(np.max(np.ptp(vertices_mm, axis=0))) / 96.0, 1.0)
    if triangles is not None and len(triangles):
        return solid_from_surface(vertices_mm, triangles, fine_mm)
    spacing_mm = _median_spacing(vertices_mm)
    if spacing_mm == 0.0:  # exact twins are 0 mm apart: with many the median is 0, so measure the distinct points
        _, first = np.unique(vertices_mm, axis=0, return_index=True)
        spacing_mm = _median_spacing(vertices_mm[np.sort(first)])
    error: InputError | None = None
    for factor in (2.0, 3.0, 4.0, 6.0):
        try:
            return solid_from_surface(vertices_mm, None, max(factor * spacing_mm, fine_mm))
        except InputError as exc:
            error = exc
    assert error is not None
    raise error


def solid_from_surface(vertices_mm: np.ndarray, triangles: np.ndarray | None, voxel_mm: float) -> VoxelSolid:
    """Voxelize a closed surface (triangles, or points dense enough for `voxel_mm`) into a filled solid."""
    from scipy.ndimage import distance_transform_edt

    vertices_mm = np.asarray(vertices_mm, dtype=np.float64)
    tris = np.zeros((0, 3), dtype=np.int64) if triangles is None else np.asarray(triangles, dtype=np.int64)
    if len(tris) and (tris.min() < 0 or tris.max() >= len(vertices_mm)):
        raise InputError("the preop mesh's triangles index vertices it does not have")
    filled = _filled(surface_samples_mm(vertices_mm, tris, 0.5 * voxel_mm), voxel_mm)
    dense = None
    if filled is None and len(tris):
        # The first pass caps each triangle's lattice (MAX_LATTICE_STEPS), so the long triangles of a coarse closed
        # mesh (decimated, a convex hull, a box) leave gaps in the shell. Retried only when the first pass found no
        # volume: every mesh it closes keeps its solid, and the deformation, bit for bit.
        dense = dense_surface_samples_mm(vertices_mm, tris, 0.5 * voxel_mm)
        if dense is not None:
            filled = _filled(dense, voxel_mm)
    if filled is None:
        raise InputError(_no_volume_reason(vertices_mm, tris, voxel_mm))
    solid, origin = filled
    inside = distance_transform_edt(solid) * voxel_mm
    outside = distance_transform_edt(~solid) * voxel_mm
    sdf = np.where(solid, -inside + 0.5 * voxel_mm, outside - 0.5 * voxel_mm)
    return VoxelSolid(
        vertices_mm=vertices_mm,
        triangles=tris,
        origin_mm=origin,
        voxel_mm=float(voxel_mm),
        sdf_mm=sdf,
        volume_mm3=float(solid.sum() * voxel_mm**3),
    )


def _filled(samples: np.ndarray, voxel_mm: float) -> tuple[np.ndarray, np.ndarray] | None:
    """(the filled voxel solid, the grid's origin) of surface samples; None when their shell encloses no volume."""
    from scipy.ndimage import binary_closing, binary_fill_holes, generate_binary_structure

    pad = 3
    origin = samples.min(axis=0) - pad * voxel_mm
    shape = np.ceil((samples.max(axis=0) + pad * voxel_mm - origin) / voxel_mm).astype(np.int64) + 1
    if np.prod(shape) > 8_000_000:
        raise InputError(f"the preop model is too large for a {voxel_mm:.1f} mm voxel grid ({shape.tolist()} voxels)")
    idx = np.clip(np.rint((samples - origin) / voxel_mm).astype(np.int64), 0, shape - 1)
    shell = np.zeros(tuple(shape), dtype=bool)
    shell[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    # Points-only models leave gaps between samples: one closing step bridges them.
    shell = binary_closing(shell, structure=generate_binary_structure(3, 3), iterations=1) | shell
    solid = binary_fill_holes(shell)
    cavity = solid & ~shell
    if cavity.sum() < MIN_FILL_SHARE * 0.1 * np.prod(shape - 2 * pad):
        return None
    return solid, origin


def _no_volume_reason(vertices_mm: np.ndarray, tris: np.ndarray, voxel_mm: float) -> str:
    """Why a surface gave no solid, as far as it can be told: points may be open or too sparse; a mesh is open
    (edges with one triangle, vertices welded by position) or closed around too little volume for the voxels."""
    if not len(tris):
        return "the preop points do not enclose a volume (an open or too sparse surface): no solid to deform"
    _, welded = np.unique(vertices_mm, axis=0, return_inverse=True)
    open_edges = int(np.sum(edge_face_counts(welded.reshape(-1)[tris]) == 1))
    if open_edges:
        return (
            f"the preop mesh does not enclose a volume: it is open ({open_edges} edges border only one triangle), "
            "no solid to deform"
        )
    return (
        f"the preop mesh is closed but encloses no volume its {voxel_mm:.1f} mm voxels resolve (flat, degenerate or "
        "sliver triangles): no solid to deform"
    )
