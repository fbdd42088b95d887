"""The bound's half-view feature (log_halves): a bent view disagrees with itself, and older calibrations ignore it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from synthetic_cases import blob_mm, crop, partial_case, rigid

from liver_p2p_reg import Registrar
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.registration.error_bound import FEATURES, interior_stand_in, pose_evidence
from liver_p2p_reg.registration.error_calibration import BUNDLED_CALIBRATION, error_scale_mm, read_calibration


def _patch(source, share=0.2):
    return source[crop(source, share)[0]]


def _bent(patch, amplitude_mm):
    """The patch bent about its middle: pushed along its normal by amplitude x (u / half-length)^2 along its
    longest axis, as an organ curls under a retractor (no rigid motion absorbs it)."""
    centre = patch.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((patch - centre).T))
    u = (patch - centre) @ axes[:, 2]
    return patch + amplitude_mm * (u / np.abs(u).max())[:, None] ** 2 * axes[:, 0]


def _halves_at_interior(source, view_preop, T, rng):
    target = transform_points(T, view_preop) + rng.uniform(-0.5, 0.5, view_preop.shape)
    evidence = pose_evidence(T, source, target, residual_mm=1.0, visibility=0.2, trim_ratio=0.9)
    return evidence, evidence.halves_mm(interior_stand_in(source))


def test_a_bent_view_moves_its_halves_and_the_interior_far_more_than_a_rigid_one(rng):
    source, T = blob_mm(rng), rigid(rng)
    patch = _patch(source)
    evidence, still = _halves_at_interior(source, patch, T, np.random.default_rng(1))
    _, bent = _halves_at_interior(source, _bent(patch, 8.0), T, np.random.default_rng(1))
    assert len(evidence.half_T) == 4  # two cuts, two halves each
    assert np.sqrt(np.mean(still**2)) < 1.0  # a rigid view's halves stay where the pose is
    assert np.sqrt(np.mean(bent**2)) > 4 * np.sqrt(np.mean(still**2))
    column = evidence.features(interior_stand_in(source))[:, FEATURES.index("log_halves")]
    assert np.array_equal(column, np.log1p(still))


def test_the_half_view_feature_is_the_same_twice(rng):
    source, T = blob_mm(rng), rigid(rng)
    view = _bent(_patch(source), 5.0)
    _, a = _halves_at_interior(source, view, T, np.random.default_rng(3))
    _, b = _halves_at_interior(source, view, T, np.random.default_rng(3))
    assert np.array_equal(a, b) and np.all(np.isfinite(a))


def test_a_view_too_small_to_cut_has_no_halves_and_a_zero_feature(rng):
    source, T = blob_mm(rng), rigid(rng)
    view = _patch(source, 0.0007)  # 10 points: paired (>= 6), but every half has fewer than 12
    evidence, halves = _halves_at_interior(source, view, T, np.random.default_rng(2))
    assert np.all(np.isfinite(evidence.cov)) and evidence.half_T == ()
    assert np.array_equal(halves, np.zeros(len(halves)))


def test_a_calibration_of_the_first_seven_features_never_reads_the_eighth(rng):
    bundled = read_calibration()
    assert len(bundled.coefficients) == 7  # made before log_halves
    feats = rng.normal(size=(50, len(FEATURES)))
    feats[:, 0] = 1.0
    feats[:, 7] = np.nan  # even a non-finite eighth column leaves its bound as it was
    assert np.array_equal(bundled.scale_mm(feats), np.exp(feats[:, :7] @ bundled.coefficients))
    assert np.all(np.isfinite(error_scale_mm(feats, bundled.coefficients)))


@pytest.mark.parametrize(
    "names",
    [
        ["const", "log_rigid", "log_lever", "log_residual", "log_visibility", "log_rival_gap", "log_halves"],
        [],
        [*FEATURES, "log_more"],
    ],
)
def test_a_calibration_whose_features_are_not_a_prefix_of_ours_is_refused(tmp_path, names):
    raw = json.loads(BUNDLED_CALIBRATION.read_text())
    raw["features"], raw["coefficients"] = names, [0.1] * len(names)
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(raw))
    with pytest.raises(InputError, match="features must be the first of"):
        read_calibration(path)


def test_a_registration_bounded_by_a_seven_feature_calibration_never_pays_for_the_halves(rng):
    source, target, _, _, _ = partial_case(rng, share=0.3)
    result = Registrar(method="fpfh-ransac-icp").register(source, target)
    evidence = result.error_model.evidence
    assert np.isfinite(result.error_bound_mm) and "half_T" not in evidence.__dict__  # not made
    assert evidence.features(evidence.interior_mm, 7).shape[1] == 7 and "half_T" not in evidence.__dict__
    full = evidence.features(evidence.interior_mm)  # a collection asks for all eight: made now, once
    assert full.shape[1] == len(FEATURES) and len(evidence.half_T) == 4 and "half_T" in evidence.__dict__
    assert np.array_equal(full[:, :7], evidence.features(evidence.interior_mm, 7))


def test_a_calibration_of_all_eight_features_makes_the_refits_and_bounds_with_them(tmp_path, rng):
    source, target, _, _, _ = partial_case(rng, share=0.3)
    raw = json.loads(BUNDLED_CALIBRATION.read_text())
    raw["features"], raw["coefficients"] = list(FEATURES), [*raw["coefficients"], 0.5]
    path = tmp_path / "eight.json"
    path.write_text(json.dumps(raw))
    seven = Registrar(method="fpfh-ransac-icp").register(source, target)
    eight = Registrar(method="fpfh-ransac-icp", error_calibration_path=str(path)).register(source, target)
    evidence = eight.error_model.evidence
    assert "half_T" in evidence.__dict__ and len(evidence.half_T) == 4  # made for the bound
    h = np.sqrt(np.mean(evidence.halves_mm(evidence.interior_mm) ** 2))
    assert np.isfinite(eight.error_bound_mm) and h > 0
    # the same pose and quantiles: the eighth term widens the scale by exp(0.5 log1p(halves)) at every point
    assert np.array_equal(seven.T_target_source, eight.T_target_source)
    assert eight.error_bound_mm > seven.error_bound_mm
