"""Procedural liver surfaces: an implicit anatomical shape, marching cubes, Taubin smoothing.

Frame of every liver (mm, centred at the vertex centroid, RAS like CT viewers): +x points to
the patient's right (the large right lobe), +y is anterior, +z is superior (the diaphragmatic
dome); the left lobe tapers towards -x. The shape is the smooth union of a right-lobe
ellipsoid and a tapering, flattened left-lobe ellipsoid, cut from below by a tilted visceral
plane that rises towards the anterior side; where that plane meets the dome the
anterior-inferior edge is sharp. Broad shallow dents on the visceral side (gallbladder fossa,
renal and colic impressions), a posterior groove (vena cava) and a few random low-frequency
waves make every seed distinct.
After meshing, the liver is scaled anisotropically to random extents inside the anatomical
ranges (the paper's random scaling).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from skimage.measure import marching_cubes

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.mechanics.surface import mesh_volume_mm3

# Final extents are drawn inside these ranges (mm): width x, depth y, height z. They sit a
# little inside the 140-220 / 80-130 / 100-170 mm so smoothing never pushes them out.
WIDTH_RANGE_MM = (145.0, 215.0)
DEPTH_RANGE_MM = (85.0, 125.0)
HEIGHT_RANGE_MM = (105.0, 165.0)
MESH_SPACING_MM = 2.2  # marching-cubes grid; after smoothing the mean edge is about 2 mm


@dataclass
class LiverShape:
    """Random parameters of one liver's implicit function (raw frame, before scaling)."""

    right_center: np.ndarray
    right_radii: np.ndarray
    left_center: np.ndarray
    left_radii: np.ndarray
    left_taper: float
    cut_z0: float
    cut_slope_y: float
    cut_slope_x: float
    dents: list[tuple[np.ndarray, np.ndarray]]  # (centre, radii) of carved ellipsoids
    waves: list[tuple[np.ndarray, float, float]]  # (wave vector rad/mm, phase, amplitude mm)


@dataclass
class GridSDF:
    """A signed distance sampled on a regular grid (mm, < 0 inside), trilinearly interpolated."""

    origin_mm: np.ndarray  # (3,) position of values[0, 0, 0]
    spacing_mm: float
    values: np.ndarray  # (nx, ny, nz)

    def __call__(self, points_mm: np.ndarray) -> np.ndarray:
        from scipy.ndimage import map_coordinates

        pts = np.asarray(points_mm, dtype=np.float64)
        coords = ((pts.reshape(-1, 3) - self.origin_mm) / self.spacing_mm).T
        # Outside the grid the value of its outside border (> 0) holds: far points stay outside.
        out = map_coordinates(self.values, coords, order=1, mode="nearest")
        return out.reshape(pts.shape[:-1])


@dataclass
class LiverMesh:
    """A closed, watertight liver surface in mm plus what is needed to rebuild its interior."""

    vertices_mm: np.ndarray  # (V, 3) float64
    triangles: np.ndarray  # (F, 3) int64, outward-facing
    seed: int = 0
    shape: LiverShape | None = field(default=None, repr=False)
    raw_center: np.ndarray = field(default_factory=lambda: np.zeros(3), repr=False)
    scale_xyz: np.ndarray = field(default_factory=lambda: np.ones(3), repr=False)
    # Surfaces read from a file (real livers, a patient's model) carry a sampled SDF instead of `shape`.
    sdf: GridSDF | None = field(default=None, repr=False)

    def implicit_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """Approximate signed distance (mm, < 0 inside) at points given in this mesh's frame."""
        if self.sdf is not None:
            return self.sdf(points_mm)
        if self.shape is None:
            raise InputError("this LiverMesh carries no implicit shape")
        raw = np.asarray(points_mm, dtype=np.float64) / self.scale_xyz + self.raw_center
        return shape_sdf(self.shape, raw) * float(np.mean(self.scale_xyz))

    @property
    def extents_mm(self) -> np.ndarray:
        return self.vertices_mm.max(axis=0) - self.vertices_mm.min(axis=0)


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Smooth minimum (union) with blend radius k; polynomial form keeps it exact far away."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def _smax(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    return -_smin(-a, -b, k)


