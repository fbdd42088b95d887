"""One liver and its deformations: anatomy -> tetrahedral mesh -> fiducials -> deformed surfaces.

Two families: "fem" (linear elasticity, the generator's default) and "arap" (as-rigid-as-possible
with handles, arap.py: a deformation no linear-elastic model reproduces).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom.anatomy import LiverMesh, make_liver
from liver_p2p_reg.registration.mechanics.fem import assemble, calibrate, random_load_case, solve_displacement
from liver_p2p_reg.registration.mechanics.tetmesh import TetMesh, build_tetmesh

MAX_FIDUCIALS = 300
DEFORMATION_FAMILIES = ("fem", "arap")


def float32_exact(points: np.ndarray) -> np.ndarray:
    """Round to float32 precision, kept as float64.

    Clouds are stored as float32; measuring visibility on exactly the stored values makes the
    stored visibility reproducible from the file.
    """
    return np.asarray(points, dtype=np.float32).astype(np.float64)


@dataclass
class Deformation:
    """One deformed state, rigidly re-aligned onto the undeformed liver (Procrustes)."""

    surface_mm: np.ndarray  # (V, 3) deformed surface vertices, same triangles as the liver
    fiducials_mm: np.ndarray  # (F, 3) deformed fiducials, same order as the undeformed ones
    rms_mm: float  # RMS fiducial displacement after rigid removal
    max_mm: float  # largest fiducial displacement after rigid removal
    n_fixed_nodes: int = 0
    rigid_rotation_deg: float = 0.0  # rotation Procrustes removed (small: linear model valid)
    coarse_mm: np.ndarray | None = None  # (C, 3) the file's own vertices, deformed (livers read from a file)


@dataclass
class SimulatedLiver:
    """An undeformed liver surface, its interior fiducials and its deformations (all mm)."""

    liver_id: int
    vertices_mm: np.ndarray  # (V, 3)
    triangles: np.ndarray  # (F, 3)
    fiducials_mm: np.ndarray  # (F, 3) interior tetrahedral-mesh vertices
    deformations: list[Deformation] = field(default_factory=list)
    n_tets: int = 0
    n_nodes: int = 0
    coarse_vertices_mm: np.ndarray | None = None  # (C, 3) a file liver's own vertices (density variants)


def select_fiducials(mesh: TetMesh, seed: int, max_count: int = MAX_FIDUCIALS) -> np.ndarray:
    """Node ids of up to `max_count` interior vertices, in a fixed (ascending) order."""
    ids = np.flatnonzero(mesh.interior)
    if len(ids) < 3:
        raise InputError("liver interior too small for fiducials")
    if len(ids) > max_count:
        ids = np.sort(np.random.default_rng([int(seed), 3]).choice(ids, size=max_count, replace=False))
    return ids


def simulate_liver(
    seed: int,
    n_deformations: int,
    target_tets: int = 10_000,
    liver: LiverMesh | None = None,
    family: str = "fem",
) -> SimulatedLiver:
    """Generate liver `seed` and `n_deformations` random deformations of it of one family ("fem" | "arap")."""
    if n_deformations < 0:
        raise InputError(f"number of deformations must be >= 0, got {n_deformations}")
    if family not in DEFORMATION_FAMILIES:
        raise InputError(f"unknown deformation family {family!r}; choose one of: {', '.join(DEFORMATION_FAMILIES)}")
    liver = liver if liver is not None else make_liver(seed)
    mesh = build_tetmesh(liver, target_tets=target_tets)
    fid_ids = select_fiducials(mesh, seed)
    sim = SimulatedLiver(
        liver_id=int(seed),
        vertices_mm=float32_exact(liver.vertices_mm),
        triangles=liver.triangles,
        fiducials_mm=mesh.nodes_mm[fid_ids].copy(),
        n_tets=len(mesh.tets),
        n_nodes=len(mesh.nodes_mm),
        coarse_vertices_mm=getattr(liver, "coarse_vertices_mm", None),
    )
    if n_deformations == 0:
        return sim
    if family == "arap":
        sim.deformations = _arap_deformations(sim, liver, mesh, fid_ids, n_deformations)
        return sim
    system = assemble(mesh)
    ids, weights = mesh.embed(liver.vertices_mm)
    coarse = sim.coarse_vertices_mm
    coarse_embedding = mesh.embed(coarse) if coarse is not None else None
    for d in range(n_deformations):
        rng = np.random.default_rng([int(seed), 2, d])
        load = random_load_case(mesh, rng)
        unit = solve_displacement(system, load, mesh.nodes_mm)
        scale, R, t, rms = calibrate(mesh.nodes_mm, unit, fid_ids, load.target_rms_mm)
        disp = scale * unit
        surface = float32_exact((liver.vertices_mm + mesh.interpolate(disp, ids, weights)) @ R.T + t)
        fids = (mesh.nodes_mm[fid_ids] + disp[fid_ids]) @ R.T + t
        coarse_mm = None
        if coarse_embedding is not None:
            coarse_mm = float32_exact((coarse + mesh.interpolate(disp, *coarse_embedding)) @ R.T + t)
        max_mm = float(np.max(np.linalg.norm(fids - sim.fiducials_mm, axis=1)))
        sim.deformations.append(
            Deformation(
                surface_mm=surface,
                fiducials_mm=fids,
                rms_mm=rms,
                max_mm=max_mm,
                n_fixed_nodes=len(load.fixed_nodes),
                rigid_rotation_deg=float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))),
                coarse_mm=coarse_mm,
            )
        )
    return sim


def _arap_deformations(
    sim: SimulatedLiver, liver: LiverMesh, mesh: TetMesh, fid_ids: np.ndarray, n_deformations: int
) -> list[Deformation]:
    """The "arap" family: handle-driven as-rigid-as-possible deformations (arap.py), FEM-family magnitudes."""
    from liver_p2p_reg.phantom.arap import arap_deformation, random_handle_case

    ids, weights = mesh.embed(liver.vertices_mm)
    coarse = sim.coarse_vertices_mm
    coarse_embedding = mesh.embed(coarse) if coarse is not None else None
    out = []
    for d in range(n_deformations):
        # Own streams ([seed, 5, d]): the FEM family's ([seed, 2, d]) stay as they are.
        case = random_handle_case(mesh, np.random.default_rng([sim.liver_id, 5, d]))
        aligned, rms, angle = arap_deformation(mesh, case, fid_ids)
        disp = aligned - mesh.nodes_mm
        fids = aligned[fid_ids]
        coarse_mm = None
        if coarse_embedding is not None:
            coarse_mm = float32_exact(coarse + mesh.interpolate(disp, *coarse_embedding))
        out.append(
            Deformation(
                surface_mm=float32_exact(liver.vertices_mm + mesh.interpolate(disp, ids, weights)),
                fiducials_mm=fids,
                rms_mm=rms,
                max_mm=float(np.max(np.linalg.norm(fids - sim.fiducials_mm, axis=1))),
                n_fixed_nodes=len(case.fixed_nodes),
                rigid_rotation_deg=angle,
                coarse_mm=coarse_mm,
            )
        )
    return out
