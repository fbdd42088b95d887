"""The surface search: poses anchored on the preop surface, scored on its distance field, screened beside the
default's other candidates on small views."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from synthetic_cases import partial_case

from liver_p2p_reg import Config, InputError, Registrar
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.registration.hypotheses import screen_candidates
from liver_p2p_reg.registration.preprocess import preprocess_pair, residual_norm
from liver_p2p_reg.registration.refine import refine_poses, rotation_about
from liver_p2p_reg.registration.surface_search import (
    KEEP,
    SEARCH_MARGIN,
    TRUNCATE_NORM,
    aligning_rotations,
    build_search_model,
    search_poses,
)

METHOD = "learned-p2p-icp"


@pytest.fixture(scope="module")
def small():
    """A 12 % crop of the blob, moved: (source, target, T_true, fiducials)."""
    return partial_case(np.random.default_rng(11), share=0.12)


def _true_norm(prep, T: np.ndarray) -> np.ndarray:
    """The true pose in the pair's normalized frames."""
    s, cs, ct = prep.source_norm.scale_mm, prep.source_norm.centroid_mm, prep.target_norm.centroid_mm
    right = np.eye(4)
    right[:3, :3], right[:3, 3] = T[:3, :3], (T[:3, :3] @ cs + T[:3, 3] - ct) / s
    return right


def test_aligning_rotations_are_rotations_onto_the_vector() -> None:
    rng = np.random.default_rng(0)
    to = rng.normal(size=3)
    to /= np.linalg.norm(to)
    vectors = rng.normal(size=(50, 3))
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
    vectors[0], vectors[1] = -to, to  # the two special cases: opposite and equal
    R = aligning_rotations(vectors, to)
    assert np.allclose(np.einsum("nij,nj->ni", R, vectors), to, atol=1e-9)
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9) and np.allclose(np.linalg.det(R), 1.0)
    assert np.allclose(R[1], np.eye(3))
    axis = np.array([0.0, 0.0, 1.0])
    assert np.allclose(rotation_about(axis, np.pi / 2) @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])


def test_distance_field_is_zero_on_the_surface_and_truncated_away_from_it(small) -> None:
    prep = preprocess_pair(small[0], small[1], Config())
    model = build_search_model(prep.source_full, prep.source)
    cells = np.floor((prep.source_full - model.lower) / 0.025 + 0.5).astype(int)
    flat = (cells[:, 0] * model.shape[1] + cells[:, 1]) * model.shape[2] + cells[:, 2]
    assert np.all(model.distance[flat] == 0) and model.distance.max() == pytest.approx(TRUNCATE_NORM)
    assert len(model.anchors) >= 50 and all(np.allclose(np.linalg.norm(n, axis=1), 1.0) for n in model.normals)


def test_a_searched_pose_reaches_the_true_basin_without_any_match(small) -> None:
    source, target, T, fid_s, fid_t = small
    config = Config()
    prep = preprocess_pair(source, target, config)
    poses = search_poses(prep, build_search_model(prep.source_full, prep.source))
    assert 1 < len(poses) <= KEEP
    again = search_poses(prep, build_search_model(prep.source_full, prep.source))
    assert all(a.tobytes() == b.tobytes() for a, b in zip(poses, again, strict=True))  # deterministic
    moved = refine_poses(poses, prep, config, {}, max_points=400, max_iterations=15)
    best = moved[int(np.argmin([residual_norm(P, prep) for P in moved]))]
    truth = _true_norm(prep, T)
    # the lowest residual after the short ICP is the true pose (a rotation within ~3 deg, 0.02 normalized)
    assert np.linalg.norm(best[:3, :3] - truth[:3, :3]) < 0.08 and np.linalg.norm(best[:3, 3] - truth[:3, 3]) < 0.02


def test_a_searched_pose_must_fit_clearly_better(small) -> None:
    source, target, T, _, _ = small
    config = Config(refine_candidates=1)
    prep = preprocess_pair(source, target, config)
    right = _true_norm(prep, T)
    wrong = right @ np.diag([-1.0, -1.0, 1.0, 1.0])  # 180 deg about z: ICP cannot fix it
    nudge = np.eye(4)
    nudge[:3, :3], nudge[:3, 3] = rotation_about(np.array([0.0, 0.6, 0.8]), 0.1), [0.06, 0.0, 0.0]
    near = right @ nudge  # ~6 deg and 0.06 off: not a near-duplicate, converges where `right` does
    # a P2P candidate in the true basin keeps the choice against an equally good searched pose (the margin) ...
    chosen, tried = screen_candidates([near, wrong, right], [0, 2], prep, config, {}, searched=frozenset({2}))
    assert [i for i, *_ in tried] == [0, 2] and chosen == 0
    assert tried[1][2] > SEARCH_MARGIN * tried[0][2]  # (the two residuals are nearly equal)
    # ... and a searched pose in the true basin wins over a P2P candidate in a wrong one, screened beyond
    # refine_candidates like RANSAC's pose
    chosen, tried = screen_candidates([wrong, near, right], [0, 2, 1], prep, config, {}, searched=frozenset({2}))
    assert [i for i, *_ in tried] == [0, 2] and chosen == 2


