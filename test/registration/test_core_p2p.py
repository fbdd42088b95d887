"""The P2P module on synthetic features: recovery, ambiguity resolution, invariance, gradients; its settings."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
import torch

from liver_p2p_reg.config import Config, P2PSection
from liver_p2p_reg.registration.p2p import (
    closest_point_residuals,
    consensus_pose,
    farthest_point_sampling,
    geometric_radii,
    p2p_register,
    robust_refit,
)
from liver_p2p_reg.registration.pipeline import p2p_settings
from liver_p2p_reg.registration.preprocess import voxel_downsample
from liver_p2p_reg.registration.procrustes import weighted_procrustes


def _surface(rng: np.random.Generator, n: int = 12000) -> np.ndarray:
    """An asymmetric lumpy ellipsoid in normalized units, voxelized like the pipeline does."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = 1 + 0.2 * np.sin(3 * d[:, 0] + 1) * np.cos(2 * d[:, 1]) + 0.15 * d[:, 2] ** 3 + 0.1 * d[:, 0] * d[:, 1]
    pts = d * r[:, None] * np.array([1.0, 0.75, 0.55])
    pts /= np.linalg.norm(pts, axis=1).max()
    return voxel_downsample(pts, 0.04)


def _rigid(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q)), rng.uniform(-0.5, 0.5, 3)


def _crop(source: np.ndarray, centre: np.ndarray, share: float) -> np.ndarray:
    """Indices of the `share` of source points nearest to `centre` (a partial view)."""
    order = np.argsort(np.linalg.norm(source - centre, axis=1))
    return np.sort(order[: int(share * len(source))])


def _features(rng: np.random.Generator, n: int, d: int = 16) -> np.ndarray:
    x = rng.normal(size=(n, d))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _noisy(x: np.ndarray, rng: np.random.Generator, sigma: float) -> np.ndarray:
    y = x + sigma * rng.normal(size=x.shape)
    return y / np.linalg.norm(y, axis=1, keepdims=True)


def _settings(**changes: Any) -> P2PSection:
    """Config's P2P section as these tests were written against: every patch row matched, no consensus
    twins (the P2P module's own defaults until Config became their one source); `changes` on top."""
    return P2PSection(**{"max_patch_rows": 0, "consensus_seeds": 0, **changes})


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(a, dtype=torch.float64)


def _moved_crop_with_features(rng: np.random.Generator, axis: int, feature_noise: float) -> tuple:
    """A 30 % crop around the surface's extreme along `axis`, rigidly moved, with noisy copies of the source features."""
    source = _surface(rng)
    crop = _crop(source, source[np.argmax(source[:, axis])], 0.3)
    R_true, t_true = _rigid(rng)
    x_source = _features(rng, len(source))
    x_target = _noisy(x_source[crop], rng, feature_noise)
    return source, source[crop] @ R_true.T + t_true, x_source, x_target, R_true, t_true


def _candidate(out, c: int) -> tuple[np.ndarray, np.ndarray]:
    return out.R[c].detach().numpy(), out.t[c].detach().numpy()


def test_fps_spreads_points(rng: np.random.Generator) -> None:
    pts = _t(_surface(rng))
    idx = farthest_point_sampling(pts, 5)
    assert len(set(idx.tolist())) == 5
    gaps = torch.pdist(pts[idx])
    assert float(gaps.min()) > 0.5  # five nodes on a unit-size surface are far apart


def test_the_pipeline_hands_p2p_the_config_section() -> None:
    config = Config().replace(k=7, max_patch_rows=0)
    assert p2p_settings(config, use_p2p=True) == config.p2p == P2PSection(k=7, max_patch_rows=0)
    # the methods without P2P: no patches, the complete-to-partial candidate alone
    assert p2p_settings(config, use_p2p=False) == dataclasses.replace(config.p2p, k=0)


@pytest.mark.parametrize("max_patch_rows", [0, 100])  # all patch rows, or an even subsample
def test_p2p_recovers_the_transform_on_a_partial_crop(rng: np.random.Generator, max_patch_rows: int) -> None:
    source = _surface(rng)
    crop = _crop(source, source[np.argmax(source[:, 0])], 0.25)
    R_true, t_true = _rigid(rng)
    target = source[crop] @ R_true.T + t_true
    x_source = _features(rng, len(source))
    x_target = _noisy(x_source[crop], rng, 0.05)
    settings = _settings(k=5, max_patch_rows=max_patch_rows)
    out = p2p_register(_t(source), _t(target), _t(x_source), _t(x_target), settings)
    assert len(out.names) == 6 and out.names[0] == "complete-to-partial"
    assert out.ok.all()
    R, t = _candidate(out, out.chosen)
    np.testing.assert_allclose(R, R_true, atol=1e-3)
    np.testing.assert_allclose(t, t_true, atol=1e-3)
    assert float(out.residual[out.chosen]) < 1e-3
    assert out.patch_nodes.shape == (5,) and len(set(out.patch_nodes.tolist())) == 5


