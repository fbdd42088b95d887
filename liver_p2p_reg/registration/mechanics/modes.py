"""The preop liver's elastic model for the non-rigid stage: a tetrahedral mesh and its lowest free vibration modes.

Why modes: linear elasticity on the free (unsupported) body, K u = lambda M u, has six zero-energy rigid
modes and then deformations ordered by strain energy. Keeping the lowest few dozen gives a basis in which
every deformation is smooth and volumetric, the strain energy is diagonal (lambda_j per mm^2 of amplitude),
and no combination moves the liver rigidly (the modes are M-orthogonal to the rigid ones), so the rigid pose
stays with the rigid parameters. The solve per registration is then a few dozen unknowns, not 3N.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.mechanics.fem import POISSON_RATIO, assemble
from liver_p2p_reg.registration.mechanics.solid import closed_solid
from liver_p2p_reg.registration.mechanics.tetmesh import TetMesh, build_tetmesh

# Young's modulus used only to report strain energy in mJ (soft liver parenchyma, a few kPa; the fit
# itself is independent of it: the regularization weight is relative to the first mode's stiffness).
YOUNGS_MODULUS_KPA = 5.0


@dataclass
class ElasticModel:
    """A preop model's tetrahedral mesh, its non-rigid modes and the embedding of its surface points."""

    mesh: TetMesh
    modes_mm: np.ndarray  # (m, N, 3) nodal displacement of each mode, volume-RMS 1 mm
    stiffness_ratio: np.ndarray  # (m,) strain energy of a 1 mm mode relative to the first mode's
    energy_mj_per_mm2: float  # strain energy (mJ at YOUNGS_MODULUS_KPA) of the first mode at 1 mm amplitude
    source_mm: np.ndarray  # (P, 3) the preop points the model was built from
    source_normals: np.ndarray  # (P, 3) their outward normals
    source_ids: np.ndarray  # (P, 4) tetrahedron node ids of each source point
    source_weights: np.ndarray  # (P, 4) barycentric weights
    build_ms: float = 0.0
    _basis_cache: dict = field(default_factory=dict, repr=False)
    _surfaces: dict = field(default_factory=dict, repr=False)  # this model fitted through other points (on_surface)

    @property
    def n_modes(self) -> int:
        return len(self.modes_mm)

    def nodal_displacement_mm(self, coefficients_mm: np.ndarray) -> np.ndarray:
        """Displacement (N, 3) of every mesh node for mode coefficients (mm)."""
        return np.einsum("m,mnd->nd", np.asarray(coefficients_mm, dtype=np.float64), self.modes_mm)

    def basis_at(self, ids: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """(P, 3, m): each point's displacement per unit coefficient of each mode."""
        return np.einsum("pk,mpkd->pdm", weights, self.modes_mm[:, ids, :])

    def source_basis(self, stride: int) -> np.ndarray:
        """basis_at of every `stride`-th source point, computed once per model and stride (the fit's per-frame need)."""
        if stride not in self._basis_cache:
            self._basis_cache[stride] = self.basis_at(self.source_ids[::stride], self.source_weights[::stride])
        return self._basis_cache[stride]

    def on_surface(self, points_mm: np.ndarray, normals: np.ndarray) -> ElasticModel:
        """The same model fitted through other preop points (a sampled cloud beside the mesh it was built on)."""
        points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        ids, weights = self.embed(points)
        return dataclasses.replace(
            self,
            source_mm=points,
            source_normals=np.asarray(normals, float),
            source_ids=ids,
            source_weights=weights,
            _basis_cache={},
            _surfaces={},
        )

    def displacement_at(self, points_mm: np.ndarray, coefficients_mm: np.ndarray) -> np.ndarray:
        """Displacement (P, 3) at any preop points; a point outside the mesh takes its nearest node's."""
        ids, weights = self.embed(points_mm)
        return self.mesh.interpolate(self.nodal_displacement_mm(coefficients_mm), ids, weights)

    def embed(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tetrahedron ids and weights of points; points outside the mesh are tied to their nearest node."""
        return embed_points(self.mesh, points_mm)


def embed_points(mesh: TetMesh, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedron ids and weights of points in `mesh`; points outside it are tied to their nearest node."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    cells = np.floor((pts - mesh.origin_mm) / mesh.spacing_mm).astype(np.int64)
    shape = np.array(mesh.node_index.shape) - 1
    inside = np.all((cells >= 0) & (cells < shape), axis=1)
    c = np.clip(cells, 0, shape - 1)
    for corner in np.ndindex(2, 2, 2):
        inside &= mesh.node_index[c[:, 0] + corner[0], c[:, 1] + corner[1], c[:, 2] + corner[2]] >= 0
    ids = np.zeros((len(pts), 4), dtype=np.int64)
    weights = np.zeros((len(pts), 4))
    if inside.any():
        ids[inside], weights[inside] = mesh.embed(pts[inside])
    if (~inside).any():
        ids[~inside, 0] = cKDTree(mesh.nodes_mm).query(pts[~inside])[1]
        weights[~inside, 0] = 1.0
    return ids, weights


def _lumped_mass(mesh: TetMesh) -> np.ndarray:
    """Each node's share (a quarter) of the volume of the tetrahedra around it (mm^3)."""
    p = mesh.nodes_mm[mesh.tets]
    vol = np.abs(np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))) / 6.0
    mass = np.zeros(len(mesh.nodes_mm))
    np.add.at(mass, mesh.tets.ravel(), np.repeat(vol / 4.0, 4))
    return mass


