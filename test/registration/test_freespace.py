"""Free-space consistency: a flipped pose that fits the back of the organ is ruled out; no origin changes nothing."""

from pathlib import Path

import numpy as np
import pytest
from same_pose import CROSS_MACHINE_MM, surface_shift_mm
from scipy.spatial.transform import Rotation

from liver_p2p_reg.bags.io import read_messages
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.registration.confidence import is_ambiguous, pose_warnings
from liver_p2p_reg.registration.features.learned.weights import BUNDLED_WEIGHTS
from liver_p2p_reg.registration.freespace import Scorer, penalized
from liver_p2p_reg.registration.preprocess import norm_to_mm, preprocess_pair
from liver_p2p_reg.registration.registrar import Registrar
from liver_p2p_reg.result import Candidate
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm

ROOT = Path(__file__).resolve().parents[2]
REFERENCE = Path(__file__).parents[1] / "data" / "unknown_origin_reference.npz"
EYE_MM = np.array([0.0, 0.0, 170.0])  # the camera, in the organ's own frame, looking down -z
HALF_THICKNESS_MM = 20.0


def organ(n: int = 6000) -> np.ndarray:
    """A liver-sized slab (160 x 110 x 40 mm) with flat front (+z) and back (-z) faces sampled alike: a
    view of the front face fits the back face just as well, from the wrong side."""
    rng = np.random.default_rng(5)
    r, phi = np.sqrt(rng.random(n // 3)), rng.uniform(0, 2 * np.pi, n // 3)
    face = np.stack([80 * r * np.cos(phi), 55 * r * np.sin(phi), np.full(n // 3, HALF_THICKNESS_MM)], axis=1)
    theta, z = rng.uniform(0, 2 * np.pi, n // 6), rng.uniform(0, HALF_THICKNESS_MM, n // 6)
    rim = np.stack([80 * np.cos(theta), 55 * np.sin(theta), z], axis=1)
    half = np.vstack([face, rim])
    return np.vstack([half, half * [1.0, -1.0, -1.0]])  # the back: the front turned 180 degrees about x


def front_view(points: np.ndarray) -> np.ndarray:
    """What the camera at EYE_MM sees of the front face (its central part)."""
    inner = (points[:, 0] / 60) ** 2 + (points[:, 1] / 40) ** 2 < 1
    return points[inner & (points[:, 2] > HALF_THICKNESS_MM - 1e-6)]


def poses() -> tuple[np.ndarray, np.ndarray]:
    """The true pose (organ -> sensor frame) and a flipped one that lays the organ's back face onto
    the view: the organ then lies between the camera and what the camera saw."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [15, -25, 40], degrees=True).as_matrix()
    T[:3, 3] = [20.0, -10.0, 60.0]
    flip = np.eye(4)
    flip[:3, :3] = Rotation.from_euler("x", 180, degrees=True).as_matrix()
    flip[:3, 3] = [0.0, 0.0, 2 * HALF_THICKNESS_MM]  # back face (z = -h) -> z = +h, the body above it
    return T, T @ flip


def test_free_space_rejects_a_flipped_pose_that_fits_the_back() -> None:
    source = organ()
    T_true, T_flip = poses()
    target = transform_points(T_true, front_view(source))
    origin = transform_points(T_true, EYE_MM[None])[0]
    registrar = Registrar(Config())
    results = {
        name: registrar.register(source, target, method="evaluate", initial_T_mm=T, sensor_origin_mm=origin)
        for name, T in (("true", T_true), ("flipped", T_flip))
    }
    true, flipped = results["true"], results["flipped"]
    # Both poses fit the observed surface within a voxel (the back face is the front's mirror image) ...
    assert max(true.residual_mm, flipped.residual_mm) < registrar.config.residual_warn_mm / 2
    # ... but the flipped one puts the organ between the camera and what it saw.
    assert true.free_space == "on" and true.free_space_violation < 0.05
    assert flipped.free_space_violation > 0.5
    assert "free_space" in pose_warnings(
        flipped.residual_mm, False, flipped.uncertainty_mm, registrar.config, flipped.free_space_violation
    )
    assert "free_space" not in pose_warnings(
        true.residual_mm, False, true.uncertainty_mm, registrar.config, true.free_space_violation
    )
    # Selection and the ambiguity test rank them apart once the violation is known.
    w = registrar.config.free_space_weight
    assert penalized(flipped.residual_mm, flipped.free_space_violation, w) > penalized(
        true.residual_mm, true.free_space_violation, w
    )
    r = true.residual_mm  # two hypotheses that fit equally well, as P2P's candidates of a smooth view can
    hypotheses = [
        Candidate("true", T_true, r, 100, free_space_violation=true.free_space_violation),
        Candidate("flipped", T_flip, 0.99 * r, 100, free_space_violation=flipped.free_space_violation),
    ]
    assert not is_ambiguous(hypotheses, source, 1.2, 15.0, free_space_weight=w)
    for c in hypotheses:
        c.free_space_violation = float("nan")  # the same hypotheses without a sensor origin
    assert is_ambiguous(hypotheses, source, 1.2, 15.0, free_space_weight=w)


def test_scorer_batches_poses_and_refuses_an_origin_that_cannot_be_the_sensor() -> None:
    source = organ()
    T_true, T_flip = poses()
    target = transform_points(T_true, front_view(source))
    config = Config()
    prep = preprocess_pair(source, target, config)

    def normalized(T: np.ndarray) -> np.ndarray:
        return np.linalg.inv(norm_to_mm(prep.target_norm)) @ T @ norm_to_mm(prep.source_norm)

    band = config.free_space_band_mm / prep.source_norm.scale_mm
    origin = prep.target_norm.apply(transform_points(T_true, EYE_MM[None]))[0]
    scorer = Scorer(prep.source, prep.target, origin, config.voxel_size_norm, band)
    both = scorer([normalized(T_true), normalized(T_flip)])
    assert both.shape == (2,) and both[0] < 0.05 < 0.5 < both[1]
    assert np.array_equal(both, np.concatenate([scorer([normalized(T_true)]), scorer([normalized(T_flip)])]))
    # An origin in the plane of the view sees its points edge-on: not the sensor's, so no scores at all.
    edge_on = prep.target_norm.apply(transform_points(T_true, np.array([[0.0, 1.0, HALF_THICKNESS_MM]])))[0]
    refused = Scorer(prep.source, prep.target, edge_on, config.voxel_size_norm, band)
    assert refused.view is None and refused.status.startswith("off: ")
    assert np.isnan(refused([normalized(T_true)])).all()


def test_bad_sensor_origin_is_one_input_error() -> None:
    source = organ()
    with pytest.raises(InputError, match="sensor origin must be 3 finite numbers"):
        Registrar().register(source, front_view(source), method="icp", sensor_origin_mm=[0.0, np.nan, 1.0])
    with pytest.raises(InputError, match="sensor origin must be 3 finite numbers"):
        Registrar().register(source, front_view(source), method="icp", sensor_origin_mm=[0.0, 1.0])


def test_unknown_origin_changes_nothing() -> None:
    """The results of main before free space existed (test/data, made by e37fd94's code on this frame).

    The reference was computed on another machine: other CPUs take other SIMD/FMA paths in torch,
    Open3D and BLAS, so across machines the poses agree within CROSS_MACHINE_MM on the preop surface,
    not bitwise (test_same_input_same_pose_bitwise checks what one machine computes twice).
    """
    messages = list(read_messages(ROOT / "bags" / "phantom_sim_03_vis0.35"))
    preop = next(cloud_to_points_mm(m.msg) for m in messages if m.topic == "/preop/points")
    frame = next(cloud_to_points_mm(m.msg) for m in messages if m.topic == "/intraop/points")
    reference = np.load(REFERENCE, allow_pickle=False)
    # e37fd94 shipped matcher_v2: the learned methods are compared with those weights.
    registrar = Registrar(Config(weights_path=str(BUNDLED_WEIGHTS.with_name("matcher_v2.safetensors"))))
    for method in ("learned-p2p-icp", "learned-p2p", "fpfh-p2p-icp", "fpfh-ransac-icp"):
        result = registrar.register(preop, frame, method=method)
        key = method.replace("-", "_")
        assert surface_shift_mm(result.T_target_source, reference[f"{key}_T"], preop) < CROSS_MACHINE_MM, method
        residual, uncertainty, ambiguous, chosen = reference[f"{key}_values"]
        assert abs(result.residual_mm - residual) < CROSS_MACHINE_MM, method
        assert abs(result.uncertainty_mm - uncertainty) < CROSS_MACHINE_MM, method
        assert (float(result.ambiguous), float(result.chosen)) == (ambiguous, chosen), method
        assert np.isnan(result.free_space_violation) and result.free_space == ""
        assert "free_space" not in result.runtime_ms


def test_same_input_same_pose_bitwise() -> None:
    """What one machine computes twice (a fresh Registrar, then the same one again) is bitwise the same."""
    messages = list(read_messages(ROOT / "bags" / "phantom_sim_03_vis0.35"))
    preop = next(cloud_to_points_mm(m.msg) for m in messages if m.topic == "/preop/points")
    frame = next(cloud_to_points_mm(m.msg) for m in messages if m.topic == "/intraop/points")
    for method in ("learned-p2p-icp", "fpfh-ransac-icp"):
        registrar = Registrar()
        first = registrar.register(preop, frame, method=method)
        again = registrar.register(preop, frame, method=method)
        fresh = Registrar().register(preop, frame, method=method)
        for other in (again, fresh):
            assert other.T_target_source.tobytes() == first.T_target_source.tobytes(), method
            assert (other.residual_mm, other.uncertainty_mm) == (first.residual_mm, first.uncertainty_mm), method


def test_camera_crops_store_the_eye_and_older_files_are_brought_up_to_date(tmp_path) -> None:
    from liver_p2p_reg.phantom.casefile import SENSOR_ORIGIN_KEY, read_case, sensor_origin_mm, write_case
    from liver_p2p_reg.phantom.dataset import DatasetSpec, case_is_current, generate_dataset

    spec = DatasetSpec(livers=1, deformations=1, targets=2, crop="camera", seed=7)
    generate_dataset(tmp_path, spec, progress=False)
    paths = sorted(tmp_path.glob("case_*.npz"))
    case = read_case(paths[0])
    eye = sensor_origin_mm(case)
    # The camera stood in front of what it saw: every target point lies within its 70-degree view.
    rays = case["tgt_pcd"] - eye
    axis = rays.mean(axis=0) / np.linalg.norm(rays.mean(axis=0))
    cos = rays @ axis / np.linalg.norm(rays, axis=1)
    assert eye is not None and np.degrees(np.arccos(cos.min())) < 50
    # A file from before the eye was stored: unknown origin, and regenerated identically plus the eye.
    older = {k: v for k, v in case.items() if k != SENSOR_ORIGIN_KEY}
    write_case(paths[0], older)
    assert sensor_origin_mm(read_case(paths[0])) is None and not case_is_current(paths[0], "camera")
    generate_dataset(tmp_path, spec, progress=False)
    again = read_case(paths[0])
    assert case_is_current(paths[0], "camera") and set(again) == set(case)
    assert all(np.array_equal(np.asarray(again[k]), np.asarray(case[k])) for k in case)


def test_register_command_takes_the_sensor_origin(tmp_path, capsys) -> None:
    import json

    from liver_p2p_reg.cli import main
    from liver_p2p_reg.cloud_io import save_points

    source = organ()
    T_true, _ = poses()
    save_points(tmp_path / "source.xyz", source)
    save_points(tmp_path / "target.xyz", transform_points(T_true, front_view(source)))
    fiducials = np.array([[0.0, 0.0, 0.0], [40.0, 10.0, 5.0], [-30.0, 20.0, -5.0], [10.0, -25.0, 10.0]])
    np.save(tmp_path / "fid_s.npy", fiducials)
    np.save(tmp_path / "fid_t.npy", transform_points(T_true, fiducials))
    origin = ",".join(f"{v:.3f}" for v in transform_points(T_true, EYE_MM[None])[0])
    argv = [
        "register",
        str(tmp_path / "source.xyz"),
        str(tmp_path / "target.xyz"),
        "--method",
        "procrustes",
        "--source-fiducials",
        str(tmp_path / "fid_s.npy"),
        "--target-fiducials",
        str(tmp_path / "fid_t.npy"),
    ]
    assert main([*argv, f"--sensor-origin={origin}"]) == 0  # `=`: a leading minus is no option
    out = json.loads(capsys.readouterr().out)
    assert out["free_space"] == "on" and 0 <= out["free_space_violation"] < 0.05
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["free_space"] == "" and out["free_space_violation"] is None
    assert main([*argv, "--sensor-origin", "1,2"]) == 2
    assert "--sensor-origin must be three finite numbers" in capsys.readouterr().err
    # typed with a space and a minus sign, as a user types coordinates (argparse alone reads it as an option)
    assert main([*argv, "--sensor-origin", "-10,0,5"]) == 0
    assert json.loads(capsys.readouterr().out)["free_space"] != ""
    assert main([*argv, "--sensor-origin", "-1,2"]) == 2
    assert "--sensor-origin must be three finite numbers" in capsys.readouterr().err
