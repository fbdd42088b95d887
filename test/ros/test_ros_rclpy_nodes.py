"""rclpy wiring of register_node and preop_loader_node in this process (the process-level tests are test_ros_graph*.py)."""

import contextlib
import time

import numpy as np
import pytest
from conftest import require_rclpy  # noqa: E402

rclpy = require_rclpy()

from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data  # noqa: E402
from ros_support import stop_executor  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from liver_p2p_reg.errors import InputError  # noqa: E402
from liver_p2p_reg.registration.registrar import available_methods  # noqa: E402
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_m, points_to_cloud  # noqa: E402
from liver_p2p_reg.ros.preop_loader_node import PreopLoaderNode  # noqa: E402
from liver_p2p_reg.ros.register_node import RCLPY_TYPES, RegisterNode  # noqa: E402
from liver_p2p_reg.ros.topics import (  # noqa: E402
    TOPIC_DEFORMED_PREOP,
    TOPIC_INTRAOP,
    TOPIC_INTRAOP_FIDUCIALS,
    TOPIC_POSE,
    TOPIC_PREOP,
    TOPIC_PREOP_FIDUCIALS,
    TOPIC_PREOP_MESH,
    TOPIC_REGISTERED,
    rclpy_qos,
)


@pytest.fixture
def ros_context():
    rclpy.init()
    yield
    rclpy.try_shutdown()


@contextlib.contextmanager
def pose_graph(overrides: list, helper_name: str):
    """register_node with `overrides`, a helper node collecting /registration/pose, both on one executor."""
    node = RegisterNode(parameter_overrides=overrides)
    helper = rclpy.create_node(helper_name)
    poses: list = []
    helper.create_subscription(PoseStamped, TOPIC_POSE, poses.append, rclpy_qos(TOPIC_POSE))
    executor = MultiThreadedExecutor(num_threads=4)
    executor.add_node(node)
    executor.add_node(helper)
    try:
        yield node, helper, executor, poses
    finally:
        stop_executor(executor)
        node.stop()
        node.destroy_node()
        helper.destroy_node()


def publish_model(helper, preop_m: np.ndarray, fid_m: np.ndarray, offset: np.ndarray) -> None:
    """The preop model and its fiducials (ct) and the intraop fiducials (camera, stamp 7: the cloud's to come)."""
    types = RCLPY_TYPES.cloud
    helper.create_publisher(PointCloud2, TOPIC_PREOP, rclpy_qos(TOPIC_PREOP)).publish(
        points_to_cloud(preop_m, types, frame_id="ct")
    )
    helper.create_publisher(PointCloud2, TOPIC_PREOP_FIDUCIALS, rclpy_qos(TOPIC_PREOP_FIDUCIALS)).publish(
        points_to_cloud(fid_m, types, frame_id="ct")
    )
    helper.create_publisher(PointCloud2, TOPIC_INTRAOP_FIDUCIALS, rclpy_qos(TOPIC_INTRAOP_FIDUCIALS)).publish(
        points_to_cloud(fid_m + offset, types, frame_id="camera", stamp_ns=7)
    )


def spin_until(executor, condition, timeout_s=30.0):
    end = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)
    return condition()


def test_topic_qos_is_what_msg_docs_say_in_rclpy_terms():
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    assert rclpy_qos(TOPIC_PREOP) == rclpy_qos(TOPIC_PREOP_FIDUCIALS) == latched
    assert rclpy_qos(TOPIC_INTRAOP) == qos_profile_sensor_data  # rclpy's own preset
    assert rclpy_qos(TOPIC_INTRAOP_FIDUCIALS) == rclpy_qos(TOPIC_POSE) == QoSProfile(depth=10)  # reliable, volatile
    assert rclpy_qos(TOPIC_REGISTERED) == rclpy_qos(TOPIC_DEFORMED_PREOP) == QoSProfile(depth=1)
    assert rclpy_qos(TOPIC_PREOP_MESH) == latched  # register_node's subscription matches the loader's latched mesh


def test_rclpy_pointcloud2_round_trip():
    pts = np.random.default_rng(0).uniform(-0.1, 0.1, size=(40, 3))
    msg = points_to_cloud(pts, RCLPY_TYPES.cloud, frame_id="camera", stamp_ns=5, big_endian=True, height=4)
    assert isinstance(msg, PointCloud2)
    np.testing.assert_allclose(cloud_to_points_m(msg), pts, atol=1e-7)


