"""Public API behaviour that does not depend on a particular method: registry, errors, metrics, JSON."""

from __future__ import annotations

import numpy as np
import pytest

from liver_p2p_reg import Config, InputError, Registrar, available_methods
from liver_p2p_reg.metrics import rms_tre_mm, rotation_angle_deg, transform_points
from liver_p2p_reg.result import Candidate, RegistrationResult


def _rigid(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = q, rng.uniform(-100, 100, 3)
    return T


def test_unknown_method_lists_choices(rng: np.random.Generator) -> None:
    pts = rng.normal(size=(200, 3)) * 50
    with pytest.raises(InputError, match="unknown method 'nope'; choose one of"):
        Registrar().register(pts, pts, method="nope")


def test_bad_clouds_are_refused_before_any_method_runs(rng: np.random.Generator) -> None:
    pts = rng.normal(size=(200, 3)) * 50
    registrar = Registrar(Config(min_points=50))
    with pytest.raises(InputError, match="target: the point cloud is empty"):
        registrar.register(pts, np.zeros((0, 3)))
    with pytest.raises(InputError, match="source: all 200 points are NaN"):
        registrar.register(np.full((200, 3), np.nan), pts)
    with pytest.raises(InputError, match="only 10 valid points"):
        registrar.register(pts, pts[:10])
    with pytest.raises(InputError, match="fiducials must be two"):
        registrar.register(pts, pts, source_fiducials_mm=pts[:5], target_fiducials_mm=pts[:6])
    nan_fiducials = np.where(np.arange(5)[:, None] == 2, np.nan, pts[:5])
    with pytest.raises(InputError, match="fiducials contain NaN"):  # a silent NaN RMS-TRE before
        registrar.register(pts, pts, source_fiducials_mm=pts[:5], target_fiducials_mm=nan_fiducials)
    # Not numbers at all: an InputError too, not numpy's ValueError / TypeError.
    with pytest.raises(InputError, match="source: not an array of numbers"):
        registrar.register([["a", "b", "c"]] * 200, pts)
    with pytest.raises(InputError, match="target: complex numbers"):
        registrar.register(pts, pts + 1j)
    with pytest.raises(InputError, match="initial_T_mm: not an array of numbers"):
        registrar.register(pts, pts, method="track", initial_T_mm=[["x"] * 4] * 4)


@pytest.mark.parametrize("scale", [1e-3, 1e3], ids=["metres", "micrometres"])
def test_clouds_in_other_units_are_refused(rng: np.random.Generator, scale: float) -> None:
    liver = rng.normal(size=(2000, 3))
    liver = liver / np.linalg.norm(liver, axis=1, keepdims=True) * [80.0, 55.0, 40.0]
    view = liver[liver[:, 0] > 20]
    with pytest.raises(InputError, match="target extent .* wrong units"):
        Registrar().register(liver, view * scale, method="icp")
    with pytest.raises(InputError, match="source extent .* wrong units"):
        Registrar().register(liver * scale, view, method="icp")
    # Other objects: the plausible range is a setting (and its bounds are checked).
    lo, hi = (0.01, 600.0) if scale < 1 else (20.0, 1e6)
    result = Registrar(Config(expected_extent_min_mm=lo, expected_extent_max_mm=hi)).register(
        liver * scale, view * scale, method="icp"
    )
    assert np.isfinite(result.T_target_source).all()
    with pytest.raises(InputError, match="expected_extent_min_mm < expected_extent_max_mm"):
        Config(expected_extent_min_mm=50.0, expected_extent_max_mm=40.0).validate()


def test_metrics_on_a_known_transform(rng: np.random.Generator) -> None:
    T = _rigid(rng)
    fid = rng.normal(size=(30, 3)) * 40
    moved = transform_points(T, fid)
    assert rms_tre_mm(T, fid, moved) < 1e-9
    shifted = moved + np.array([3.0, 4.0, 0.0])
    assert rms_tre_mm(T, fid, shifted) == pytest.approx(5.0)
    assert rotation_angle_deg(T[:3, :3], T[:3, :3]) == pytest.approx(0.0, abs=1e-5)


def test_result_json_is_serializable() -> None:
    import json

    cand = Candidate("complete-to-partial", np.eye(4), float("nan"), 0, ok=False)
    res = RegistrationResult(np.eye(4), "m", 1.5, runtime_ms={"total": 3.0}, candidates=[cand], chosen=0)
    text = json.dumps(res.to_json_dict())
    assert '"residual_mm": null' in text and "complete-to-partial" in text
    assert "residual=1.50 mm" in repr(res)


def test_available_methods_is_a_sorted_list() -> None:
    names = available_methods()
    assert names == sorted(names)


def test_remember_latest_reuses_one_entry_per_kind(rng: np.random.Generator) -> None:
    from liver_p2p_reg.registration.context import remember_latest

    cache: dict = {}
    calls: list[int] = []
    a, b = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    assert remember_latest(cache, "k", a, (1,), lambda: calls.append(1) or "A") == "A"
    assert remember_latest(cache, "k", a.copy(), (1,), lambda: calls.append(1) or "X") == "A"  # same content: hit
    assert remember_latest(cache, "k", b, (1,), lambda: calls.append(1) or "B") == "B"
    assert remember_latest(cache, "other", a, (1,), lambda: "O") == "O"
    assert len(calls) == 2 and len(cache) == 2  # only the latest entry of each kind is kept


def test_track_method_needs_a_rigid_prior_pose():
    rng = np.random.default_rng(0)
    source = rng.normal(size=(500, 3)) * [40.0, 30.0, 20.0]
    registrar = Registrar(Config())
    with pytest.raises(InputError, match="needs initial_T_mm"):
        registrar.register(source, source[:200], method="track")
    with pytest.raises(InputError, match="finite 4x4"):
        registrar.register(source, source[:200], method="track", initial_T_mm=np.eye(3))
    with pytest.raises(InputError, match="not a rotation"):
        registrar.register(source, source[:200], method="track", initial_T_mm=np.diag([2.0, 1, 1, 1]))
    projective = np.eye(4)
    projective[3] = [1.0, 2.0, 3.0, 4.0]
    with pytest.raises(InputError, match="bottom row"):
        registrar.register(source, source[:200], method="track", initial_T_mm=projective)
    result = registrar.register(source, source[:200], method="track", initial_T_mm=np.eye(4))
    assert result.method == "track" and result.residual_mm < 1.0  # voxel means vs points
    np.testing.assert_allclose(result.T_target_source, np.eye(4), atol=1e-6)


def test_warm_up_fills_the_source_caches_and_never_raises():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(3000, 3))
    source = d / np.linalg.norm(d, axis=1, keepdims=True) * [80.0, 55.0, 40.0]
    registrar = Registrar(Config(method="fpfh-p2p-icp"))
    assert registrar.warm_up(source) > 0
    kinds = {key.split(":")[0] for key in registrar.cache if isinstance(key, str)}
    assert {"prepared-source", "fpfh", "icp-source-index"} <= kinds  # the model's share is done
    # the oracle needs fiducials: its warm-up fails quietly, the real call reports the error
    assert Registrar(Config(method="procrustes")).warm_up(source) >= 0
    assert Registrar(Config()).warm_up(np.zeros((0, 3))) >= 0  # bad source: nothing to prepare