def _ellipsoid(p: np.ndarray, center: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """First-order ellipsoid distance: (|q/r| - 1) * |q/r| / |q/r^2| (good near the surface)."""
    q = p - center
    k0 = np.linalg.norm(q / radii, axis=-1)
    k1 = np.linalg.norm(q / radii**2, axis=-1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)


def random_shape(seed: int) -> LiverShape:
    """Draw the anatomical parameters of liver `seed` (raw frame, roughly 190 x 110 x 140 mm)."""
    rng = np.random.default_rng([int(seed), 0])
    u = rng.uniform
    right_radii = np.array([u(62, 78), u(52, 62), u(62, 76)])
    right_center = np.array([-35.0, -6.0, 4.0])  # bulk sits posterior-superior: a wedge in profile
    left_radii = np.array([u(60, 80), u(38, 48), u(30, 42)])
    left_center = np.array([u(30, 45), u(8, 18), u(12, 28)])
    dents: list[tuple[np.ndarray, np.ndarray]] = []
    cut_z0 = u(-34, -22)
    cut_slope_y = u(0.8, 1.15)
    cut_slope_x = u(-0.1, 0.15)
    # Visceral impressions: broad ellipsoids centred below the visceral plane, biting 2-5 mm in.
    for cx, cy in ((u(-25, -5), u(-12, 6)), (u(-75, -50), u(-35, -15)), (u(-60, -35), u(-5, 10))):
        plane_z = cut_z0 + cut_slope_y * cy + cut_slope_x * cx
        r = np.array([u(22, 34), u(18, 28), u(12, 18)])
        dents.append((np.array([cx, cy, plane_z - r[2] + u(2, 5)]), r))
    # Vena-cava groove on the posterior side of the right lobe: a vertical elongated dent.
    r = np.array([u(10, 14), u(10, 14), 90.0])
    dents.append((np.array([u(-15, 0), -right_radii[1] - r[1] + u(4, 7), 0.0]), r))
    waves = []
    for _ in range(4):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        wavelength = u(90, 220)
        waves.append((direction * 2 * np.pi / wavelength, u(0, 2 * np.pi), u(1.0, 3.0)))
    return LiverShape(
        right_center=right_center,
        right_radii=right_radii,
        left_center=left_center,
        left_radii=left_radii,
        left_taper=u(0.35, 0.6),
        cut_z0=cut_z0,
        cut_slope_y=cut_slope_y,
        cut_slope_x=cut_slope_x,
        dents=dents,
        waves=waves,
    )


def shape_sdf(shape: LiverShape, p: np.ndarray) -> np.ndarray:
    """Approximate signed distance (mm, < 0 inside) of the raw-frame shape at points (..., 3)."""
    # Parameters are written with the right lobe at -x; mirroring puts it at the patient's right (+x).
    p = np.asarray(p, dtype=np.float64) * np.array([-1.0, 1.0, 1.0])
    right = _ellipsoid(p, shape.right_center, shape.right_radii)
    # Left lobe: its y/z radii shrink linearly towards its tip so it tapers to a thin wedge.
    rel = np.clip((p[..., 0] - shape.left_center[0]) / shape.left_radii[0] + 0.3, 0.0, 1.0)
    shrink = (1.0 - shape.left_taper * rel)[..., None]
    lq = p - shape.left_center
    lq = np.concatenate([lq[..., :1], lq[..., 1:] / shrink], axis=-1)
    left = _ellipsoid(lq, np.zeros(3), shape.left_radii) * shrink[..., 0]
    body = _smin(right, left, 18.0)
    # Visceral plane: rises anteriorly, so it meets the dome at a sharp anterior-inferior edge.
    plane_z = shape.cut_z0 + shape.cut_slope_y * p[..., 1] + shape.cut_slope_x * p[..., 0]
    cut = (plane_z - p[..., 2]) / np.sqrt(1 + shape.cut_slope_y**2 + shape.cut_slope_x**2)
    body = _smax(body, cut, 3.0)
    for center, radii in shape.dents:
        body = _smax(body, -_ellipsoid(p, center, radii), 5.0)
    for kvec, phase, amp in shape.waves:
        body = body + amp * np.sin(p @ kvec + phase)
    return body


def _taubin(vertices: np.ndarray, triangles: np.ndarray, iterations: int, lam: float = 0.5, mu: float = -0.53):
    """Taubin lambda|mu smoothing with uniform weights: removes grid steps without shrinking."""
    n = len(vertices)
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    edges = np.concatenate([edges, edges[:, ::-1]])
    degree = np.bincount(edges[:, 0], minlength=n).astype(np.float64)
    v = vertices.copy()
    for _ in range(iterations):
        for w in (lam, mu):
            acc = np.zeros_like(v)
            np.add.at(acc, edges[:, 0], v[edges[:, 1]])
            v = v + w * (acc / degree[:, None] - v)
    return v


def _largest_component(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep the connected component with most faces (random waves can pinch off tiny islands)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(vertices)
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    face_label = labels[triangles[:, 0]]
    keep_label = np.bincount(face_label).argmax()
    faces = triangles[face_label == keep_label]
    used = np.unique(faces)
    remap = -np.ones(n, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[faces]


def surface_from_grid(
    values: np.ndarray, origin_mm: np.ndarray, spacing_mm: float, smooth_iterations: int
) -> tuple[np.ndarray, np.ndarray]:
    """Closed, outward-facing, Taubin-smoothed surface (mm) of the zero level of a sampled SDF."""
    values = np.array(values, dtype=np.float64)
    # A closed surface needs an outside layer on every face of the box.
    values[[0, -1], :, :] = values[:, [0, -1], :] = values[:, :, [0, -1]] = 1.0
    verts, faces, _, _ = marching_cubes(values, level=0.0, spacing=(spacing_mm,) * 3)
    verts = verts.astype(np.float64) + origin_mm
    faces = faces.astype(np.int64)
    verts, faces = _largest_component(verts, faces)
    if mesh_volume_mm3(verts, faces) < 0:  # make triangles face outwards
        faces = faces[:, ::-1].copy()
    return _taubin(verts, faces, smooth_iterations), faces


def make_liver(seed: int, spacing_mm: float = MESH_SPACING_MM, smooth_iterations: int = 10) -> LiverMesh:
    """Generate liver `seed`: closed watertight surface in mm, centred at its vertex centroid."""
    if not isinstance(seed, int | np.integer) or seed < 0:
        raise InputError(f"liver seed must be a non-negative integer, got {seed!r}")
    if not 0.5 <= spacing_mm <= 10:
        raise InputError(f"mesh spacing must be in [0.5, 10] mm, got {spacing_mm}")
    shape = random_shape(int(seed))
    lo = np.array([-130.0, -95.0, -95.0])
    hi = np.array([140.0, 95.0, 105.0])
    axes = [np.arange(lo[i], hi[i] + spacing_mm, spacing_mm) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    verts, faces = surface_from_grid(shape_sdf(shape, grid), lo, spacing_mm, smooth_iterations)
    rng = np.random.default_rng([int(seed), 1])
    target = np.array([rng.uniform(*WIDTH_RANGE_MM), rng.uniform(*DEPTH_RANGE_MM), rng.uniform(*HEIGHT_RANGE_MM)])
    raw_center = verts.mean(axis=0)
    extents = verts.max(axis=0) - verts.min(axis=0)
    scale = target / extents
    vertices_mm = (verts - raw_center) * scale
    return LiverMesh(
        vertices_mm=vertices_mm,
        triangles=faces,
        seed=int(seed),
        shape=shape,
        raw_center=raw_center,
        scale_xyz=scale,
    )
