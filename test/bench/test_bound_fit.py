"""Split-conformal calibration of the error bound on a synthetic collection whose true error law is known."""

from __future__ import annotations

import json

import numpy as np
import pytest

from liver_p2p_reg.bench.bound_data import concat, subset
from liver_p2p_reg.bench.bound_fit import (
    MIN_GROUP,
    VISIBILITY_EDGES,
    calibrate,
    conformal_quantile,
    coverage_at,
    groups_of,
    pose_rival_ratio,
    split_livers,
)
from liver_p2p_reg.bench.bound_markdown import results_page
from liver_p2p_reg.bench.bound_report import BAD_MM, bin_rows, judge, passed_bad, worst_ok_mm
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.error_bound import FEATURES
from liver_p2p_reg.registration.error_calibration import FORMAT, read_calibration


def synthetic_collection(
    seed: int, poses: int = 400, markers: int = 40, interior: int = 10, halves_weight: float = 0.0
) -> dict[str, np.ndarray]:
    """Poses whose marker errors are |N(0, s^2 I)| with s = exp(features . w): a law the fit can find; the first
    `interior` markers of each pose stand in for its interior (where the pose-level bound is taken). The eighth
    feature (log_halves) is drawn from a stream of its own and weighs `halves_weight` in the law."""
    rng = np.random.default_rng(seed)
    w = np.array([0.3, 0.8, 0.4, 0.2, -0.3, 0.3, -0.5, halves_weight])
    vis = rng.uniform(0.05, 0.4, poses)
    feats = np.empty((poses * markers, len(FEATURES)))
    feats[:, 0] = 1.0
    feats[:, 1] = rng.uniform(0, 2, len(feats))
    feats[:, 2] = rng.uniform(0, 4, len(feats))
    feats[:, 3] = np.repeat(rng.uniform(0, 1.5, poses), markers)
    feats[:, 4] = np.repeat(np.log(vis), markers)
    feats[:, 5] = rng.uniform(0, 3, len(feats))
    feats[:, 6] = np.repeat(rng.uniform(0, np.log(4), poses), markers)
    feats[:, 7] = np.random.default_rng(seed + 1000).uniform(0, 2, len(feats))
    scale = np.exp(feats @ w)
    errors = scale * np.linalg.norm(rng.normal(size=(len(feats), 3)), axis=1) / np.sqrt(3)
    per = np.repeat(np.arange(poses), markers)
    rms = np.sqrt(np.bincount(per, errors**2) / markers)
    return {
        "set": np.array(["real-val-v2"] * poses),
        "case_id": np.array([f"c{i}" for i in range(poses)]),
        "noise_mm": np.full(poses, 2.0),
        "count": np.full(poses, markers),
        "errors": errors,
        "features": feats,
        "interior_count": np.full(poses, interior),
        "interior_features": feats.reshape(poses, markers, -1)[:, :interior].reshape(-1, len(FEATURES)),
        "liver_id": rng.integers(0, 8, poses),
        "visibility": vis,
        "method_visibility": vis,
        "rms_mm": rms,
        "ok": np.ones(poses, bool),
        "reasons": np.array([""] * poses),
        "bound_ms": np.full(poses, 5.0),
    }


def _as_calibration(tmp_path, raw):
    path = tmp_path / "cal.json"
    path.write_text(json.dumps({**raw, "method": "learned-p2p-icp", "weights_sha256": ""}))
    return read_calibration(path)


def test_the_bound_covers_its_share_of_fresh_poses(tmp_path):
    cal = _as_calibration(tmp_path, calibrate(synthetic_collection(0), seed=0))
    assert cal.coverages == (0.8, 0.9, 0.95)
    fresh = synthetic_collection(1, poses=1500)
    for coverage in cal.coverages:
        point_bound, pose_bound = coverage_at(fresh, cal, coverage)
        assert abs(np.mean(fresh["errors"] <= point_bound) - coverage) < 0.03
        assert abs(np.mean(fresh["rms_mm"] <= pose_bound) - coverage) < 0.05
    rows = bin_rows(fresh, judge(fresh, cal, 0.9, 10.0))
    assert all(0.85 <= r["coverage"] <= 0.95 for r in rows)


def test_the_calibration_is_the_same_from_the_same_data_and_seed():
    data = synthetic_collection(0)
    first, again = json.dumps(calibrate(data, seed=0)), json.dumps(calibrate(data, seed=0))
    assert first == again
    assert json.loads(first)["format"] == FORMAT
    assert json.dumps(calibrate(data, seed=1)) != first  # another liver split


