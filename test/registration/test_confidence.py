"""Pose confidence: the uncertainty of a fit on the visible surface, and rival hypotheses (ambiguity)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from liver_p2p_reg import Config, Registrar
from liver_p2p_reg.registration.confidence import is_ambiguous, pose_uncertainty
from liver_p2p_reg.result import Candidate


def _ellipsoid(n: int = 6000, axes: tuple[float, float, float] = (1.0, 0.6, 0.4)) -> np.ndarray:
    """An ellipsoid shell in normalized-like units."""
    d = np.random.default_rng(0).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * np.asarray(axes)


def _view(source: np.ndarray, centre: np.ndarray, radius: float, noise: float, seed: int = 1) -> np.ndarray:
    """The source points within `radius` of `centre`, each moved by Gaussian noise of `noise`."""
    patch = source[np.linalg.norm(source - centre, axis=1) < radius]
    return patch + np.random.default_rng(seed).normal(scale=noise, size=patch.shape)


def _uncertainty(source: np.ndarray, target: np.ndarray, T: np.ndarray | None = None) -> float:
    return pose_uncertainty(np.eye(4) if T is None else T, source, target, max_corr=0.1, trim_ratio=0.8)


def test_uncertainty_scales_with_the_misfit() -> None:
    source = _ellipsoid()
    tip = np.array([1.0, 0.0, 0.0])
    small, large = (_uncertainty(source, _view(source, tip, 0.5, noise)) for noise in (0.005, 0.02))
    assert 0 < small < large
    assert large / small == pytest.approx(4.0, rel=0.35)  # sigma x GDOP: linear in sigma, same view


def test_a_smooth_view_that_can_slide_is_less_certain_than_a_curved_one() -> None:
    source = _ellipsoid(axes=(1.0, 0.8, 0.15))  # a flat disc with a rounded rim
    # the same amount of noise on the broad face (slides in its plane) and on the rim
    flat = _uncertainty(source, _view(source, np.array([0.0, 0.0, 0.15]), 0.3, 0.01))
    curved = _uncertainty(source, _view(source, np.array([1.0, 0.0, 0.0]), 0.3, 0.01))
    assert flat > 5.0 * curved


def test_uncertainty_does_not_depend_on_the_sensor_frame() -> None:
    source = _ellipsoid()
    target = _view(source, np.array([0.7, 0.3, 0.2]), 0.5, 0.01)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [30, -50, 110], degrees=True).as_matrix()
    T[:3, 3] = [0.4, -2.0, 1.5]
    moved = target @ T[:3, :3].T + T[:3, 3]  # the same view seen from elsewhere, pose T
    assert _uncertainty(source, moved, T) == pytest.approx(_uncertainty(source, target), rel=1e-6)


def test_a_pose_that_pairs_nothing_is_infinitely_uncertain() -> None:
    source = _ellipsoid()
    far = np.eye(4)
    far[:3, 3] = [5.0, 0.0, 0.0]
    assert _uncertainty(source, _view(source, np.array([1.0, 0.0, 0.0]), 0.5, 0.01), far) == float("inf")


def test_every_result_reports_its_uncertainty(rng: np.random.Generator) -> None:
    source = _ellipsoid(4000) * 100.0  # mm
    target = _view(source, np.array([80.0, 30.0, 20.0]), 60.0, 0.5)
    fid = source[::400]
    for method in ("procrustes", "icp", "fpfh-p2p-icp"):
        result = Registrar(Config(seed=0)).register(
            source, target, method=method, source_fiducials_mm=fid, target_fiducials_mm=fid
        )
        assert np.isfinite(result.uncertainty_mm) and result.uncertainty_mm > 0, method
        assert "confidence" in result.runtime_ms and result.to_json_dict()["uncertainty_mm"] > 0


def test_ambiguity_needs_close_residuals_and_different_poses(rng: np.random.Generator) -> None:
    source = rng.normal(size=(1000, 3)) * 60
    far = np.eye(4)
    far[:3, 3] = [40.0, 0, 0]
    near = np.eye(4)
    near[:3, 3] = [1.0, 0, 0]

    def ambiguous(*candidates: Candidate) -> bool:
        return is_ambiguous(candidates, source, residual_ratio=1.2, pose_mm=15.0)

    assert ambiguous(Candidate("a", np.eye(4), 2.0, 50), Candidate("b", far, 2.3, 50))
    # Same pose twice is not ambiguous, nor is a clearly worse rival, nor a failed one.
    assert not ambiguous(Candidate("a", np.eye(4), 2.0, 50), Candidate("b", near, 2.1, 50))
    assert not ambiguous(Candidate("a", np.eye(4), 2.0, 50), Candidate("b", far, 4.0, 50))
    assert not ambiguous(Candidate("a", np.eye(4), 2.0, 50), Candidate("b", far, 2.0, 2, ok=False))
    # any close rival counts, not only the runner-up
    assert ambiguous(Candidate("a", np.eye(4), 2.0, 50), Candidate("b", near, 2.05, 50), Candidate("c", far, 2.3, 50))


def test_screened_methods_judge_ambiguity_on_the_screened_hypotheses() -> None:
    source = _ellipsoid(4000) * 100.0
    target = _view(source, np.array([0.0, 0.0, 40.0]), 45.0, 0.3)  # a small smooth face: rivals likely
    result = Registrar(Config(seed=0)).register(source, target, method="fpfh-p2p-icp")
    assert result.screened and all(c.name in {k.name for k in result.candidates} for c in result.screened)
    cfg = Config()
    expected = is_ambiguous(result.screened, source, cfg.ambiguity_residual_ratio, cfg.ambiguity_pose_mm)
    assert result.ambiguous == expected
    assert len(result.to_json_dict()["screened"]) == len(result.screened)
