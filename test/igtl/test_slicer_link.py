"""SlicerLink without ROS: rosbags messages and CDR bytes in, OpenIGTLink out over loopback; bad messages counted."""

from __future__ import annotations

import numpy as np
import pytest
from igtl_support import Recorder, assert_wire_equal, expected_transform

from liver_p2p_reg.bags.io import rosbags_output_types, rosbags_types, typestore
from liver_p2p_reg.igtl.bridge import SlicerBridge, open_endpoint
from liver_p2p_reg.igtl.link import SlicerLink, decimated_points_mm
from liver_p2p_reg.ros.messages import diagnostic_array, pose_stamped
from liver_p2p_reg.ros.pointcloud2 import points_to_cloud
from liver_p2p_reg.slicer_config import SlicerConfig
from liver_p2p_reg.stream.core import NodeCore
from liver_p2p_reg.stream.outputs import DIAG_NAME, ERROR, OK, Diagnostic, PoseOutput


@pytest.fixture
def link():
    config = SlicerConfig(host="127.0.0.1", port=0, max_cloud_points=100, cloud_rate_hz=1000.0)
    endpoint = open_endpoint(config)
    yield SlicerLink(SlicerBridge(config, endpoint))
    endpoint.close()


def test_decimation_reads_only_the_kept_points_of_any_layout(rng: np.random.Generator) -> None:
    points_m = rng.uniform(-0.1, 0.1, (1200, 3))
    expected = points_m[np.linspace(0, 1199, 100).round().astype(int)] * 1000
    for layout in ({}, {"big_endian": True, "dtype": np.float64}, {"height": 30, "pad_bytes": 4}):
        msg = points_to_cloud(points_m, rosbags_types(), frame_id="camera", **layout)
        np.testing.assert_allclose(decimated_points_mm(msg, 100), expected, atol=1e-3)
    msg.row_step += 8  # organized with row padding the data lacks: one clear error
    with pytest.raises(Exception, match="truncated"):
        decimated_points_mm(msg, 100)


def test_verdicts_become_strings_summaries_do_not(link: SlicerLink) -> None:
    types = rosbags_output_types()
    slicer = Recorder.connect(link.bridge.endpoint.port)
    # Connected is not yet accepted: a peer the server has not registered gets only each device's
    # latest message on arrival (by design), so both verdicts need the peer in place first.
    assert link.bridge.endpoint.wait_for_peers(1, 10.0)
    try:
        summary = NodeCore().status()  # the node's 1 Hz summary: the last verdict plus its counters
        verdict = Diagnostic(OK, DIAG_NAME, "registered: residual 1.20 mm", {"residual_mm": "1.200"})
        failure = Diagnostic(ERROR, DIAG_NAME, "empty intraop cloud (0 points)")
        for diags in ([summary], [verdict], [summary], [failure]):
            link.on_diagnostics_msg(diagnostic_array(diags, 5, types))
        texts = [m.value for m in slicer.wait_for("RegistrationStatus", 2)]
        assert texts == ["OK: registered: residual 1.20 mm", "ERROR: empty intraop cloud (0 points)"]
    finally:
        slicer.close()


def test_the_pose_brings_the_cloud_of_its_stamp(link: SlicerLink, rng: np.random.Generator) -> None:
    slicer = Recorder.connect(link.bridge.endpoint.port)
    try:
        clouds = {stamp: rng.uniform(-0.05, 0.05, (50, 3)) for stamp in (10, 20, 30)}
        for stamp, points in clouds.items():
            msg = points_to_cloud(points, rosbags_types(), frame_id="camera", stamp_ns=stamp)
            link.on_intraop_cdr(bytes(typestore().serialize_cdr(msg, "sensor_msgs/msg/PointCloud2")))
        T = np.eye(4)
        T[:3, 3] = [1.0, 2.0, 3.0]
        link.on_pose_msg(pose_stamped(PoseOutput(20, "camera", "ct", T), rosbags_output_types()))
        assert_wire_equal(slicer.wait_for("CTToSensor")[0].value, expected_transform(T))
        cloud = slicer.wait_for("IntraopCloud")[0].value
        np.testing.assert_allclose(cloud.points[:50], (clouds[20] * 1000).astype(np.float32), atol=1e-4)
        link.on_pose_msg(pose_stamped(PoseOutput(99, "camera", "ct", T), rosbags_output_types()))  # no such cloud
        assert slicer.wait_for("CTToSensor", 2) and link.counters["clouds_missing"] == 1
    finally:
        slicer.close()


def test_bad_messages_are_counted_never_raised(link: SlicerLink) -> None:
    types = rosbags_output_types()
    link.on_intraop_cdr(b"\x00\x01\x00\x00garbage")
    T = np.eye(4)
    bad_pose = pose_stamped(PoseOutput(1, "camera", "ct", T), types)
    bad_pose.pose.orientation.w = 0.0  # a zero quaternion
    link.on_pose_msg(bad_pose)
    empty = points_to_cloud(np.zeros((0, 3)), rosbags_types(), frame_id="ct", stamp_ns=3)
    link.on_preop_msg(empty)
    sphere = _zero(typestore().types["visualization_msgs/msg/Marker"])
    sphere.type = 2  # a SPHERE, not a TRIANGLE_LIST
    link.on_mesh_msg(sphere)
    assert link.counters["bad_messages"] == 4 and link.counters["poses_sent"] == 0


def _zero(kind: type) -> object:
    """A rosbags message of `kind` with every field zero / empty (nested messages too)."""
    import dataclasses

    types = typestore().types
    values = {}
    for f in dataclasses.fields(kind):
        name = str(f.type)
        if name.startswith("ClassVar"):
            continue
        if name.startswith(("list[", "np.ndarray", "numpy")):
            values[f.name] = np.zeros(0, np.uint8) if name.startswith(("np", "numpy")) else []
        elif name in ("str", "bool", "int", "float"):
            values[f.name] = {"str": "", "bool": False, "int": 0, "float": 0.0}[name]
        else:
            values[f.name] = _zero(types[name.replace("__", "/")])
    return kind(**values)
