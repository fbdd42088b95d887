"""preop_loader_node's structures in this process (rclpy): the managed twin publishes them while active, a string parameter works."""

import json
import time

import numpy as np
import pytest
from conftest import require_rclpy

rclpy = require_rclpy()

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from liver_p2p_reg.cloud_io import save_points  # noqa: E402
from liver_p2p_reg.livegraph.graph import set_isolated_environment  # noqa: E402
from liver_p2p_reg.ros.pointcloud2 import cloud_to_structures, stamp_to_ns  # noqa: E402
from liver_p2p_reg.ros.preop_loader_lifecycle_node import ManagedPreopLoaderNode  # noqa: E402
from liver_p2p_reg.ros.preop_loader_node import PreopLoaderNode  # noqa: E402
from liver_p2p_reg.ros.topics import (  # noqa: E402
    TOPIC_DIAGNOSTICS,
    TOPIC_PREOP,
    TOPIC_PREOP_STRUCTURES,
    TOPIC_STRUCTURE_LABELS,
    rclpy_qos,
)
from liver_p2p_reg.stream.outputs import ERROR, LOADER_DIAG_NAME, OK  # noqa: E402


def spin_until(executor, condition, timeout_s=20.0):
    end = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)
    return condition()


def files(tmp_path, rng):
    d = rng.normal(size=(2000, 3))
    liver = d / np.linalg.norm(d, axis=1, keepdims=True) * [80.0, 55.0, 40.0] + [0.0, -150.0, 300.0]
    tumour = liver.mean(axis=0) + rng.normal(size=(12, 3)) * 2.0
    save_points(tmp_path / "liver.npy", liver)
    save_points(tmp_path / "tumour.xyz", tumour)
    return tumour


def listen(node):
    got = {TOPIC_PREOP: [], TOPIC_PREOP_STRUCTURES: [], TOPIC_STRUCTURE_LABELS: [], TOPIC_DIAGNOSTICS: []}
    for topic, kind in (
        (TOPIC_PREOP, PointCloud2),
        (TOPIC_PREOP_STRUCTURES, PointCloud2),
        (TOPIC_STRUCTURE_LABELS, String),
    ):
        node.create_subscription(kind, topic, got[topic].append, rclpy_qos(topic))
    node.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS, got[TOPIC_DIAGNOSTICS].append, 10)
    return got


def test_the_managed_loader_publishes_structures_and_its_status_only_while_active(tmp_path, rng):
    tumour = files(tmp_path, rng)
    specs = [f"{tmp_path / 'tumour.xyz'}:tumour", str(tmp_path / "missing.ply")]
    set_isolated_environment()  # a domain of its own: no other graph's /diagnostics
    rclpy.init()
    try:
        loader = ManagedPreopLoaderNode(
            parameter_overrides=[
                Parameter("model_path", value=str(tmp_path / "liver.npy")),
                Parameter("structures_paths", value=specs),
            ]
        )
        helper = rclpy.create_node("structures_helper")
        got = listen(helper)
        executor = SingleThreadedExecutor()
        executor.add_node(loader)
        executor.add_node(helper)
        loader.trigger_configure()  # a bad structure file does not fail configure
        assert loader.loaded is not None and [s.label for s in loader.loaded["structures"]] == ["tumour"]
        loader.trigger_activate()
        assert spin_until(executor, lambda: all(got.values()))
        points_m, ids, bounds = cloud_to_structures(got[TOPIC_PREOP_STRUCTURES][0])
        np.testing.assert_allclose(points_m * 1e3, tumour, atol=1e-3)
        assert ids.tolist() == [0] * 12 and bounds is None and got[TOPIC_PREOP_STRUCTURES][0].header.frame_id == "ct"
        stamp = stamp_to_ns(got[TOPIC_PREOP][0].header.stamp)
        assert stamp_to_ns(got[TOPIC_PREOP_STRUCTURES][0].header.stamp) == stamp
        assert json.loads(got[TOPIC_STRUCTURE_LABELS][0].data) == {"labels": ["tumour"], "stamp_ns": stamp}
        (status,) = [s for m in got[TOPIC_DIAGNOSTICS] for s in m.status][:1]
        assert status.name == LOADER_DIAG_NAME and status.level == bytes([ERROR]) and "missing.ply" in status.message
        loader.trigger_deactivate()  # publishers and the status timer withdrawn
        assert spin_until(executor, lambda: not helper.get_publishers_info_by_topic(TOPIC_PREOP_STRUCTURES), 10)
        spin_until(executor, lambda: False, 0.3)
        seen = len(got[TOPIC_DIAGNOSTICS])
        spin_until(executor, lambda: False, 1.5)
        assert len(got[TOPIC_DIAGNOSTICS]) == seen
        loader.trigger_cleanup()
        assert loader.loaded is None
        executor.shutdown()
        loader.destroy_node()
        helper.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_a_comma_separated_string_parameter_and_no_structures(tmp_path, rng):
    files(tmp_path, rng)
    set_isolated_environment()
    rclpy.init()
    try:
        text = f"{tmp_path / 'tumour.xyz'}:tumour, {tmp_path / 'tumour.xyz'}:again"  # what a launch argument gives
        loader = PreopLoaderNode(
            parameter_overrides=[
                Parameter("model_path", value=str(tmp_path / "liver.npy")),
                Parameter("structures_paths", value=text),
            ]
        )
        assert [s.label for s in loader.loaded["structures"]] == ["tumour", "again"] and loader.status.level == OK
        loader.destroy_node()
        bare = PreopLoaderNode(parameter_overrides=[Parameter("model_path", value=str(tmp_path / "liver.npy"))])
        assert bare.loaded["structures"] == [] and bare.status.level == OK and "0 structure(s)" in bare.status.message
        bare.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_loader_parameters_of_the_wrong_kind_are_one_line_naming_the_parameter(tmp_path) -> None:
    from liver_p2p_reg.errors import InputError
    from liver_p2p_reg.ros.preop_loader_node import load_model_m, structure_specs

    with pytest.raises(InputError, match="structures_paths must be a string or a list"):  # was a TypeError
        structure_specs(True)
    with pytest.raises(InputError, match="fiducials_path not found"):  # it used to blame model_path
        load_model_m(str(tmp_path / "missing.xyz"), "mm", "fiducials_path")
    with pytest.raises(InputError, match="model_path: expected a file, got a directory"):  # was "not found"
        load_model_m(str(tmp_path), "mm")