@pytest.mark.skipif("procrustes" not in available_methods(), reason="procrustes method not implemented yet")
def test_register_node_publishes_pose_and_answers_service(ros_context):
    rng = np.random.default_rng(0)
    d = rng.normal(size=(1500, 3))
    preop_m = d / np.linalg.norm(d, axis=1, keepdims=True) * [0.08, 0.055, 0.04]
    fid_m = rng.uniform(-0.02, 0.02, size=(5, 3))
    offset = np.array([0.01, -0.02, 0.3])
    with pose_graph([Parameter("method", value="procrustes")], "test_helper") as (node, helper, executor, poses):
        types = RCLPY_TYPES.cloud
        publish_model(helper, preop_m, fid_m, offset)
        assert spin_until(executor, lambda: node.core.preop_mm is not None)
        intraop = helper.create_publisher(PointCloud2, TOPIC_INTRAOP, rclpy_qos(TOPIC_INTRAOP))
        intraop.publish(points_to_cloud(preop_m[preop_m[:, 0] > 0] + offset, types, frame_id="camera", stamp_ns=7))
        assert spin_until(executor, lambda: len(poses) > 0)
        p = poses[0].pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], offset, atol=1e-6)
        assert poses[0].header.frame_id == "camera"
        client = helper.create_client(Trigger, "/register_node/reregister")
        assert client.wait_for_service(timeout_sec=10)
        future = client.call_async(Trigger.Request())
        assert spin_until(executor, future.done)
        assert future.result().success and "residual" in future.result().message


def test_register_node_runs_the_ransac_candidate_method(ros_context):
    """The default's RANSAC candidate through register_node over DDS: RANSAC's pose is among the screened hypotheses."""
    from synthetic_cases import partial_case

    source_mm, target_mm, T_true, _, _ = partial_case(np.random.default_rng(7))
    overrides = [
        Parameter("ransac_candidate_visibility", value=1.0),  # this crop is larger than the default's 0.2
        Parameter("sensor_at_frame_origin", value=False),  # a synthetic crop: no camera at its frame's origin
    ]
    with pose_graph(overrides, "test_helper_ransac") as (node, helper, executor, poses):
        types = RCLPY_TYPES.cloud
        helper.create_publisher(PointCloud2, TOPIC_PREOP, rclpy_qos(TOPIC_PREOP)).publish(
            points_to_cloud(source_mm / 1000.0, types, frame_id="ct")
        )
        assert spin_until(executor, lambda: node.core.preop_mm is not None)
        intraop = helper.create_publisher(PointCloud2, TOPIC_INTRAOP, rclpy_qos(TOPIC_INTRAOP))
        intraop.publish(points_to_cloud(target_mm / 1000.0, types, frame_id="camera", stamp_ns=7))
        assert spin_until(executor, lambda: len(poses) > 0, timeout_s=60.0)
        p = poses[0].pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], T_true[:3, 3] / 1000.0, atol=0.005)  # within 5 mm
        # the pose is published from inside the registration; its output is kept just after
        assert spin_until(executor, lambda: node.core.last_output is not None)
        result = node.core.last_output.result
        assert result.method == "learned-p2p-icp" and "ransac" in result.runtime_ms
        assert "fpfh-ransac" in [c.name for c in result.candidates]


def test_register_node_judges_small_views_contenders_on_the_preop_mesh(ros_context):
    """contender_judge_ratio over DDS: the contenders are judged by the elastic model of /preop/mesh (the stage's)."""
    from synthetic_cases import rigid
    from visualization_msgs.msg import Marker

    from liver_p2p_reg.metrics import transform_points
    from liver_p2p_reg.phantom.simulate import simulate_liver
    from liver_p2p_reg.ros.messages import triangle_list_marker
    from liver_p2p_reg.ros.rclpy_types import RCLPY_MARKER_TYPES

    sim = simulate_liver(3, 1, target_tets=1500)
    surface = sim.deformations[0].surface_mm
    centre = surface[np.argmax(surface[:, 0] + surface[:, 2])]
    view_mm = transform_points(
        rigid(np.random.default_rng(3)),
        surface[np.argsort(np.linalg.norm(surface - centre, axis=1))[: int(0.15 * len(surface))]],
    )
    overrides = [
        Parameter("ransac_candidate_visibility", value=1.0),
        Parameter("contender_judge_ratio", value=100.0),  # every screened candidate a contender
        Parameter("deform_modes", value=12),
        Parameter("deform_target_tets", value=1500),
        Parameter("sensor_at_frame_origin", value=False),  # a synthetic view: no camera at its frame's origin
    ]
    with pose_graph(overrides, "test_helper_judge") as (node, helper, executor, poses):
        types = RCLPY_TYPES.cloud
        helper.create_publisher(Marker, TOPIC_PREOP_MESH, rclpy_qos(TOPIC_PREOP_MESH)).publish(
            triangle_list_marker(sim.vertices_mm / 1000.0, sim.triangles, RCLPY_MARKER_TYPES, "ct", 5)
        )
        helper.create_publisher(PointCloud2, TOPIC_PREOP, rclpy_qos(TOPIC_PREOP)).publish(
            points_to_cloud(sim.vertices_mm / 1000.0, types, frame_id="ct", stamp_ns=5)
        )
        assert spin_until(
            executor, lambda: node.core.preop_mm is not None and node.core.mesh.for_model("ct", 5) is not None
        )
        intraop = helper.create_publisher(PointCloud2, TOPIC_INTRAOP, rclpy_qos(TOPIC_INTRAOP))
        intraop.publish(points_to_cloud(view_mm / 1000.0, types, frame_id="camera", stamp_ns=7))
        assert spin_until(executor, lambda: len(poses) > 0 and node.core.last_output is not None, timeout_s=90.0)
        result = node.core.last_output.result
        keys = [c.judge_key_mm for c in result.screened]
        assert "judge" in result.runtime_ms and len(keys) >= 2 and np.all(np.isfinite(keys)), keys
        assert result.candidates[result.chosen].name == result.screened[int(np.argmin(keys))].name
        models = [k for k in node.core.registrar.cache if isinstance(k, str) and k.startswith("elastic:")]
        assert len(models) == 1 and "True)" in models[0], models  # the mesh's model, not one rebuilt from the points


