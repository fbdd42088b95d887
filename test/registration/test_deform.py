"""The non-rigid stage: a known FEM deformation recovered, no deformation left alone, degenerate inputs refused."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from synthetic_cases import blob_mm, partial_case

from liver_p2p_reg import Config, Registrar
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom.simulate import simulate_liver
from liver_p2p_reg.registration import registrar as registrar_module
from liver_p2p_reg.registration.deform import deform_result
from liver_p2p_reg.registration.deform_fit import fit_deformation
from liver_p2p_reg.registration.mechanics.modes import _lumped_mass, _rigid_modes, build_elastic_model
from liver_p2p_reg.registration.mechanics.solid import closed_solid
from liver_p2p_reg.result import RegistrationResult

# A small, well-resolved model: the fit is exact arithmetic on a few thousand unknowns, fast on CPU.
FIT = dict(deform=True, deform_modes=96, deform_regularization=0.001, deform_iterations=30, deform_min_gain=0.0)


@pytest.fixture(scope="module")
def fem_liver():
    """A procedural liver and one linear-FEM deformation of it (the generator's own model)."""
    return simulate_liver(1, 1, target_tets=3000)


def rigid_result(residual_mm: float = 1.0, ok: bool = True) -> RegistrationResult:
    return RegistrationResult(T_target_source=np.eye(4), method="test", residual_mm=residual_mm, ok=ok)


def interior_rms(points: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((points - truth) ** 2, axis=1))))


def test_known_fem_deformation_is_recovered_at_interior_points(fem_liver):
    sim, d = fem_liver, fem_liver.deformations[0]
    out = deform_result(rigid_result(), sim.vertices_mm, d.surface_mm, Config(**FIT), {}, sim.triangles)
    assert out.applied, out.reason
    error = interior_rms(out.deformed_position_mm(sim.fiducials_mm), d.fiducials_mm)
    applied = interior_rms(sim.fiducials_mm, d.fiducials_mm)
    assert applied > 1.0  # a real deformation to recover
    assert error <= 0.3 * applied, (error, applied)
    assert out.residual_after_mm < out.residual_before_mm


def test_an_undeformed_view_gives_a_near_zero_displacement(fem_liver):
    sim = fem_liver
    rng = np.random.default_rng(0)
    view = sim.vertices_mm[sim.vertices_mm[:, 0] > np.median(sim.vertices_mm[:, 0])]
    view = view + rng.uniform(-0.5, 0.5, view.shape)  # sensor noise, no deformation
    out = deform_result(rigid_result(), sim.vertices_mm, view, Config(**FIT), {}, sim.triangles)
    assert out.rms_displacement_mm < 0.3, out
    moved = out.deformed_position_mm(sim.fiducials_mm)
    assert interior_rms(moved, sim.fiducials_mm) < 0.5


@pytest.mark.parametrize(
    "case, reason",
    [
        ("few_points", "too little overlap"),
        ("gross_pose", "a gross pose"),
        ("failed", "the rigid registration failed"),
        ("open_surface", "no elastic model"),
    ],
)
def test_degenerate_inputs_return_the_rigid_result_with_the_reason(fem_liver, case, reason):
    sim = fem_liver
    source, triangles, view, result = sim.vertices_mm, sim.triangles, sim.deformations[0].surface_mm, rigid_result()
    if case == "few_points":
        view = view[:150]
    elif case == "gross_pose":
        result = rigid_result(residual_mm=40.0)
    elif case == "failed":
        result = rigid_result(ok=False)
    else:  # a cap of the surface, points only: it encloses nothing
        source, triangles = source[source[:, 2] > np.percentile(source[:, 2], 70)], None
    out = deform_result(result, source, view, Config(**FIT), {}, triangles)
    assert not out.applied and reason in out.reason
    assert np.array_equal(out.T_target_source, result.T_target_source)
    assert np.array_equal(out.deformed_position_mm(sim.fiducials_mm), sim.fiducials_mm)  # identity pose here
    assert "\n" not in out.reason


def test_points_only_solid_matches_the_mesh_solid(fem_liver):
    sim = fem_liver
    from liver_p2p_reg.registration.mechanics.surface import mesh_volume_mm3

    exact = mesh_volume_mm3(sim.vertices_mm, sim.triangles)
    for triangles in (sim.triangles, None):
        solid = closed_solid(sim.vertices_mm, triangles)
        assert abs(solid.volume_mm3 - exact) < 0.12 * exact  # voxel shell: a slightly inflated solid
        assert (solid.implicit_mm(sim.fiducials_mm) < 0).mean() > 0.99  # the interior is inside