def test_the_livers_that_fit_never_calibrate():
    fit, cal = split_livers(np.arange(8), seed=0)
    assert len(fit) == len(cal) == 4 and not set(fit) & set(cal)
    ids = np.array([1, 2, 3, 4, 5, 6, 7, 8, 91, 92, 93, 94, 95, 96])
    fit, cal = split_livers(ids, seed=0, sources=np.array(["real"] * 8 + ["insilico"] * 6))
    for source in (set(range(1, 9)), set(range(91, 97))):  # each source split in halves
        assert len(source & set(fit)) == len(source & set(cal)) == len(source) // 2
    with pytest.raises(InputError, match="at least 2 livers"):
        split_livers(np.zeros(5), seed=0)


def test_failed_poses_are_left_out_and_unbounded(tmp_path):
    data = synthetic_collection(0)
    data["ok"][:10] = False
    raw = calibrate(data, seed=0)
    assert raw["left_out_failed_poses"] == 10
    _, pose_bound = coverage_at(data, _as_calibration(tmp_path, raw), 0.9)
    assert np.all(np.isinf(pose_bound[:10])) and np.all(np.isfinite(pose_bound[10:]))


def test_the_conformal_quantile_has_the_finite_sample_correction():
    values = np.arange(1.0, 11.0)  # 10 scores: level 0.9 x (1 + 1/10) = 0.99 -> the largest
    assert conformal_quantile(values, np.ones(10), 0.9, 10) == 10.0
    assert conformal_quantile(values, np.ones(10), 0.5, 10) == 6.0  # 0.55 -> the 6th


def test_a_subset_keeps_each_poses_interior_points_with_it():
    # poses hold different numbers of interior stand-in points (a failed pose none): a subset and a concat keep
    # each pose's own rows (their first feature tells the pose here)
    data = synthetic_collection(0, poses=5, markers=4)
    counts = np.array([3, 0, 2, 5, 1])
    data["interior_count"] = counts
    data["interior_features"] = np.repeat(np.arange(5.0), counts)[:, None] * np.ones((1, len(FEATURES)))
    keep = np.array([True, True, False, True, False])
    part = subset(data, keep)
    assert part["interior_count"].tolist() == [3, 0, 5]
    assert part["interior_features"][:, 0].tolist() == [0, 0, 0, 3, 3, 3, 3, 3]
    both = concat([part, subset(data, ~keep)])
    assert both["interior_features"][:, 0].tolist() == [0, 0, 0, 3, 3, 3, 3, 3, 2, 2, 4]
    assert both["interior_count"].tolist() == [3, 0, 5, 2, 1]


def test_the_page_says_how_far_off_the_poses_it_passed_are(tmp_path):
    cal = _as_calibration(tmp_path, calibrate(synthetic_collection(0), seed=0))
    fresh = synthetic_collection(2, poses=600)
    fresh = subset(fresh, fresh["visibility"] < 0.3)  # the page's range (0.05-0.3)
    warn_mm = 30.0  # lax: some poses >= 10 mm pass
    _, pose_bound = coverage_at(fresh, cal, 0.9)
    ok = pose_bound <= warn_mm
    bad_ok = ok & (fresh["rms_mm"] >= BAD_MM)
    assert 0 < bad_ok.sum() < ok.sum()
    judged = judge(fresh, cal, 0.9, warn_mm)
    passed = passed_bad(fresh, judged)
    assert passed["count"] == bad_ok.sum() and passed["error_max_mm"] == fresh["rms_mm"][ok].max()
    assert passed["bound_max_mm"] == pose_bound[bad_ok].max() and passed["far"] == (fresh["rms_mm"][ok] >= 15).sum()
    assert worst_ok_mm(fresh, judged, np.ones(len(ok), bool)) == fresh["rms_mm"][ok].max()
    page, block = results_page(fresh, cal, 0.9, warn_mm, 0, "cmd")
    assert f"no pose with an OK verdict is more than {fresh['rms_mm'][ok].max():.1f} mm off" in page
    assert f"| {bad_ok.sum()} | {fresh['rms_mm'][ok].max():.1f} mm |" in block
    listed = page.split("## The bad poses with an OK verdict")[1].split("##")[0]
    assert listed.count("| real-val-v2 | c") == bad_ok.sum()  # one row each, the worst first
    assert f"| {fresh['rms_mm'][ok].max():.1f} mm |" in listed.splitlines()[4]
    fresh["reasons"][:] = "residual"  # every pose warned: no OK pose, said so
    page, _ = results_page(fresh, cal, 0.9, warn_mm, 0, "cmd")
    assert "No pose >= 10 mm got an OK verdict; the worst OK pose is - off." in page