def test_the_default_screens_searched_poses_on_small_views_only(small) -> None:
    source, target, T, fid_s, fid_t = small
    larger = partial_case(np.random.default_rng(11), share=0.35)
    config = Config(k=2, surface_search_visibility=0.2)
    for view, below in ((small, True), (larger, False)):
        result = Registrar(config).register(view[0], view[1], method=METHOD)
        names = [c.name for c in result.candidates]
        assert (result.visibility < 0.2) is below and ("search" in result.runtime_ms) is below
        searched = [n for n in names if n.startswith("surface-search-")]
        assert searched == ([f"surface-search-{k}" for k in range(len(searched))] if below else [])
        assert (1 < len(searched) <= KEEP) is below
    off = Registrar(Config(k=2)).register(source, target, method=METHOD)
    assert Config().surface_search_visibility == 0.0 and "search" not in off.runtime_ms
    on = Registrar(config).register(source, target, method=METHOD, source_fiducials_mm=fid_s, target_fiducials_mm=fid_t)
    assert on.rms_tre_mm < 3.0 and any(c.name.startswith("surface-search") for c in on.screened)
    twice = Registrar(config).register(source, target, method=METHOD)
    assert (
        twice.T_target_source.tobytes()
        == Registrar(config).register(source, target, method=METHOD).T_target_source.tobytes()
    )
    assert np.allclose(transform_points(on.T_target_source, fid_s), fid_t, atol=5.0)


def test_the_searchs_pose_answers_where_p2p_and_ransac_have_none(small) -> None:
    from liver_p2p_reg.errors import RegistrationError

    source, target, _, fid_s, fid_t = small
    # no dual-softmax confidence reaches 1: every P2P candidate fails; no RANSAC candidate either
    config = Config(k=2, confidence_threshold=1.0, ransac_candidate_visibility=0.0)
    with pytest.raises(RegistrationError, match="no candidate"):
        Registrar(config).register(source, target, method=METHOD)
    result = Registrar(config.replace(surface_search_visibility=1.0)).register(
        source, target, method=METHOD, source_fiducials_mm=fid_s, target_fiducials_mm=fid_t
    )
    assert result.candidates[result.chosen].name.startswith("surface-search-") and result.rms_tre_mm < 3.0


def test_other_methods_never_search(small) -> None:
    result = Registrar(Config(k=2, surface_search_visibility=1.0)).register(small[0], small[1], method="fpfh-p2p-icp")
    assert "search" not in result.runtime_ms
    assert not any(c.name.startswith("surface-search") for c in result.candidates)


def test_warm_up_builds_the_search_model(small) -> None:
    for threshold, built in ((0.2, True), (0.0, False)):
        registrar = Registrar(Config(k=2, surface_search_visibility=threshold))
        registrar.warm_up(small[0], METHOD)
        assert any(key.startswith("surface-search:") for key in registrar.cache) is built


@pytest.mark.parametrize("value", [-0.1, 1.5, float("nan")])
def test_surface_search_visibility_out_of_range_is_refused(value: float) -> None:
    with pytest.raises(InputError, match="surface_search_visibility must be in"):
        Config(surface_search_visibility=value).validate()


def test_a_calibration_made_before_the_setting_holds_for_the_search_off_only() -> None:
    import json

    from liver_p2p_reg.registration.error_calibration import (
        BUNDLED_CALIBRATION,
        calibration_from_dict,
        calibration_note,
        read_calibration,
    )

    bundled = read_calibration()  # records the search off
    assert bundled.pose["surface_search_visibility"] == 0.0
    assert calibration_note(bundled, METHOD, Config()) == ""
    raw = json.loads(Path(BUNDLED_CALIBRATION).read_text())
    del raw["pose"]["surface_search_visibility"]  # as a file made before the setting existed
    older = calibration_from_dict(raw)
    assert calibration_note(older, METHOD, Config(surface_search_visibility=0.0)) == ""
    for calibration in (bundled, older):
        note = calibration_note(calibration, METHOD, Config(surface_search_visibility=0.1))
        assert "surface_search_visibility" in note and "not known" in note


def test_a_tiny_threshold_still_warms_the_rest() -> None:
    source = partial_case(np.random.default_rng(11), share=0.12)[0]
    registrar = Registrar(Config(k=2, surface_search_visibility=0.001))  # a cap of 0.05 % of the points
    registrar.warm_up(source, METHOD)
    assert any(key.startswith("icp-source-index:") for key in registrar.cache)  # the cap was registered