def test_modes_carry_no_rigid_motion_and_are_ordered_by_stiffness():
    source = blob_mm(np.random.default_rng(3))
    normals = source - source.mean(axis=0)
    model = build_elastic_model(source, normals / np.linalg.norm(normals, axis=1, keepdims=True), n_modes=12)
    rigid = _rigid_modes(model.mesh.nodes_mm).reshape(6, -1)
    modes = model.modes_mm.reshape(model.n_modes, -1)
    w = np.repeat(_lumped_mass(model.mesh), 3)  # orthogonal in the mass (volume) inner product
    cosine = np.abs((rigid * w) @ modes.T) / np.outer(np.sqrt((rigid**2 * w).sum(1)), np.sqrt((modes**2 * w).sum(1)))
    assert cosine.max() < 1e-8
    assert model.stiffness_ratio[0] == 1.0 and np.all(np.diff(model.stiffness_ratio) >= -1e-9)


def test_registrar_runs_the_stage_and_the_same_input_gives_bitwise_the_same_output():
    source, target, T, fid_s, fid_t = partial_case(np.random.default_rng(5))
    config = Config(method="fpfh-ransac-icp", deform=True, deform_modes=12, deform_target_tets=1500)
    runs = [
        Registrar(config).register(source, target, source_fiducials_mm=fid_s, target_fiducials_mm=fid_t)
        for _ in range(2)
    ]
    a, b = (r.deformation for r in runs)
    assert a is not None and a.reason == b.reason and a.applied == b.applied
    assert np.array_equal(a.T_target_source, b.T_target_source)
    assert np.array_equal(a.deformed_position_mm(fid_s), b.deformed_position_mm(fid_s))
    assert runs[0].deformed_rms_tre_mm == runs[1].deformed_rms_tre_mm
    block = runs[0].to_json_dict()["deformation"]
    assert block["applied"] == a.applied and block["n_modes"] == 12 and "residual_after_mm" in block
    # an undeformed rigid crop: the stage may refine but must not move the interior by more than noise
    assert (runs[0].deformed_rms_tre_mm is None) == (not a.applied)  # reported only where it moved something
    assert (runs[0].deformed_rms_tre_mm if a.applied else runs[0].rms_tre_mm) < runs[0].rms_tre_mm + 1.0


def test_bad_triangles_are_one_line_errors():
    source, target, _, _, _ = partial_case(np.random.default_rng(6))
    registrar = Registrar(Config(method="fpfh-ransac-icp"))
    result = registrar.register(source, target)
    with pytest.raises(InputError, match="source has 15000 points"):
        registrar.deform(result, source, target, np.array([[0, 1, 15000]]))
    with pytest.raises(InputError, match=r"\(F, 3\) integer array"):
        registrar.deform(result, source, target, np.array([[0.0, 1.0, 2.0]]))


def test_the_held_out_check_passes_a_real_deformation_and_refuses_fitted_noise(fem_liver):
    sim, d = fem_liver, fem_liver.deformations[0]
    check = Config(**FIT, deform_holdout_check=True, deform_min_holdout_gain=0.05)
    real = deform_result(rigid_result(), sim.vertices_mm, d.surface_mm, check, {}, sim.triangles)
    assert real.applied and real.holdout_gain > 0.05, (real.reason, real.holdout_gain)
    rng = np.random.default_rng(0)
    view = sim.vertices_mm[sim.vertices_mm[:, 0] > np.median(sim.vertices_mm[:, 0])]
    noise = deform_result(
        rigid_result(), sim.vertices_mm, view + rng.uniform(-0.5, 0.5, view.shape), check, {}, sim.triangles
    )
    # the residual gate is off (FIT): only the held-out half can refuse a deformation fitted to noise
    assert not noise.applied and "held-out half" in noise.reason and noise.holdout_gain < 0.05, noise.reason
    assert np.array_equal(noise.T_target_source, np.eye(4)) and "\n" not in noise.reason
    assert real.to_json_dict()["holdout_gain"] == round(real.holdout_gain, 4)
    unchecked_config = Config(**FIT, deform_holdout_check=False)
    unchecked = deform_result(rigid_result(), sim.vertices_mm, d.surface_mm, unchecked_config, {}, sim.triangles)
    assert np.isnan(unchecked.holdout_gain) and unchecked.to_json_dict()["holdout_gain"] is None


