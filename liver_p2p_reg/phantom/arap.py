"""A second deformation family: as-rigid-as-possible (ARAP) deformations of the tetrahedral mesh driven by
handles (a sagging lobe, an abdominal wall pressing in), which no linear-elastic model reproduces.

Why a second family: every set of the generator deforms with linear FEM; a non-rigid stage built on
linear FEM and judged on those sets would be judged on data made by its own model. ARAP
(Sorkine & Alexa 2007, here on the tet mesh's edges) is geometric and nonlinear: each node's
neighbourhood keeps its shape up to a rotation of its own, so a lobe swings and bends where linear
elasticity would stretch. The handles: a posterior patch held in place (ligaments, vena cava, as in
the FEM family), and one to three moved regions: a lobe tip translated mostly downward ("gravity")
or a patch of the anterior surface pushed inward along its normals ("pneumoperitoneum"). The
magnitude is drawn from the FEM family's distribution (fem.RMS_MEAN_MM, fem.RMS_SHAPE, interior RMS
after rigid removal) and reached by bisection on the handles' displacement.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.linalg import splu

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.mechanics.fem import RMS_MEAN_MM, RMS_RANGE_MM, RMS_SHAPE, posterior_support
from liver_p2p_reg.registration.mechanics.tetmesh import TetMesh
from liver_p2p_reg.registration.procrustes import rigid_fit_np

ITERATIONS = 12  # local/global steps; the energy changes by < 1e-3 relative after about 8 on these meshes
HANDLE_KINDS = ("gravity", "pneumoperitoneum")


@dataclass
class HandleCase:
    """Handles of one deformation: fixed nodes and moved nodes with their unit displacement (scaled later)."""

    fixed_nodes: np.ndarray  # (K,) node ids held in place
    moved_nodes: np.ndarray  # (H,) node ids moved
    unit_disp: np.ndarray  # (H, 3) their displacement at scale 1 (mm)
    kinds: tuple[str, ...]  # what each moved region imitates
    target_rms_mm: float  # interior RMS after rigid removal to reach


def mesh_edges(tets: np.ndarray) -> np.ndarray:
    """The unique undirected edges (E, 2) of a tetrahedral mesh."""
    pairs = np.concatenate([tets[:, [a, b]] for a in range(4) for b in range(a + 1, 4)])
    return np.unique(np.sort(pairs, axis=1), axis=0)


class ArapSolver:
    """ARAP on one tet mesh with a fixed set of constrained nodes (uniform edge weights); factorized once."""

    def __init__(self, nodes_mm: np.ndarray, tets: np.ndarray, constrained: np.ndarray) -> None:
        self.rest = np.asarray(nodes_mm, dtype=np.float64)
        n = len(self.rest)
        self.edges = mesh_edges(tets)
        i, j = self.edges[:, 0], self.edges[:, 1]
        ones = np.ones(len(i))
        adjacency = coo_matrix((np.concatenate([ones, ones]), (np.concatenate([i, j]), np.concatenate([j, i]))), (n, n))
        degree = np.asarray(adjacency.sum(axis=1)).ravel()
        laplacian = (coo_matrix((degree, (np.arange(n), np.arange(n))), (n, n)) - adjacency).tocsr()
        self.constrained = np.unique(constrained)
        self.free = np.setdiff1d(np.arange(n), self.constrained)
        if len(self.constrained) < 3 or len(self.free) == 0:
            raise InputError("ARAP needs at least 3 constrained nodes and one free node")
        self._lu = splu(laplacian[self.free][:, self.free].tocsc())
        self._coupling = laplacian[self.free][:, self.constrained].tocsr()
        self._rest_edges = self.rest[i] - self.rest[j]  # (E, 3)

    def solve(self, constrained_mm: np.ndarray, start_mm: np.ndarray | None = None) -> np.ndarray:
        """Node positions (N, 3) with the constrained nodes at `constrained_mm` (their order in `self.constrained`)."""
        current = self.rest.copy() if start_mm is None else np.array(start_mm, dtype=np.float64)
        current[self.constrained] = constrained_mm
        i, j = self.edges[:, 0], self.edges[:, 1]
        for _ in range(ITERATIONS):
            rotations = self._local_rotations(current)
            # b_i = sum_j (R_i + R_j) / 2 (p_i - p_j): each edge adds to both ends with opposite signs
            rotated = 0.5 * np.einsum("eab,eb->ea", rotations[i] + rotations[j], self._rest_edges)
            rhs = np.zeros_like(current)
            np.add.at(rhs, i, rotated)
            np.add.at(rhs, j, -rotated)
            b = rhs[self.free] - self._coupling @ current[self.constrained]
            current[self.free] = self._lu.solve(b)
        return current

    def _local_rotations(self, current: np.ndarray) -> np.ndarray:
        """Each node's best rotation (N, 3, 3) of its rest edges onto its current edges (Kabsch per node)."""
        i, j = self.edges[:, 0], self.edges[:, 1]
        outer = np.einsum("ea,eb->eab", self._rest_edges, current[i] - current[j])  # (E, 3, 3)
        cov = np.zeros((len(current), 3, 3))
        np.add.at(cov, i, outer)
        np.add.at(cov, j, outer)
        U, _, Vt = np.linalg.svd(cov)
        flip = np.linalg.det(np.einsum("nab,nbc->nac", U, Vt)) < 0
        U[flip, :, 2] *= -1.0
        return np.einsum("nab,nbc->nac", U, Vt).transpose(0, 2, 1)  # R = V U^T