def test_preop_loader_missing_file_is_fatal_input_error(ros_context, tmp_path):
    with pytest.raises(InputError, match="not found"):
        PreopLoaderNode(parameter_overrides=[Parameter("model_path", value=str(tmp_path / "missing.stl"))])


def test_parameter_set_keeps_the_registrar_cache(ros_context):
    """A parameter set swaps the configuration but keeps what was computed about the model."""
    node = RegisterNode(parameter_overrides=[Parameter("method", value="icp")])
    try:
        marker = object()
        node.core.registrar.cache["test-marker:x:()"] = marker
        assert node.set_parameters([Parameter("residual_warn_mm", value=5.0)])[0].successful
        end = time.monotonic() + 30
        while node.core.config.residual_warn_mm != 5.0 and time.monotonic() < end:
            time.sleep(0.02)  # applied by the node's worker, between registrations
        assert node.core.config.residual_warn_mm == 5.0
        assert node.core.registrar.cache.get("test-marker:x:()") is marker
        bad = node.set_parameters([Parameter("method", value="nope")])[0]
        assert not bad.successful and "unknown method 'nope'" in bad.reason
    finally:
        node.stop()
        node.destroy_node()


def test_preop_loader_publishes_mesh_path_beside_a_point_model(ros_context, tmp_path):
    """A model given as points with its mesh beside it (the demo's bags): /preop/mesh is that mesh's."""
    from liver_p2p_reg.o3d import o3d_module
    from liver_p2p_reg.ros.messages import mesh_marker_mm

    o3d = o3d_module()
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=60.0, resolution=8)
    mesh = tmp_path / "mesh.ply"
    assert o3d.io.write_triangle_mesh(str(mesh), sphere)
    model = tmp_path / "model.npy"
    np.save(model, np.random.default_rng(0).normal(size=(500, 3)) * 50.0)
    node = PreopLoaderNode(
        parameter_overrides=[Parameter("model_path", value=str(model)), Parameter("mesh_path", value=str(mesh))]
    )
    try:
        vertices_mm, triangles = mesh_marker_mm(node.loaded["mesh"])
        assert len(triangles) == len(sphere.triangles) and len(vertices_mm) == len(sphere.vertices)
        assert np.abs(np.linalg.norm(vertices_mm, axis=1) - 60.0).max() < 1e-3  # the mesh's, in mm
        assert len(node.loaded["model_m"]) == 500  # the points stay the model
    finally:
        node.destroy_node()
    for bad, reason in ((model, "not a mesh file"), (tmp_path / "none.ply", "mesh_path not found")):
        with pytest.raises(InputError, match=reason):
            PreopLoaderNode(
                parameter_overrides=[Parameter("model_path", value=str(model)), Parameter("mesh_path", value=str(bad))]
            )


