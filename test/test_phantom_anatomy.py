"""Procedural liver anatomy: watertight surfaces, anatomical sizes, FEM deformation statistics."""

from __future__ import annotations

import numpy as np
import pytest

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom.anatomy import edge_face_counts, make_liver, mesh_volume_mm3, winding_number
from liver_p2p_reg.phantom.fem import RMS_RANGE_MM, procrustes
from liver_p2p_reg.phantom.simulate import simulate_liver
from liver_p2p_reg.phantom.tetmesh import build_tetmesh


@pytest.mark.parametrize("seed", [0, 7, 123456])
def test_liver_is_watertight_and_sized(seed: int) -> None:
    liver = make_liver(seed)
    assert np.all(edge_face_counts(liver.triangles) == 2)
    width, depth, height = liver.extents_mm
    assert 140 <= width <= 220 and 80 <= depth <= 130 and 100 <= height <= 170
    assert mesh_volume_mm3(liver.vertices_mm, liver.triangles) > 0  # outward-facing
    edges = liver.vertices_mm[liver.triangles[:, 0]] - liver.vertices_mm[liver.triangles[:, 1]]
    assert 1.0 < np.linalg.norm(edges, axis=1).mean() < 3.0  # about 2 mm spacing
    # The visceral side rises anteriorly: the anterior half is thinner than the posterior half.
    v = liver.vertices_mm
    front = v[v[:, 1] > np.percentile(v[:, 1], 75)]
    back = v[v[:, 1] < np.percentile(v[:, 1], 25)]
    assert np.ptp(front[:, 2]) < np.ptp(back[:, 2])


def test_livers_differ_by_seed_and_repeat_for_same_seed() -> None:
    a, b, a2 = make_liver(1), make_liver(2), make_liver(1)
    assert np.array_equal(a.vertices_mm, a2.vertices_mm)
    assert a.vertices_mm.shape != b.vertices_mm.shape or not np.allclose(a.vertices_mm, b.vertices_mm)


def test_bad_seed_is_input_error() -> None:
    with pytest.raises(InputError):
        make_liver(-1)


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
        # The deformed surface moved, and little rigid motion is left (Procrustes used all
        # volumetric vertices; the fiducials are a subset, so allow a small residual rotation).
        assert np.abs(d.surface_mm - sim.vertices_mm).max() > 0.3
        R, t = procrustes(d.fiducials_mm, sim.fiducials_mm)
        assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 3.0
    rms = [d.rms_mm for d in sim.deformations]
    assert 0.5 < np.mean(rms) < 8.0