def test_the_rigid_only_fit_moves_no_mode(fem_liver):
    sim, d = fem_liver, fem_liver.deformations[0]
    model = deform_result(rigid_result(), sim.vertices_mm, d.surface_mm, Config(**FIT), {}, sim.triangles).model
    fit = fit_deformation(model, d.surface_mm, np.eye(4), regularization=0.001, iterations=10, deform=False)
    assert np.array_equal(fit.coefficients_mm, np.zeros(model.n_modes))
    assert fit.residual_after_mm <= fit.residual_before_mm + 1e-9  # the rigid correction alone still helps


def test_a_deformed_bound_is_not_claimed_for_other_gates(fem_liver):
    sim, d = fem_liver, fem_liver.deformations[0]
    rigid = Registrar(Config(method="fpfh-ransac-icp")).register(sim.vertices_mm, d.surface_mm)
    notes = []
    for extra in ({}, {"deform_holdout_check": False}):
        registrar = Registrar(Config(method="fpfh-ransac-icp", deform=True, **extra))
        r = registrar.deform(rigid, sim.vertices_mm, d.surface_mm, sim.triangles)
        assert r.deformation.applied, r.deformation.reason
        notes.append(r.deformed_error_calibration_note)
    # the bundled calibration holds for the default gates, the held-out check on
    assert "calibrated with other" not in notes[0], notes[0]
    # without the check the stage is applied to poses the calibration never saw: its coverage is not claimed
    assert "calibrated with other deform_holdout_check, deform_min_holdout_gain" in notes[1], notes[1]


def test_bad_triangles_are_refused_before_the_rigid_registration(monkeypatch: pytest.MonkeyPatch) -> None:
    source, target, _, _, _ = partial_case(np.random.default_rng(6))
    monkeypatch.setattr(registrar_module, "run_method", lambda *a: pytest.fail("registered before the check"))
    registrar = Registrar(Config(method="fpfh-ransac-icp", deform=True))
    with pytest.raises(InputError, match="source has 15000 points"):
        registrar.register(source, target, source_triangles=np.array([[0, 1, 15000]]))
    with pytest.raises(InputError, match=r"preop mesh: expected an \(N, 3\) array"):
        registrar.register(source, target, source_triangles=np.array([[0, 1, 2]]), mesh_vertices_mm=source[:, :2])


def test_a_non_finite_mesh_vertex_is_dropped_with_its_triangles(fem_liver, caplog: pytest.LogCaptureFixture) -> None:
    sim = fem_liver
    config = Config(deform=True, deform_modes=12, deform_target_tets=1500, deform_min_gain=0.0)
    view = sim.deformations[0].surface_mm
    holed = sim.vertices_mm.copy()
    holed[7] = np.nan
    registrar = Registrar(config)
    with caplog.at_level(logging.WARNING, logger="liver_p2p_reg"):
        # it used to raise "the indices no longer match" here, after the rigid pose was found
        out = registrar.deform(rigid_result(), sim.vertices_mm, view, sim.triangles, mesh_vertices_mm=holed)
    using = int(np.any(sim.triangles == 7, axis=1).sum())
    assert [r.getMessage() for r in caplog.records] == [
        f"preop mesh: dropped 1 of {len(holed)} vertices with NaN/inf coordinates and the {using} of "
        f"{len(sim.triangles)} triangles using them"
    ]
    # the same as the mesh without that vertex and its triangles, re-indexed by hand
    keep = ~np.any(sim.triangles == 7, axis=1)
    by_hand = Registrar(config).deform(
        rigid_result(),
        sim.vertices_mm,
        view,
        np.where(sim.triangles[keep] > 7, sim.triangles[keep] - 1, sim.triangles[keep]),
        mesh_vertices_mm=np.delete(sim.vertices_mm, 7, axis=0),
    )
    assert out.deformation.reason == by_hand.deformation.reason
    assert np.array_equal(out.deformation.T_target_source, by_hand.deformation.T_target_source)
    assert np.array_equal(out.deformation.coefficients_mm, by_hand.deformation.coefficients_mm)


def test_the_deformed_tre_is_reported_only_where_the_stage_was_applied(fem_liver) -> None:
    sim = fem_liver
    registrar = Registrar(Config(deform=True, deform_modes=12, deform_target_tets=1500))
    view, fid_t = sim.deformations[0].surface_mm, sim.deformations[0].fiducials_mm
    failed = registrar.deform(rigid_result(ok=False), sim.vertices_mm, view, sim.triangles, sim.fiducials_mm, fid_t)
    assert not failed.deformation.applied
    assert failed.deformed_rms_tre_mm is None and "deformed_rms_tre_mm" not in failed.to_json_dict()