def random_handle_case(mesh: TetMesh, rng: np.random.Generator) -> HandleCase:
    """A posterior fixed patch and one to three moved regions (gravity-like sag, pneumoperitoneum-like press)."""
    nodes = mesh.nodes_mm
    bnd, anchor, fix_radius, fixed = posterior_support(mesh, rng)  # as the FEM family's support
    far = bnd[np.linalg.norm(nodes[bnd] - anchor, axis=1) > fix_radius + 40.0]
    candidates = far if len(far) else bnd
    centroid = nodes.mean(axis=0)
    disp = np.zeros_like(nodes)
    moved = np.zeros(len(nodes), dtype=bool)
    kinds = []
    for _ in range(int(rng.integers(1, 4))):
        kind = HANDLE_KINDS[int(rng.integers(len(HANDLE_KINDS)))]
        center = nodes[rng.choice(candidates)]
        radius = rng.uniform(15.0, 35.0)
        near = bnd[np.linalg.norm(nodes[bnd] - center, axis=1) <= radius]
        if kind == "gravity":  # the whole region translated: the lobe between it and the support bends
            down = np.array([0.0, 0.0, -1.0]) + rng.normal(size=3) * 0.4
            disp[near] += down / np.linalg.norm(down)
        else:  # pushed in along the local inward direction, most at the patch's centre
            inward = centroid - nodes[near]
            inward /= np.linalg.norm(inward, axis=1, keepdims=True) + 1e-12
            bump = np.cos(0.5 * np.pi * np.linalg.norm(nodes[near] - center, axis=1) / radius) ** 2
            disp[near] += bump[:, None] * inward
        moved[near] = True
        kinds.append(kind)
    moved[fixed] = False  # a support wins over a handle
    moved_ids = np.flatnonzero(moved)
    target = float(np.clip(rng.gamma(RMS_SHAPE, RMS_MEAN_MM / RMS_SHAPE), *RMS_RANGE_MM))
    return HandleCase(np.unique(fixed), moved_ids, disp[moved_ids], tuple(kinds), target)


def interior_rms_mm(
    rest_mm: np.ndarray, moved_mm: np.ndarray, fiducial_ids: np.ndarray
) -> tuple[float, np.ndarray, float]:
    """RMS displacement of the fiducials after the rigid fit of all nodes (as the FEM family measures it), the
    nodes rigidly re-aligned onto the rest shape, and the rotation that fit removed (degrees)."""
    R, t = rigid_fit_np(moved_mm, rest_mm)
    aligned = moved_mm @ R.T + t
    d = aligned[fiducial_ids] - rest_mm[fiducial_ids]
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1)))), aligned, angle


def arap_deformation(
    mesh: TetMesh, case: HandleCase, fiducial_ids: np.ndarray, solver: ArapSolver | None = None
) -> tuple[np.ndarray, float, float]:
    """Node positions (N, 3) of the deformed mesh, rigidly re-aligned onto the rest shape, whose fiducial RMS
    is the case's target (bisection on the handles' scale); that RMS (mm) and the rotation removed (deg)."""
    constrained = np.concatenate([case.fixed_nodes, case.moved_nodes])
    solver = solver or ArapSolver(mesh.nodes_mm, mesh.tets, constrained)
    order = np.searchsorted(solver.constrained, constrained)
    rest = mesh.nodes_mm

    def deform(scale: float, start: np.ndarray | None) -> tuple[tuple[float, np.ndarray, float], np.ndarray]:
        target = rest[constrained].copy()
        target[len(case.fixed_nodes) :] += scale * case.unit_disp
        placed = np.empty((len(solver.constrained), 3))
        placed[order] = target
        moved = solver.solve(placed, start)
        return interior_rms_mm(rest, moved, fiducial_ids), moved

    lo, hi = 0.0, max(case.target_rms_mm, 1.0)
    (rms_hi, _, _), start = deform(hi, None)
    for _ in range(12):  # grow the bracket (the RMS grows with the handles' displacement)
        if rms_hi >= case.target_rms_mm:
            break
        lo, hi = hi, hi * 2.0
        (rms_hi, _, _), start = deform(hi, start)
    for _ in range(30):  # bisection, each solve started from the last one (a few ARAP steps suffice then)
        mid = 0.5 * (lo + hi)
        (rms, aligned, angle), start = deform(mid, start)
        if abs(rms - case.target_rms_mm) < 0.01 * case.target_rms_mm:
            break
        lo, hi = (mid, hi) if rms < case.target_rms_mm else (lo, mid)
    return aligned, rms, angle
