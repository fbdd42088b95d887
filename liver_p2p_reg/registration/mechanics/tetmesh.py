"""Structured tetrahedral mesh of a liver's interior with the surface embedded in it.

Why structured and not TetGen/gmsh: those are heavy native dependencies; a regular grid of
cubes covering the liver (every cube whose centre lies inside the implicit surface, plus
every cube that holds a surface vertex) split into the 6 Kuhn tetrahedra is conforming,
needs no native code, and makes the embedding trivial. Each surface vertex lies in exactly
one cube; the Kuhn tetrahedron holding it follows from the ordering of its local
coordinates, and its barycentric weights are differences of those sorted coordinates, so the
FEM displacement (linear on each tetrahedron) is interpolated exactly.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from itertools import permutations

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.mechanics.surface import SurfaceMesh, mesh_volume_mm3

LOG = logging.getLogger("liver_p2p_reg")

# Kuhn subdivision: the tetrahedron for permutation (a, b, c) walks 0 -> e_a -> e_a+e_b -> 1.
_PERMS = np.array(list(permutations(range(3))), dtype=np.int64)  # (6, 3)
_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.int64)


def _kuhn_local_tets() -> np.ndarray:
    """(6, 4) corner indices (into _CORNERS) of the 6 Kuhn tetrahedra of the unit cube."""
    tets = []
    for perm in _PERMS:
        c = np.zeros(3, dtype=np.int64)
        path = [c.copy()]
        for axis in perm:
            c[axis] = 1
            path.append(c.copy())
        tets.append([int(p[0] * 4 + p[1] * 2 + p[2]) for p in path])
    return np.array(tets, dtype=np.int64)


_LOCAL_TETS = _kuhn_local_tets()


@dataclass
class TetMesh:
    """Tetrahedral mesh (mm) on a regular grid, with the liver surface embedded in it."""

    nodes_mm: np.ndarray  # (N, 3)
    tets: np.ndarray  # (T, 4) int64
    origin_mm: np.ndarray  # (3,) grid origin
    spacing_mm: float
    node_index: np.ndarray  # (nx+1, ny+1, nz+1) int64: node id of each grid point or -1
    interior: np.ndarray  # (N,) bool: node lies inside the surface by a margin
    boundary: np.ndarray  # (N,) bool: node touches a cube outside the mesh

    def embed(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Node ids (P, 4) and barycentric weights (P, 4) of the tetrahedron holding each point."""
        pts = (np.asarray(points_mm, dtype=np.float64) - self.origin_mm) / self.spacing_mm
        cube = np.floor(pts).astype(np.int64)
        shape = np.array(self.node_index.shape) - 1
        cube = np.clip(cube, 0, shape - 1)
        local = np.clip(pts - cube, 0.0, 1.0)
        order = np.argsort(-local, axis=1, kind="stable")  # axes by decreasing local coordinate
        sorted_local = np.take_along_axis(local, order, axis=1)
        weights = np.stack(
            [
                1.0 - sorted_local[:, 0],
                sorted_local[:, 0] - sorted_local[:, 1],
                sorted_local[:, 1] - sorted_local[:, 2],
                sorted_local[:, 2],
            ],
            axis=1,
        )
        ids = np.empty((len(pts), 4), dtype=np.int64)
        corner = cube.copy()
        ids[:, 0] = self.node_index[corner[:, 0], corner[:, 1], corner[:, 2]]
        rows = np.arange(len(pts))
        for step in range(3):
            corner[rows, order[:, step]] += 1
            ids[:, step + 1] = self.node_index[corner[:, 0], corner[:, 1], corner[:, 2]]
        if np.any(ids < 0):
            raise InputError("a point lies outside the tetrahedral mesh")
        return ids, weights

    def interpolate(self, node_values: np.ndarray, ids: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """Linear interpolation of per-node values at embedded points."""
        return np.einsum("pk,pkd->pd", weights, node_values[ids])


# A part of the cubes holding at least this share is a body of its own (refused beside another); smaller ones are
# specks of the segmentation or a sharp tip's cube hanging on an edge or a corner (dropped).
MIN_PART_SHARE = 0.01


def _one_body(active: np.ndarray) -> np.ndarray:
    """The cubes of the solid's one body. Why: each part not joined to it through a cube face (a free part, or one
    hanging on an edge or a corner, a hinge) brings its own zero-energy motions, which the modes would take for the
    softest deformations. Small parts are dropped with a warning; a second part of MIN_PART_SHARE or more is an
    InputError naming the count."""
    from scipy.ndimage import label

    parts, n = label(active)  # face-adjacent cubes: the default structure is the 6-neighbourhood
    if n <= 1:
        return active
    sizes = np.bincount(parts.ravel())[1:]
    shares = sizes / sizes.sum()
    bodies = int(np.sum(shares >= MIN_PART_SHARE))
    if bodies > 1:
        raise InputError(
            f"the preop solid has {bodies} separate parts (the largest holds {100 * shares.max():.0f}% of its "
            "volume): the elastic model needs one connected organ"
        )
    largest = int(np.argmax(sizes))
    LOG.warning(
        "preop solid: %d small piece(s) joined to the rest by no cube face (%.2f%% of its volume: a speck or a sharp "
        "tip) left out of the elastic model; the surface points there follow their nearest mesh node",
        n - 1,
        100 * (1 - shares[largest]),
    )
    return parts == largest + 1


def build_tetmesh(liver: SurfaceMesh, target_tets: int = 10_000, margin_mm: float = 2.0) -> TetMesh:
    """Cover the liver with cubes of the edge giving about `target_tets` tetrahedra."""
    if target_tets < 60:
        raise InputError(f"target_tets must be >= 60, got {target_tets}")
    verts = liver.vertices_mm
    # A voxelized solid (solid.py) knows its volume; a closed triangle surface gives it exactly.
    volume = getattr(liver, "volume_mm3", None) or abs(mesh_volume_mm3(verts, liver.triangles))
    # Boundary cubes add roughly a shell's worth; 0.8 compensates so the count lands near target.
    h = float((volume / (0.8 * target_tets / 6.0)) ** (1.0 / 3.0))
    origin = verts.min(axis=0) - 1.5 * h
    n_cells = np.ceil((verts.max(axis=0) + 1.5 * h - origin) / h).astype(np.int64)
    axes = [origin[i] + h * (np.arange(n_cells[i]) + 0.5) for i in range(3)]
    centers = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    active = liver.implicit_mm(centers.reshape(-1, 3)).reshape(tuple(n_cells)) < 0
    # Every surface point the generator will deform must lie in a cube of the mesh: the surface's
    # vertices and, for a liver read from a file, the file's own (coarse) vertices too.
    coarse = getattr(liver, "coarse_vertices_mm", None)
    embedded = verts if coarse is None else np.concatenate([verts, coarse])
    cube_of_vertex = np.clip(np.floor((embedded - origin) / h).astype(np.int64), 0, n_cells - 1)
    active[cube_of_vertex[:, 0], cube_of_vertex[:, 1], cube_of_vertex[:, 2]] = True
    active = _one_body(active)
    cubes = np.argwhere(active)  # (C, 3), sorted lexicographically -> deterministic ids
    node_shape = tuple(n_cells + 1)
    used = np.zeros(node_shape, dtype=bool)
    for c in _CORNERS:
        used[cubes[:, 0] + c[0], cubes[:, 1] + c[1], cubes[:, 2] + c[2]] = True
    node_index = -np.ones(node_shape, dtype=np.int64)
    grid_nodes = np.argwhere(used)
    node_index[grid_nodes[:, 0], grid_nodes[:, 1], grid_nodes[:, 2]] = np.arange(len(grid_nodes))
    corner_ids = np.stack(
        [node_index[cubes[:, 0] + c[0], cubes[:, 1] + c[1], cubes[:, 2] + c[2]] for c in _CORNERS], axis=1
    )  # (C, 8)
    tets = corner_ids[:, _LOCAL_TETS].reshape(-1, 4)
    nodes_mm = origin + h * grid_nodes.astype(np.float64)
    # A node is on the mesh boundary when one of its 8 surrounding cubes is not active.
    padded = np.zeros(tuple(n_cells + 2), dtype=bool)
    padded[1:-1, 1:-1, 1:-1] = active
    full = np.ones(len(grid_nodes), dtype=bool)
    for c in _CORNERS:
        g = grid_nodes + c  # cube (g - 1 + c) in unpadded indices -> padded index g + c
        full &= padded[g[:, 0], g[:, 1], g[:, 2]]
    interior = liver.implicit_mm(nodes_mm) < -margin_mm
    return TetMesh(
        nodes_mm=nodes_mm,
        tets=tets,
        origin_mm=origin,
        spacing_mm=h,
        node_index=node_index,
        interior=interior,
        boundary=~full,
    )