def test_register_node_in_survey_mode_deforms_onto_the_fused_sweep(ros_context):
    """mode survey + deform over DDS: from the second fused frame the stage fits the fused surface (deform_view)."""
    from pathlib import Path

    from ros_support import bag_frames_m

    preop_m, frames_m = bag_frames_m(Path(__file__).resolve().parents[2] / "bags" / "sweep_insilico_9000002")
    overrides = [
        Parameter("mode", value="survey"),
        Parameter("deform", value=True),
        Parameter("max_rate_hz", value=50.0),
    ]
    with pose_graph(overrides, "test_helper_survey_deform") as (node, helper, executor, poses):
        types = RCLPY_TYPES.cloud
        deformed: list = []
        helper.create_subscription(PointCloud2, TOPIC_DEFORMED_PREOP, deformed.append, rclpy_qos(TOPIC_DEFORMED_PREOP))
        helper.create_publisher(PointCloud2, TOPIC_PREOP, rclpy_qos(TOPIC_PREOP)).publish(
            points_to_cloud(preop_m, types, frame_id="ct")
        )
        assert spin_until(executor, lambda: node.core.preop_mm is not None)
        intraop = helper.create_publisher(PointCloud2, TOPIC_INTRAOP, rclpy_qos(TOPIC_INTRAOP))
        views = []
        for i, k in enumerate((0, 4, 8)):
            intraop.publish(points_to_cloud(frames_m[k], types, frame_id="camera", stamp_ns=100 + i))

            def done(stamp=str(100 + i)):
                out = node.core.last_output
                return out is not None and out.diagnostics[0].values.get("stamp_ns") == stamp

            assert spin_until(executor, done, timeout_s=90.0)
            views.append(node.core.last_output.diagnostics[0].values)
        assert [v["survey_state"] for v in views] == ["fusing"] * 3, [v.get("survey_state") for v in views]
        assert all(v["deform_view"] == "survey" for v in views)  # the fused surface, from the first frame on
        assert int(views[-1]["deform_view_points"]) == int(views[-1]["survey_points"])
        applied = sum(v["deform_applied"] == "true" for v in views)
        assert applied > 0, [v["deform_reason"] for v in views]
        # every pose and every deformed surface the stage gave arrives (and nothing is left in flight at teardown)
        assert spin_until(executor, lambda: len(deformed) == applied and len(poses) == 3, timeout_s=30.0)


def test_bad_runtime_input_never_takes_the_node_down(ros_context):
    """Found by an adversarial pass: parameters that crashed the node or were accepted and then failed every frame,
    a rate that ended the worker thread, and an unreadable cloud after which ~/reregister never answered."""
    rng = np.random.default_rng(1)
    d = rng.normal(size=(1500, 3))
    preop_m = d / np.linalg.norm(d, axis=1, keepdims=True) * [0.08, 0.055, 0.04]
    fid_m = rng.uniform(-0.02, 0.02, size=(5, 3))
    offset = np.array([0.01, -0.02, 0.3])
    overrides = [Parameter("method", value="procrustes"), Parameter("mode", value="on_demand")]
    with pose_graph(overrides, "fuzz_helper") as (node, helper, executor, poses):
        refused = {
            "record_path": ("~nosuchuser_zz/run.mcap", "not usable"),  # RuntimeError from expanduser: a crash
            "error_coverage": (0.5, "error_coverage 0.5 is not calibrated"),
            "error_calibration_path": ("/nonexistent/cal.json", "not found"),
        }
        for name, (value, words) in refused.items():
            answer = node.set_parameters([Parameter(name, value=value)])[0]
            assert not answer.successful and words in answer.reason, (name, answer.reason)
        long_name = node.set_parameters([Parameter("record_path", value="/tmp/" + "r" * 300 + ".mcap")])[0]
        assert not long_name.successful and "not usable" in long_name.reason  # OSError: file name too long
        types = RCLPY_TYPES.cloud
        publish_model(helper, preop_m, fid_m, offset)
        assert spin_until(executor, lambda: node.core.preop_mm is not None)
        intraop = helper.create_publisher(PointCloud2, TOPIC_INTRAOP, rclpy_qos(TOPIC_INTRAOP))
        client = helper.create_client(Trigger, "/register_node/reregister")
        assert client.wait_for_service(timeout_sec=10)

        def reregister() -> Trigger.Response:
            future = client.call_async(Trigger.Request())
            assert spin_until(executor, future.done, timeout_s=30.0), "~/reregister never answered"
            return future.result()

        broken = points_to_cloud(preop_m[:10], types, frame_id="camera", stamp_ns=8)
        broken.point_step = 2**31  # numpy's record type takes a C int: a ValueError past the checks
        intraop.publish(broken)
        spin_until(executor, lambda: False, timeout_s=0.5)
        answer = reregister()
        assert not answer.success and "point_step" in answer.message, answer.message
        assert node.set_parameters([Parameter("max_rate_hz", value=1e-10)])[0].successful
        intraop.publish(points_to_cloud(preop_m[preop_m[:, 0] > 0] + offset, types, frame_id="camera", stamp_ns=7))
        spin_until(executor, lambda: False, timeout_s=0.5)
        assert reregister().success and spin_until(executor, lambda: len(poses) == 1)
        spin_until(executor, lambda: False, timeout_s=1.0)  # the worker's next wait: 1e10 s, beyond TIMEOUT_MAX
        assert node._worker.is_alive()
        assert reregister().success  # and it still registers
