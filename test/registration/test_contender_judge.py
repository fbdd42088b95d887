"""contender_judge_ratio: small views' close contenders refined by the full ICP and judged by the elastic stage."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_cases import rigid

from liver_p2p_reg import Config, InputError, Registrar
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.phantom.simulate import simulate_liver
from liver_p2p_reg.registration.contenders import elastic_keys
from liver_p2p_reg.registration.context import MethodContext
from liver_p2p_reg.registration.deform import fitted_residual_mm
from liver_p2p_reg.registration.methods import run_method

METHOD = "learned-p2p-icp"
# every screened candidate a contender, the judge on any view; a small elastic model (fast on CPU)
JUDGE = dict(
    method=METHOD,
    k=2,
    ransac_candidate_visibility=1.0,
    contender_judge_ratio=100.0,
    deform_modes=12,
    deform_target_tets=1500,
)


@pytest.fixture(scope="module")
def view():
    """(preop vertices, triangles, a small deformed view of them moved by a rigid pose, that pose)."""
    sim = simulate_liver(3, 1, target_tets=1500)
    surface = sim.deformations[0].surface_mm
    centre = surface[np.argmax(surface[:, 0] + surface[:, 2])]
    keep = np.argsort(np.linalg.norm(surface - centre, axis=1))[: int(0.15 * len(surface))]
    T = rigid(np.random.default_rng(3))
    return sim.vertices_mm, sim.triangles, transform_points(T, surface[keep]), T


def _register(view, **settings):
    source, tris, target, _ = view
    return Registrar(Config(**{**JUDGE, **settings})).register(source, target, source_triangles=tris)


def test_the_contenders_are_keyed_and_the_lowest_key_wins(view) -> None:
    result = _register(view)
    keys = [c.judge_key_mm for c in result.screened]
    assert len(result.screened) >= 2 and all(np.isfinite(keys)), keys
    assert "judge" in result.runtime_ms
    winner = result.candidates[result.chosen].name
    assert winner == result.screened[int(np.argmin(keys))].name
    # its pose is the full ICP from the winner's own candidate pose, as the pipeline refines any winner
    source, tris, target, _ = view
    tracked = Registrar(Config(**JUDGE)).register(
        source, target, method="track", initial_T_mm=result.candidates[result.chosen].T_target_source
    )
    assert np.allclose(tracked.T_target_source, result.T_target_source, atol=1e-6)
    assert result.to_json_dict()["screened"][0]["judge_key_mm"] == pytest.approx(keys[0])
    again = _register(view)  # deterministic: the same input gives bitwise the same pose and keys
    assert again.T_target_source.tobytes() == result.T_target_source.tobytes()
    assert [c.judge_key_mm for c in again.screened] == keys


def test_the_judges_choice_is_what_the_keys_say(view) -> None:
    """Any key function decides: one preferring the last contender makes its ICP pose the result."""
    source, _, target, _ = view
    config = Config(**JUDGE)
    plain = run_method(METHOD, source, target, config, MethodContext())
    assert len(plain.screened) >= 2 and "judge" not in plain.runtime_ms  # no key function: no judge
    seen: list[int] = []

    def last_wins(poses_mm, residuals_mm):
        seen.append(len(poses_mm))
        return [float(len(poses_mm) - i) for i in range(len(poses_mm))]

    judged = run_method(METHOD, source, target, config, MethodContext(judge_keys=last_wins))
    assert seen == [len(plain.screened)]  # ratio 100: every screened candidate is a contender
    last = judged.screened[-1].name
    assert judged.candidates[judged.chosen].name == last
    tracked = run_method(
        "track", source, target, config, MethodContext(initial_T_mm=judged.candidates[judged.chosen].T_target_source)
    )
    assert np.allclose(tracked.T_target_source, judged.T_target_source, atol=1e-6)
    assert [c.judge_key_mm for c in judged.screened][-1] == 1.0


@pytest.mark.parametrize("settings", [{"contender_judge_ratio": 0.0}, {"ransac_candidate_visibility": 0.01}])
def test_off_or_on_a_larger_view_nothing_is_judged(view, settings) -> None:
    result = _register(view, **settings)
    plain = _register(
        view, contender_judge_ratio=0.0, ransac_candidate_visibility=settings.get("ransac_candidate_visibility", 1.0)
    )
    assert "judge" not in result.runtime_ms and all(np.isnan(c.judge_key_mm) for c in result.screened)
    assert result.T_target_source.tobytes() == plain.T_target_source.tobytes()


def test_the_stages_residual_explains_a_deformation_and_refuses_what_it_would_not_fit(view) -> None:
    source, tris, target, T = view
    config = Config(**JUDGE)
    cache: dict = {}
    rigid_fit = Registrar(config).register(source, target, method="track", initial_T_mm=T)
    fitted = fitted_residual_mm(rigid_fit.T_target_source, rigid_fit.residual_mm, source, target, config, cache, tris)
    assert fitted is not None and fitted < rigid_fit.residual_mm  # the deformation explains part of the residual
    assert (
        fitted_residual_mm(T, 6.0, source, target, config, cache, tris) is None
    )  # a gross pose: deform_max_residual_mm
    assert fitted_residual_mm(T, 1.0, source, target[:150], config, cache, tris) is None  # < deform_min_points
    keys = elastic_keys(config, cache, source, target, source, tris, None)
    near = rigid_fit.T_target_source.copy()
    near[:3, 3] += 0.01  # within SAME_POSE_MM of the first pose: its fit is shared, not its fallback
    out = keys([rigid_fit.T_target_source, near], [1.0, 9.0])
    assert out == [pytest.approx(fitted), pytest.approx(fitted)]
    far = T.copy()
    far[:3, 3] += 200.0
    assert keys([far], [7.5]) == [7.5]  # the stage does not fit a gross pose: its ICP residual is its key


def test_only_a_method_screening_ransacs_pose_is_judged_and_has_its_surface_checked(view) -> None:
    source, tris, target, T = view
    bad = np.array([[0, 1, len(source) + 5]])  # indexes a vertex the model does not have
    no_ransac = (("fpfh-p2p-icp", {}), ("track", {}), ("learned-p2p-icp", {"ransac_candidate_visibility": 0.0}))
    for method, extra in no_ransac:  # no RANSAC candidate: no judge, no elastic model, no surface check
        registrar = Registrar(Config(**{**JUDGE, "method": method, **extra}))
        result = registrar.register(source, target, initial_T_mm=T, source_triangles=bad)
        assert "judge" not in result.runtime_ms and all(np.isnan(c.judge_key_mm) for c in result.screened)
        assert not any(isinstance(k, str) and k.startswith("elastic:") for k in registrar.cache)
    with pytest.raises(InputError, match="triangles"):  # where the judge runs, a bad surface is refused first
        _register((source, bad, target, T))


def test_with_a_sensor_origin_the_keys_carry_the_free_space_violation(view) -> None:
    source, tris, target, T = view
    centre, patch = source.mean(axis=0), np.linalg.solve(T[:3, :3], (target - T[:3, 3]).T).T.mean(axis=0)
    origin = transform_points(T, (patch + 150.0 * (patch - centre) / np.linalg.norm(patch - centre))[None])[0]
    runs = [
        Registrar(Config(**JUDGE, free_space_weight=w)).register(
            source, target, source_triangles=tris, sensor_origin_mm=origin
        )
        for w in (0.0, 0.5)
    ]
    assert runs[0].free_space == "on" and "judge" in runs[1].runtime_ms
    plain, weighed = ({c.name: c.judge_key_mm for c in r.screened if np.isfinite(c.judge_key_mm)} for r in runs)
    shared = sorted(set(plain) & set(weighed))
    assert shared and all(weighed[n] >= plain[n] - 1e-12 for n in shared)
    assert any(weighed[n] > plain[n] for n in shared)  # a contender the camera's view contradicts pays for it


def test_a_surface_without_a_solid_leaves_the_rigid_keys_and_is_not_rebuilt(view) -> None:
    source, _, target, _ = view
    registrar = Registrar(Config(**JUDGE))
    flat = np.array([[0, 1, 2]])  # one triangle: no closed solid, no elastic model
    result = registrar.register(source, target, source_triangles=flat)
    assert "judge" in result.runtime_ms and result.ok
    failed = [k for k in registrar.cache if isinstance(k, str) and k.startswith("elastic:")]
    assert len(failed) == 1 and isinstance(registrar.cache[failed[0]], InputError)
    kept = registrar.cache[failed[0]]
    again = registrar.register(source, target, source_triangles=flat)
    assert registrar.cache[failed[0]] is kept  # the failed build is remembered, not retried per pose
    assert again.T_target_source.tobytes() == result.T_target_source.tobytes()
    # without a model each contender's key is its full ICP residual: the winner is the lowest of those
    assert (
        result.candidates[result.chosen].name
        == min((c for c in result.screened if np.isfinite(c.judge_key_mm)), key=lambda c: c.judge_key_mm).name
    )


@pytest.mark.parametrize("ratio", [0.5, -1.0, float("inf"), float("nan")])
def test_a_ratio_neither_off_nor_a_finite_factor_is_refused(ratio: float) -> None:
    with pytest.raises(InputError, match="contender_judge_ratio must be 0"):
        Config(contender_judge_ratio=ratio).validate()


def test_warm_up_builds_the_elastic_model_of_the_given_surface(view) -> None:
    source, tris, _, _ = view
    registrar = Registrar(Config(**JUDGE))
    registrar.warm_up(source, source_triangles=tris)
    built = [k for k in registrar.cache if isinstance(k, str) and k.startswith("elastic:")]
    assert len(built) == 1 and "True)" in built[0]  # one model, of the mesh (not rebuilt from the points)