def _rigid_modes(nodes_mm: np.ndarray) -> np.ndarray:
    """(6, N, 3) translations and rotations about the centroid."""
    r = nodes_mm - nodes_mm.mean(axis=0)
    out = np.zeros((6, len(nodes_mm), 3))
    for axis in range(3):
        out[axis, :, axis] = 1.0
        e = np.zeros(3)
        e[axis] = 1.0
        out[3 + axis] = np.cross(e, r)
    return out


def build_elastic_model(
    source_mm: np.ndarray,
    source_normals: np.ndarray,
    triangles: np.ndarray | None = None,
    *,
    n_modes: int = 24,
    target_tets: int = 6000,
    poisson_ratio: float = POISSON_RATIO,
) -> ElasticModel:
    """Tetrahedralize the closed preop surface and compute its `n_modes` lowest non-rigid modes (once per model)."""
    from scipy.sparse import diags
    from scipy.sparse.linalg import ArpackError, eigsh

    start = time.perf_counter()
    source_mm = np.asarray(source_mm, dtype=np.float64)
    extent = float(np.max(source_mm.max(axis=0) - source_mm.min(axis=0)))
    solid = closed_solid(source_mm, triangles)
    mesh = build_tetmesh(solid, target_tets=target_tets, margin_mm=0.0)
    if len(mesh.nodes_mm) < 3 * (n_modes + 6):
        raise InputError(f"the preop solid gives too few mesh nodes ({len(mesh.nodes_mm)}) for {n_modes} modes")
    system = assemble(mesh, youngs_modulus=1.0, poisson_ratio=poisson_ratio)
    node_mass = _lumped_mass(mesh)
    dofs = system.nodal_dofs  # (3, N)
    mass = np.zeros(system.stiffness.shape[0])
    for axis in range(3):
        mass[dofs[axis]] = node_mass
    volume = float(node_mass.sum())
    # Shift-invert just below zero: the six rigid modes and the softest deformations come first.
    shift = -1e-3 / extent**2
    try:
        v0 = np.full(len(mass), 1.0 / np.sqrt(len(mass)))  # a fixed start vector: the same modes every build
        values, vectors = eigsh(system.stiffness, k=n_modes + 6, M=diags(mass), sigma=shift, which="LM", v0=v0)
    except (ArpackError, RuntimeError) as exc:
        raise InputError(f"the preop model's elastic modes did not converge ({exc})") from exc
    order = np.argsort(values)
    values, vectors = values[order][6:], vectors[:, order][:, 6:]
    modes = np.stack([vectors[dofs[axis]] for axis in range(3)], axis=-1).transpose(1, 0, 2)  # (m, N, 3)
    modes = _without_rigid(modes, mesh.nodes_mm, node_mass)
    modes *= np.sqrt(volume)  # M-orthonormal -> volume-RMS displacement 1 mm
    # A mode's sign is arbitrary in the eigensolver: fix it so the same model always has the same modes.
    flip = np.sign(np.einsum("mnd->m", modes[:, : min(50, modes.shape[1]), :]) + 1e-300)
    modes *= flip[:, None, None]
    normals = np.asarray(source_normals, dtype=np.float64)
    try:
        ids, weights = mesh.embed(source_mm)
    except InputError:  # points on a speck build_tetmesh dropped: tied to their nearest node, as `embed` does later
        ids, weights = embed_points(mesh, source_mm)
    energy_mj = 0.5 * values[0] * volume * YOUNGS_MODULUS_KPA * 1e-3  # E (N/mm^2) x mm^3 = mJ
    return ElasticModel(
        mesh=mesh,
        modes_mm=modes,
        stiffness_ratio=values / values[0],
        energy_mj_per_mm2=float(energy_mj),
        source_mm=source_mm,
        source_normals=normals,
        source_ids=ids,
        source_weights=weights,
        build_ms=(time.perf_counter() - start) * 1e3,
    )


def _without_rigid(modes: np.ndarray, nodes_mm: np.ndarray, node_mass: np.ndarray) -> np.ndarray:
    """Project the (numerically not quite) rigid part out of each mode, M-weighted, and re-normalize."""
    rigid = _rigid_modes(nodes_mm).reshape(6, -1)
    w = np.repeat(node_mass, 3)
    gram = (rigid * w) @ rigid.T
    flat = modes.reshape(len(modes), -1)
    flat = flat - np.linalg.solve(gram, (rigid * w) @ flat.T).T @ rigid
    flat /= np.sqrt(np.sum(flat**2 * w, axis=1, keepdims=True))
    return flat.reshape(modes.shape)
