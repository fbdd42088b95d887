"""Tetrahedral mesh, FEM loads and deformations: exact embedding, equilibrium, statistics, fiducials."""

from __future__ import annotations

import numpy as np
import pytest

from liver_p2p_reg.phantom.anatomy import make_liver
from liver_p2p_reg.phantom.simulate import simulate_liver
from liver_p2p_reg.registration.mechanics.fem import RMS_RANGE_MM, assemble, random_load_case, solve_displacement
from liver_p2p_reg.registration.mechanics.surface import winding_number
from liver_p2p_reg.registration.mechanics.tetmesh import build_tetmesh
from liver_p2p_reg.registration.procrustes import rigid_fit_np as procrustes


def test_embedding_interpolates_linear_fields_exactly() -> None:
    liver = make_liver(3)
    mesh = build_tetmesh(liver, target_tets=2000)
    A = np.array([[0.01, 0.02, -0.03], [0.0, 0.05, 0.01], [0.02, -0.01, 0.0]])
    field = mesh.nodes_mm @ A.T + np.array([1.0, 2.0, 3.0])
    ids, w = mesh.embed(liver.vertices_mm)
    assert np.allclose(w.sum(axis=1), 1.0) and np.all(w >= -1e-12)
    expected = liver.vertices_mm @ A.T + np.array([1.0, 2.0, 3.0])
    assert np.allclose(mesh.interpolate(field, ids, w), expected, atol=1e-9)


def test_simulated_deformations_are_in_range_and_rigid_free() -> None:
    sim = simulate_liver(11, 4, target_tets=3000)
    assert len(sim.fiducials_mm) >= 100
    # Fiducials are volumetric vertices strictly inside the undeformed surface.
    assert np.all(winding_number(sim.vertices_mm, sim.triangles, sim.fiducials_mm) > 0.99)
    for d in sim.deformations:
        assert d.surface_mm.shape == sim.vertices_mm.shape
        assert d.fiducials_mm.shape == sim.fiducials_mm.shape
        disp = np.linalg.norm(d.fiducials_mm - sim.fiducials_mm, axis=1)
        assert RMS_RANGE_MM[0] - 0.05 <= d.rms_mm <= RMS_RANGE_MM[1] + 0.05
        assert d.rms_mm == pytest.approx(np.sqrt(np.mean(disp**2)), rel=1e-6)
        assert d.max_mm == pytest.approx(disp.max())
        assert d.max_mm < 60.0
        assert d.rigid_rotation_deg < 12.0  # small rotations: the linear model is valid
        # The deformed surface moved, and little rigid motion is left (Procrustes used all
        # volumetric vertices; the fiducials are a subset, so allow a small residual rotation).
        assert np.abs(d.surface_mm - sim.vertices_mm).max() > 0.3
        R, t = procrustes(d.fiducials_mm, sim.fiducials_mm)
        assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 3.0
    rms = [d.rms_mm for d in sim.deformations]
    assert 0.5 < np.mean(rms) < 8.0


def test_loads_are_self_equilibrated_and_supports_hold() -> None:
    mesh = build_tetmesh(make_liver(5), target_tets=2000)
    load = random_load_case(mesh, np.random.default_rng(0))
    scale = np.abs(load.forces).sum()
    assert np.abs(load.forces.sum(axis=0)).max() < 1e-9 * scale
    torque = np.cross(mesh.nodes_mm - mesh.nodes_mm.mean(axis=0), load.forces).sum(axis=0)
    assert np.abs(torque).max() < 1e-7 * scale * 100
    u = solve_displacement(assemble(mesh), load, mesh.nodes_mm)
    assert np.abs(u).max() > 0
    # The support patch only moves rigidly (the infinitesimal rigid part was subtracted afterwards).
    from liver_p2p_reg.registration.mechanics.fem import remove_infinitesimal_rigid

    patch = mesh.nodes_mm[load.fixed_nodes]
    assert np.abs(remove_infinitesimal_rigid(patch, u[load.fixed_nodes])).max() < 1e-9 * np.abs(u).max()
    assert np.all(mesh.boundary[load.fixed_nodes])