def test_rival_classes_split_the_quantiles_as_the_product_groups_a_pose(tmp_path):
    data = synthetic_collection(0, poses=800)
    raw = calibrate(data, seed=0, rival_edges=(1.5,))
    assert raw["rival_ratio_edges"] == [1.5] and len(raw["pose_quantiles"]) == 2 * (len(VISIBILITY_EDGES) + 1)
    cal = _as_calibration(tmp_path, raw)
    ratio = pose_rival_ratio(data)
    assert np.allclose(ratio, np.exp(data["features"][::40, 6]))  # the pose's own feature, read back
    groups = groups_of(data, cal.visibility_edges, cal.rival_ratio_edges)
    want = [cal.group(v, r) for v, r in zip(data["method_visibility"], ratio, strict=True)]
    assert groups.tolist() == want and set(groups.tolist()) >= {0, len(VISIBILITY_EDGES) + 1}
    # a cell with too few calibration poses takes its visibility group's quantiles (both classes together)
    counts = raw["calibration_poses_per_group"]
    plain = calibrate(data, seed=0)
    n_vis = len(VISIBILITY_EDGES) + 1
    for g, n in enumerate(counts):
        if n < MIN_GROUP:
            assert raw["pose_quantiles"][g] == plain["pose_quantiles"][g % n_vis]
    assert any(n >= MIN_GROUP for n in counts[n_vis:])  # some clear cell has its own
    # without rival edges nothing changes: the calibration of before, key for key
    assert "rival_ratio_edges" not in plain and calibrate(data, seed=0, rival_edges=()) == plain
    swapped = calibrate(data, seed=0, swap=True)
    assert (swapped["fit_livers"], swapped["calibration_livers"]) == (plain["calibration_livers"], plain["fit_livers"])


def test_a_calibration_with_unusable_rival_edges_is_one_line(tmp_path):
    raw = calibrate(synthetic_collection(0), seed=0, rival_edges=(1.5,))
    for edges in ([0.5], [1.0], [2.0, 1.5], [float("nan")], [4.0]):
        with pytest.raises(InputError, match=r"rival_ratio_edges must be increasing ratios in \(1, 4\)"):
            _as_calibration(tmp_path, {**raw, "rival_ratio_edges": edges})
    with pytest.raises(InputError, match="quantiles must be 10 groups"):
        _as_calibration(tmp_path, {**raw, "rival_ratio_edges": [1.5], "pose_quantiles": raw["pose_quantiles"][:5]})


def test_the_scale_model_takes_the_half_view_feature_when_asked_and_only_then(tmp_path):
    data = synthetic_collection(0, halves_weight=0.6)
    seven, eight = calibrate(data, seed=0, n_features=7), calibrate(data, seed=0, n_features=8)
    assert seven["features"] == list(FEATURES[:7]) and len(seven["coefficients"]) == 7
    assert eight["features"] == list(FEATURES) and abs(eight["coefficients"][7] - 0.6) < 0.05
    assert len(_as_calibration(tmp_path, eight).coefficients) == 8
    # the law's eighth term is what the seven-feature scale cannot follow: markers where it is large are covered
    # less than their share and those where it is small more; the eight-feature bound covers both alike
    high = data["features"][:, 7] > 1.5
    gaps = []
    for raw in (seven, eight):
        point_bound, _ = coverage_at(data, _as_calibration(tmp_path, raw), 0.9)
        covered = data["errors"] <= point_bound
        gaps.append(np.mean(covered[~high]) - np.mean(covered[high]))
    assert gaps[0] > 0.15 and abs(gaps[1]) < 0.03  # measured: 0.24 and 0.01


def test_the_selection_rules_cross_fitting_judges_every_pose_once_on_the_half_that_did_not_calibrate_it():
    from liver_p2p_reg.bench.bound_select import cross_fitted
    from liver_p2p_reg.config import Config

    data = synthetic_collection(0, halves_weight=1.0, poses=600)
    k = 4.0 / np.median(data["rms_mm"])  # a few poses bad (>= 10 mm), most good
    data["errors"], data["rms_mm"] = data["errors"] * k, data["rms_mm"] * k
    config = Config(method="icp")
    first = cross_fitted(data, config, n_features=8)
    assert first == cross_fitted(data, config, n_features=8)
    assert 0 <= first["bad_ok"] <= int((data["rms_mm"] >= BAD_MM).sum()) and 0 < first["good_warned"] < 1
    # each fold's quantiles come from the other half: every bin's coverage near the 90 % asked, not above it by design
    assert all(0.8 < c < 0.97 for c in first["coverage"].values())
    assert cross_fitted(data, config, n_features=7) != first
