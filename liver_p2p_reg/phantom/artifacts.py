"""What a real intraoperative view adds to a clean crop: non-uniform density, holes, flying pixels, background.

All functions work in the deformed liver's frame (mm), on the points a crop kept, before the
target's random pose and noise; each draws only from the generator it is given.
- density `mesh-vertices`: the view is made of the vertices of a (coarser, re-meshed) surface
  mesh instead of a sensor's samples: the density of the mesh, not of a camera;
- density `depth-falloff`: a depth camera's points per surface area fall with the incidence
  angle and the square of the depth;
- instrument holes (capsules removed), flying pixels (points pushed along the viewing ray) and
  background points (a patch of another surface beside the liver) for training.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

DENSITY_MODES = ("uniform", "mesh-vertices", "depth-falloff")


@dataclass(frozen=True)
class Artifacts:
    """Upper bounds of the training-time artifacts (each drawn uniformly in [0, bound] per target)."""

    hole_probability: float = 0.0  # chance of 1-3 instrument-shaped holes
    outlier_fraction: float = 0.0  # flying pixels, as a share of the view's points
    background_fraction: float = 0.0  # another surface's points, as a share of the view's points

    @property
    def any(self) -> bool:
        return self.hole_probability > 0 or self.outlier_fraction > 0 or self.background_fraction > 0


def clustered_vertices(vertices_mm: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices of a coarse, re-meshed vertex set: one vertex per occupied cell of a 4-9 mm grid
    with a random offset (vertex clustering, the decimation CT pipelines use)."""
    cell = rng.uniform(4.0, 9.0)
    keys = np.floor((vertices_mm - vertices_mm.min(axis=0) + rng.uniform(0, cell, 3)) / cell).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first)


def mesh_vertex_view(
    dense_mm: np.ndarray, kept: np.ndarray, coarse_mm: np.ndarray, max_gap_mm: float = 3.0
) -> np.ndarray:
    """The coarse vertices lying in the region a crop kept: those whose nearest dense sample was kept."""
    in_view = np.zeros(len(dense_mm), dtype=bool)
    in_view[kept] = True
    dist, nearest = cKDTree(dense_mm).query(coarse_mm, k=1)
    return coarse_mm[in_view[nearest] & (dist <= max_gap_mm)]


def depth_falloff(
    points_mm: np.ndarray, normals: np.ndarray, eye_mm: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Indices kept by a depth camera at `eye_mm`: density ~ cos(incidence) / depth^2.

    A sensor samples far more densely than the generator's surface samples, so the falloff
    thins only the sparse tail: the 40 % of points the camera sees best are all kept and the
    rest in proportion to cos / depth^2 (grazing and far parts of the view thin out).
    """
    ray = points_mm - eye_mm
    depth = np.linalg.norm(ray, axis=1)
    cos = np.abs(np.einsum("ij,ij->i", ray / depth[:, None], normals))
    p = cos / depth**2
    p = p / max(float(np.quantile(p, 0.6)), 1e-12)
    return np.flatnonzero(rng.random(len(points_mm)) < p)


def virtual_eye(points_mm: np.ndarray, normals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A camera position for a view that has none (random crops): 80-150 mm out along its mean normal."""
    n = normals.mean(axis=0)
    n = n / max(float(np.linalg.norm(n)), 1e-9)
    return points_mm.mean(axis=0) + rng.uniform(80.0, 150.0) * n


def instrument_holes(points_mm: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices kept after 1-3 instrument shadows: capsules 3-7 mm wide and 20-70 mm long through the view."""
    keep = np.ones(len(points_mm), dtype=bool)
    for _ in range(int(rng.integers(1, 4))):
        start = points_mm[rng.integers(len(points_mm))]
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        length, radius = rng.uniform(20.0, 70.0), rng.uniform(3.0, 7.0)
        rel = points_mm - start
        along = np.clip(rel @ direction, 0.0, length)
        keep &= np.linalg.norm(rel - along[:, None] * direction, axis=1) > radius
    return np.flatnonzero(keep)


def flying_pixels(points_mm: np.ndarray, eye_mm: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """`fraction` of the points pushed 5-40 mm along their viewing ray (mixed depths at edges)."""
    n = int(round(fraction * len(points_mm)))
    if n == 0:
        return np.zeros((0, 3))
    src = points_mm[rng.choice(len(points_mm), size=n)]
    ray = src - eye_mm
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    return src + ray * rng.uniform(-40.0, 40.0, size=(n, 1))


def background_patch(
    points_mm: np.ndarray, normals: np.ndarray, fraction: float, rng: np.random.Generator
) -> np.ndarray:
    """`fraction` x N points on a tilted plane patch beside and behind the view (another organ)."""
    n = int(round(fraction * len(points_mm)))
    if n == 0:
        return np.zeros((0, 3))
    centre = points_mm.mean(axis=0)
    normal = normals.mean(axis=0)
    normal /= max(float(np.linalg.norm(normal)), 1e-9)
    radius = float(np.percentile(np.linalg.norm(points_mm - centre, axis=1), 90))
    side = rng.normal(size=3)
    side -= (side @ normal) * normal
    side /= max(float(np.linalg.norm(side)), 1e-9)
    plane_centre = centre + side * radius * rng.uniform(0.6, 1.3) - normal * rng.uniform(5.0, 40.0)
    tilt = normal + rng.normal(size=3) * 0.4
    tilt /= np.linalg.norm(tilt)
    u = np.cross(tilt, [1.0, 0.0, 0.0] if abs(tilt[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(tilt, u)
    r = radius * rng.uniform(0.3, 0.8) * np.sqrt(rng.random(n))
    a = rng.uniform(0, 2 * np.pi, n)
    return plane_centre + (r * np.cos(a))[:, None] * u + (r * np.sin(a))[:, None] * v