def _ambiguous_case(rng: np.random.Generator):
    """Target = crop A; a second region B carries copies of the target's features.

    B's copies are exact while A's own features are noisy, so whole-source matching prefers
    B and the complete-to-partial candidate is pulled to the wrong place.
    """
    source = _surface(rng)
    a_centre = source[np.argmax(source[:, 0])]
    b_centre = source[np.argmin(source[:, 0])]
    crop_a = _crop(source, a_centre, 0.2)
    region_b = _crop(source, b_centre, 0.2)
    R_true, t_true = _rigid(rng)
    target = source[crop_a] @ R_true.T + t_true
    x_target = _features(rng, len(crop_a))
    x_source = _features(rng, len(source))
    x_source[crop_a] = _noisy(x_target, rng, 0.1)
    # Give B's points the target features in a spatially scrambled order (B's geometry does
    # not fit the target, so a transform from B matches is wrong).
    twins = rng.permutation(len(crop_a))[: len(region_b)]
    x_source[region_b] = x_target[twins]
    return source, target, x_source, x_target, R_true, t_true


def test_closest_point_rule_resolves_ambiguity(rng: np.random.Generator) -> None:
    source, target, x_source, x_target, R_true, t_true = _ambiguous_case(rng)
    out = p2p_register(_t(source), _t(target), _t(x_source), _t(x_target), _settings(k=5))
    R0, _ = _candidate(out, 0)
    assert np.abs(R0 - R_true).max() > 0.1  # the complete-to-partial candidate is wrong
    assert out.chosen != 0
    R, t = _candidate(out, out.chosen)
    np.testing.assert_allclose(R, R_true, atol=1e-2)
    np.testing.assert_allclose(t, t_true, atol=1e-2)
    assert float(out.residual[out.chosen]) < float(out.residual[0])


def test_inlier_rule_and_no_candidate_proposal_are_selectable(rng: np.random.Generator) -> None:
    source, target, x_source, x_target, R_true, _ = _ambiguous_case(rng)
    args = (_t(source), _t(target), _t(x_source), _t(x_target))
    by_inliers = p2p_register(*args, _settings(k=5, selection="inlier-count"))
    assert by_inliers.chosen == int(torch.argmax(by_inliers.inliers))
    no_proposal = p2p_register(*args, _settings(k=8, candidate_proposal=False))
    nodes = source[no_proposal.patch_nodes.numpy()]
    # FPS over the whole source spreads the nodes over the whole shape, not only the visible part.
    assert np.ptp(nodes[:, 0]) > 1.0
    only_c2p = p2p_register(*args, _settings(k=0))
    assert only_c2p.names == ["complete-to-partial"] and only_c2p.chosen == 0


def test_moving_the_target_moves_the_estimate(rng: np.random.Generator) -> None:
    # noisy enough features that the estimate is not exact
    source, target, x_source, x_target, _, _ = _moved_crop_with_features(rng, axis=1, feature_noise=0.6)
    settings = _settings(k=5)
    out = p2p_register(_t(source), _t(target), _t(x_source), _t(x_target), settings)
    Q, b = _rigid(rng)
    moved = p2p_register(_t(source), _t(target @ Q.T + b), _t(x_source), _t(x_target), settings)
    assert moved.chosen == out.chosen
    R, t = _candidate(out, out.chosen)
    Rm, tm = _candidate(moved, moved.chosen)
    np.testing.assert_allclose(Rm, Q @ R, atol=1e-6)
    np.testing.assert_allclose(tm, Q @ t + b, atol=1e-6)


def test_gradients_reach_the_features(rng: np.random.Generator) -> None:
    source = _surface(rng)
    crop = _crop(source, source[np.argmax(source[:, 2])], 0.3)
    R_true, t_true = _rigid(rng)
    target = source[crop] @ R_true.T + t_true
    x_source = _t(_features(rng, len(source))).requires_grad_(True)
    x_target = _t(_noisy(x_source.detach().numpy()[crop], rng, 0.5)).requires_grad_(True)
    out = p2p_register(_t(source), _t(target), x_source, x_target, _settings(k=5))
    c = out.chosen
    loss = ((out.R[c] - _t(R_true)) ** 2).sum() + ((out.t[c] - _t(t_true)) ** 2).sum()
    loss.backward()
    for x in (x_source, x_target):
        assert x.grad is not None and torch.isfinite(x.grad).all()
        assert float(x.grad.abs().sum()) > 0


@pytest.mark.parametrize("k", [1, 3, 8])
def test_candidate_count_follows_k(rng: np.random.Generator, k: int) -> None:
    source = _surface(rng)
    crop = _crop(source, source[0], 0.3)
    x_source = _features(rng, len(source))
    out = p2p_register(_t(source), _t(source[crop]), _t(x_source), _t(x_source[crop]), _settings(k=k))
    assert len(out.names) == 1 + k and out.R.shape == (1 + k, 3, 3)
    assert out.n_matches.shape == (1 + k,) and int(out.n_matches[out.chosen]) >= 3


