"""The second deformation family (ARAP with handles): right magnitude, deterministic, and not linear elasticity."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.sparse.linalg import spsolve
from skfem import condense

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom.anatomy import make_liver
from liver_p2p_reg.phantom.arap import ArapSolver, arap_deformation, random_handle_case
from liver_p2p_reg.phantom.simulate import select_fiducials, simulate_liver
from liver_p2p_reg.registration.mechanics.fem import assemble, calibrate, random_load_case, solve_displacement
from liver_p2p_reg.registration.mechanics.tetmesh import build_tetmesh


@pytest.fixture(scope="module")
def mesh_and_fiducials():
    mesh = build_tetmesh(make_liver(7), target_tets=2500)
    return mesh, select_fiducials(mesh, 7)


def linear_elastic_interior(mesh, disp: np.ndarray) -> np.ndarray:
    """Linear FEM's best account of a deformation: the interior it gives for exactly that surface displacement."""
    system = assemble(mesh)
    dofs = system.nodal_dofs
    x = np.zeros(system.stiffness.shape[0])
    for axis in range(3):
        x[dofs[axis]] = disp[:, axis]
    A, b, _, free = condense(system.stiffness, np.zeros_like(x), x=x, D=dofs[:, mesh.boundary].ravel())
    x[free] = spsolve(A.tocsc(), b)
    return np.stack([x[dofs[axis]] for axis in range(3)], axis=1)


def relative_misfit(mesh, disp: np.ndarray) -> float:
    inside = ~mesh.boundary
    fit = linear_elastic_interior(mesh, disp)
    return float(np.linalg.norm(fit[inside] - disp[inside]) / np.linalg.norm(disp[inside]))


def test_linear_fem_does_not_reproduce_the_arap_family(mesh_and_fiducials) -> None:
    mesh, fid = mesh_and_fiducials
    arap, fem = [], []
    for seed in range(3):
        rng = np.random.default_rng([seed, 9])
        aligned, _, _ = arap_deformation(mesh, random_handle_case(mesh, rng), fid)
        arap.append(relative_misfit(mesh, aligned - mesh.nodes_mm))
        load = random_load_case(mesh, rng)
        unit = solve_displacement(assemble(mesh), load, mesh.nodes_mm)
        scale, R, t, _ = calibrate(mesh.nodes_mm, unit, fid, load.target_rms_mm)
        fem.append(relative_misfit(mesh, (mesh.nodes_mm + scale * unit) @ R.T + t - mesh.nodes_mm))
    # the FEM family's own interior follows from its surface (a few % from the rigid re-alignment);
    # the ARAP family's interior is a different body: linear elasticity misses a large share of it
    assert max(fem) < 0.05, fem
    assert min(arap) > 0.2, arap


def test_magnitude_matches_the_target_and_is_deterministic(mesh_and_fiducials) -> None:
    mesh, fid = mesh_and_fiducials
    case = random_handle_case(mesh, np.random.default_rng(4))
    first, rms, angle = arap_deformation(mesh, case, fid)
    assert rms == pytest.approx(case.target_rms_mm, rel=0.011)
    again, _, _ = arap_deformation(mesh, random_handle_case(mesh, np.random.default_rng(4)), fid)
    assert again.tobytes() == first.tobytes()
    assert 0.0 <= angle < 30.0


def test_no_handle_motion_is_no_deformation_and_a_rigid_one_is_rigid(mesh_and_fiducials) -> None:
    mesh, _ = mesh_and_fiducials
    constrained = np.flatnonzero(mesh.boundary)[::7]
    solver = ArapSolver(mesh.nodes_mm, mesh.tets, constrained)
    rest = solver.solve(mesh.nodes_mm[solver.constrained])
    np.testing.assert_allclose(rest, mesh.nodes_mm, atol=1e-8)
    # a rigid motion of every handle: ARAP's fixed point is the moved body; 12 steps from rest come close
    shift = np.array([5.0, -3.0, 2.0])
    shifted = solver.solve(mesh.nodes_mm[solver.constrained] + shift)
    assert np.linalg.norm(shifted - (mesh.nodes_mm + shift), axis=1).max() < 0.01 * np.linalg.norm(shift)
    c, s = np.cos(0.2), np.sin(0.2)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    rigid = mesh.nodes_mm @ R.T
    moved = solver.solve(rigid[solver.constrained])
    motion = np.linalg.norm(rigid - mesh.nodes_mm, axis=1).max()
    assert np.linalg.norm(moved - rigid, axis=1).max() < 0.02 * motion


def test_simulate_liver_makes_either_family_and_refuses_others() -> None:
    fem = simulate_liver(11, 1, target_tets=1500)
    arap = simulate_liver(11, 1, target_tets=1500, family="arap")
    assert np.array_equal(fem.fiducials_mm, arap.fiducials_mm)  # the same liver, other deformations
    assert arap.deformations[0].surface_mm.shape == fem.deformations[0].surface_mm.shape
    assert not np.allclose(arap.deformations[0].fiducials_mm, fem.deformations[0].fiducials_mm, atol=0.1)
    with pytest.raises(InputError, match="unknown deformation family"):
        simulate_liver(11, 1, target_tets=1500, family="kelvinlet")


def test_a_dataset_of_the_second_family_reaches_the_low_bins(tmp_path) -> None:
    from liver_p2p_reg.bench.cases import BIN_LABELS, visibility_bin
    from liver_p2p_reg.phantom.casefile import read_case
    from liver_p2p_reg.phantom.dataset import DatasetSpec, generate_dataset, spec_record
    from liver_p2p_reg.phantom.manifest import read_manifest

    bins = [[0.05, 0.1], [0.1, 0.15], [0.15, 0.2]]
    spec = DatasetSpec(
        livers=1, deformations=1, targets=3, seed=7, target_tets=1500, visibility_bins=bins, family="arap"
    )
    rows = read_manifest(generate_dataset(tmp_path, spec, progress=False).parent)
    labels = sorted(BIN_LABELS[visibility_bin(read_case(tmp_path / r["file"])["visibility"])] for r in rows)
    assert labels == ["[0.05,0.10)", "[0.10,0.15)", "[0.15,0.20)"]
    assert json.loads((tmp_path / "dataset.json").read_text())["family"] == "arap"
    # a set made before families existed stores no `family`: its stored spec still matches
    assert "family" not in spec_record(DatasetSpec(livers=1, deformations=1, targets=3))
    with pytest.raises(InputError, match="--family"):
        DatasetSpec(livers=1, deformations=1, targets=3, family="linear").validate()


def test_v2_sets_exist_in_both_families_with_enough_low_visibility_poses() -> None:
    from liver_p2p_reg.phantom.realsets import REAL_SETS
    from liver_p2p_reg.phantom.testset import TESTSETS

    for split in ("val", "test"):
        for crop in ("", "-camera"):
            fem, arap = REAL_SETS[f"real-{split}{crop}-v2"], REAL_SETS[f"real-{split}{crop}-v2-arap"]
            assert (fem.family, arap.family) == ("fem", "arap") and fem.random_bins == arap.random_bins
            for lo in (0.05, 0.1, 0.15, 0.2):  # 8 livers x 4 deformations x crops per bin >= 128
                per_deformation = sum(b[0] == lo for b in fem.random_bins + fem.camera_bins)
                assert 8 * fem.deformations * per_deformation >= 128, (split, crop, lo)
            assert TESTSETS[f"insilico-{split}{crop}-v2-arap"].family == "arap"