def test_robust_refit_recovers_the_pose_despite_outlier_matches(rng: np.random.Generator) -> None:
    source = _surface(rng)[:400]
    R_true, t_true = _rigid(rng)
    target = source @ R_true.T + t_true
    bad = rng.random(len(source)) < 0.4  # 40 % of the matches point somewhere else on the surface
    target[bad] = target[rng.permutation(np.flatnonzero(bad))]
    src, tgt = _t(source)[None], _t(target)[None]
    weights = torch.ones(1, len(source), dtype=torch.float64)
    R0, t0, ok0 = weighted_procrustes(src, tgt, weights)
    assert float((R0[0] - _t(R_true)).abs().max()) > 0.01  # one least-squares fit is pulled off
    R, t = robust_refit(src, tgt, weights, R0, t0, ok0, geometric_radii(0.6, 0.02, 8))
    np.testing.assert_allclose(R[0].numpy(), R_true, atol=1e-9)
    np.testing.assert_allclose(t[0].numpy(), t_true, atol=1e-9)


def test_robust_refit_keeps_the_pose_when_too_few_matches_remain(rng: np.random.Generator) -> None:
    source = _t(_surface(rng)[:50])[None]
    target = source + 1.0  # every match is 1.7 away from the identity pose: none is within the radii
    weights = torch.ones(1, 50, dtype=torch.float64)
    R0, t0 = torch.eye(3, dtype=torch.float64)[None], torch.zeros(1, 3, dtype=torch.float64)
    R, t = robust_refit(source, target, weights, R0, t0, torch.tensor([True]), (0.5, 0.1))
    assert torch.equal(R, R0) and torch.equal(t, t0)


def test_consensus_pose_finds_the_pose_of_a_minority_of_matches(rng: np.random.Generator) -> None:
    source = _surface(rng)[:400]
    R_true, t_true = _rigid(rng)
    target = source @ R_true.T + t_true
    bad = rng.random(len(source)) < 0.6  # most matches point somewhere else on the surface
    target[bad] = target[rng.permutation(np.flatnonzero(bad))]
    src, tgt = _t(source)[None], _t(target)[None]
    weights = torch.ones(1, len(source), dtype=torch.float64)
    R0, _, _ = weighted_procrustes(src, tgt, weights)
    assert float((R0[0] - _t(R_true)).abs().max()) > 0.1  # the plain fit is far off
    R, t, ok = consensus_pose(src, tgt, weights, _settings(consensus_seeds=64))
    assert bool(ok[0])
    # The winning hypothesis is fitted on correct matches only, so it is exact.
    np.testing.assert_allclose(R[0].numpy(), R_true, atol=1e-9)
    np.testing.assert_allclose(t[0].numpy(), t_true, atol=1e-9)


def test_consensus_pose_reports_failure_without_matches(rng: np.random.Generator) -> None:
    source = _t(_surface(rng)[:50])[None]
    _, _, ok = consensus_pose(
        source, source + 1.0, torch.zeros(1, 50, dtype=torch.float64), _settings(consensus_seeds=16)
    )
    assert not bool(ok[0])


def test_consensus_adds_one_candidate_per_plain_one(rng: np.random.Generator) -> None:
    source, target, x_source, x_target, R_true, t_true = _moved_crop_with_features(rng, axis=0, feature_noise=0.3)
    settings = _settings(k=3, consensus_seeds=32)
    out = p2p_register(_t(source), _t(target), _t(x_source), _t(x_target), settings)
    assert out.names[4:] == [f"{name}-consensus" for name in out.names[:4]] and out.R.shape == (8, 3, 3)
    assert torch.equal(out.n_matches[:4], out.n_matches[4:])  # a twin shares its plain candidate's matches
    R, t = _candidate(out, out.chosen)
    assert np.abs(R - R_true).max() < 0.05 and np.abs(t - t_true).max() < 0.05


def test_closest_point_residuals_measure_repeated_poses_once_and_exactly(rng: np.random.Generator) -> None:
    source = _surface(rng)[:300]
    target = source[:120] + 0.01
    poses = [_rigid(rng), (np.eye(3), np.zeros(3))]
    order = [0, 1, 0, 1, 0]  # repeated poses, as when a consensus twin ends where its plain candidate did
    R = _t(np.stack([poses[i][0] for i in order]))
    t = _t(np.stack([poses[i][1] for i in order]))
    ok = torch.tensor([True, True, True, False, True])
    residual = closest_point_residuals(_t(source), _t(target), R, t, ok).numpy()
    for c, i in enumerate(order):
        Ri, ti = poses[i]
        moved = source @ Ri.T + ti
        expected = np.linalg.norm(target[:, None] - moved[None], axis=2).min(axis=1).mean()  # brute force
        assert residual[c] == (pytest.approx(expected, abs=1e-12) if ok[c] else np.inf)
