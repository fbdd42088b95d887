"""The non-rigid stage through the real graph: preop_loader_node (a mesh file) -> register_node (deform) ->
/registration/deformed_preop after the pose, real rclpy processes on an isolated domain.

The loader publishes the mesh (/preop/mesh) and the points sampled from it (/preop/points, same stamp);
register_node builds the elastic model on that mesh during the model's warm-up, publishes the rigid pose,
then the deformed preop surface and the `deform_*` diagnostics; with `deform` off nothing comes on that
topic and the pose and verdict are those of the deformed run. A malformed mesh marker is one ERROR.
"""

import time

import numpy as np
import pytest
from conftest import require_rclpy

rclpy = require_rclpy()

from builtin_interfaces.msg import Time  # noqa: E402
from geometry_msgs.msg import Point  # noqa: E402
from ros_support import clean_stderr, wait_for_fiducial_paths  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from visualization_msgs.msg import Marker  # noqa: E402

from liver_p2p_reg.config import Config  # noqa: E402
from liver_p2p_reg.livegraph.graph import (  # noqa: E402
    GraphProbe,
    NodeProcess,
    level_of,
    set_isolated_environment,
    stamp_ns,
    values_of,
)
from liver_p2p_reg.phantom.anatomy import make_liver  # noqa: E402
from liver_p2p_reg.phantom.dataset import make_case  # noqa: E402
from liver_p2p_reg.phantom.simulate import simulate_liver  # noqa: E402
from liver_p2p_reg.registration.deform import Deformation  # noqa: E402
from liver_p2p_reg.ros.messages import mesh_marker_mm  # noqa: E402
from liver_p2p_reg.ros.pointcloud2 import FLOAT32, cloud_to_points_m, cloud_to_points_mm, points_to_cloud  # noqa: E402
from liver_p2p_reg.ros.preop_loader_node import load_model_m, mesh_marker  # noqa: E402
from liver_p2p_reg.ros.rclpy_types import RCLPY_TYPES  # noqa: E402
from liver_p2p_reg.ros.topics import (  # noqa: E402
    TOPIC_DEFORMED_PREOP,
    TOPIC_INTRAOP,
    TOPIC_INTRAOP_FIDUCIALS,
    TOPIC_POSE,
    TOPIC_PREOP_MESH,
    TOPIC_REGISTERED,
    rclpy_qos,
)
from liver_p2p_reg.stream.core import NodeCore  # noqa: E402
from liver_p2p_reg.stream.deformation import stage_values  # noqa: E402
from liver_p2p_reg.stream.outputs import DIAG_NAME, ERROR, PREOP_DIAG_NAME  # noqa: E402

TYPES = RCLPY_TYPES.cloud
# a small elastic model (built in about a second) and an exact rigid pose from the fiducials
PARAMS = {"method": "procrustes", "deform": True, "deform_modes": 12, "deform_target_tets": 1500}
DEFORM_KEYS = set(stage_values(Deformation(True, "", np.eye(4)), None, 1.0, 1.0, 1.0))
STAMP_NS = 1_700_000_000_000_000_000


class DeformProbe(GraphProbe):
    """The harness's probe, recording the deformed preop surface too."""

    RECORDED = {**GraphProbe.RECORDED, TOPIC_DEFORMED_PREOP: PointCloud2}


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A small procedural liver as a mesh file (mm), its fiducials, and a deformed partial view of it."""
    import open3d as o3d

    tmp = tmp_path_factory.mktemp("deform_graph")
    sim = simulate_liver(7, 1, target_tets=1500, liver=make_liver(7, spacing_mm=5.0))
    c = make_case(sim, 0, 0.35, seed=1)
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(c["src_pcd"]), o3d.utility.Vector3iVector(c["src_triangles"])
    )
    assert o3d.io.write_triangle_mesh(str(tmp / "preop.ply"), mesh)
    np.save(tmp / "fid.npy", c["src_marker"])
    view = points_to_cloud(c["tgt_pcd"] * 1e-3, TYPES, frame_id="camera", stamp_ns=STAMP_NS)
    fiducials = points_to_cloud(c["tgt_marker"] * 1e-3, TYPES, frame_id="camera", stamp_ns=STAMP_NS)
    return {"dir": tmp, "view": view, "fiducials": fiducials}


def expected_output(case):
    """(the output, the welded mesh vertices (mm, ct)) register_node should publish for the frame, computed here
    from the same messages the graph carries."""
    path = str(case["dir"] / "preop.ply")
    preop = cloud_to_points_mm(points_to_cloud(load_model_m(path, "mm"), TYPES, frame_id="ct"))
    vertices, triangles = mesh_marker_mm(mesh_marker(path, "mm", "ct", Time(sec=1, nanosec=0)))
    core = NodeCore(Config(**PARAMS, mode="on_demand"))
    core.set_preop_mesh(vertices, triangles, "ct", 1)
    core.set_preop(preop, "ct", 1)
    core.set_preop_fiducials(
        cloud_to_points_mm(points_to_cloud(np.load(case["dir"] / "fid.npy") * 1e-3, TYPES, frame_id="ct"))
    )
    core.set_intraop_fiducials(cloud_to_points_mm(case["fiducials"]), STAMP_NS)
    core.on_intraop_points(cloud_to_points_mm(case["view"]), "camera", STAMP_NS)
    return core.reregister(), vertices


def attempts(probe, since=0):
    """Registration diagnostics (not the periodic status) since `since`."""
    return [s for s, _ in probe.diagnostics(since, DIAG_NAME) if "received_clouds" not in values_of(s)]


def test_register_node_publishes_the_deformed_preop_after_the_pose_only_with_deform_on(case, tmp_path):
    env = set_isolated_environment()
    probe = DeformProbe()
    register = NodeProcess("register_node", PARAMS, env=env, log_dir=tmp_path)
    loader = None
    try:
        assert probe.wait_for(lambda: "loaded in" in register.stderr() or not register.alive(), 120), register.stderr()
        assert probe.wait_for(lambda: probe.diagnostics(0, DIAG_NAME), 60), register.stderr()  # matched both ways
        assert probe.wait_for_subscriber(TOPIC_INTRAOP, 60)
        params = {"model_path": case["dir"] / "preop.ply", "fiducials_path": case["dir"] / "fid.npy"}
        loader = NodeProcess("preop_loader_node", params, env=env, log_dir=tmp_path)

        # the elastic model is built on the loader's mesh while the model warms up (or again when the mesh comes late)
        def on_mesh():
            found = [values_of(s) for s, _ in probe.diagnostics(0, PREOP_DIAG_NAME)]
            return [v for v in found if v.get("deform_surface") == "mesh" and v.get("deform_model") == "ready"]

        assert probe.wait_for(on_mesh, 120), register.stderr()
        # the oracle needs the model's fiducials (the loader's own latched topic, discovered on its own: under a
        # loaded suite they came after the mesh once) and the cloud's (another topic): let both arrive first, or
        # the cloud is registered before them and procrustes refuses it
        assert wait_for_fiducial_paths(probe, len(np.load(case["dir"] / "fid.npy"))), register.stderr()
        probe.publish(TOPIC_INTRAOP_FIDUCIALS, case["fiducials"])
        time.sleep(1.0)
        probe.publish(TOPIC_INTRAOP, case["view"])
        assert probe.wait_for(lambda: attempts(probe) and probe.count(TOPIC_DEFORMED_PREOP), 60), register.stderr()
        (pose,), (rigid,), (deformed,) = (probe.since(t) for t in (TOPIC_POSE, TOPIC_REGISTERED, TOPIC_DEFORMED_PREOP))
        assert deformed.received_s >= pose.received_s  # the rigid pose first
        assert stamp_ns(deformed.msg) == stamp_ns(pose.msg) == STAMP_NS == stamp_ns(rigid.msg)
        assert deformed.msg.header.frame_id == pose.msg.header.frame_id == "camera"
        assert [(f.name, f.datatype) for f in deformed.msg.fields] == [(c, FLOAT32) for c in "xyz"]
        (verdict,) = attempts(probe)
        values = values_of(verdict)
        assert DEFORM_KEYS <= set(values) and values["deform_applied"] == "true" and values["deform_reason"] == ""
        assert values["deform_surface"] == "mesh" and float(values["deform_ms"]) > 0
        assert values["deform_view"] == "frame" and int(values["deform_view_points"]) > 0  # not a survey: the frame
        assert float(values["deformed_error_bound_mm"]) > 0  # the deformed positions' own calibrated bound
        # the same arithmetic as the ROS-free core on the same messages (float32 metres on the wire)
        expected, vertices = expected_output(case)
        # on the loader's mesh: its welded vertices in their order (a /preop/mesh holder pairs them with its triangles)
        assert deformed.msg.width * deformed.msg.height == len(vertices) != rigid.msg.width * rigid.msg.height
        np.testing.assert_allclose(cloud_to_points_m(deformed.msg) * 1e3, expected.deformed_preop_mm, rtol=0, atol=1e-3)
        np.testing.assert_allclose(cloud_to_points_m(rigid.msg) * 1e3, expected.registered_preop_mm, rtol=0, atol=1e-3)
        T = expected.pose.T_sensor_ct_mm  # the rigid pose: how far the stage moved each vertex from it
        shift_mm = np.linalg.norm(cloud_to_points_m(deformed.msg) * 1e3 - (vertices @ T[:3, :3].T + T[:3, 3]), axis=1)
        assert 0.01 < shift_mm.max() < 25.0

        # deform off: the same pose and verdict, nothing on the deformed topic, no deform_* keys
        mark, n_deformed = probe.count("/diagnostics"), probe.count(TOPIC_DEFORMED_PREOP)
        assert all(r.successful for r in probe.set_parameters({"deform": False}))
        answer = probe.reregister()
        assert answer is not None and answer.success, register.stderr()
        off = probe.wait_for(lambda: attempts(probe, mark), 30)
        assert off and not DEFORM_KEYS & set(values_of(off[0]))
        assert (level_of(off[0]), off[0].message) == (level_of(verdict), verdict.message)
        second = probe.since(TOPIC_POSE)[-1].msg
        assert (second.pose.position, second.pose.orientation) == (pose.msg.pose.position, pose.msg.pose.orientation)
        time.sleep(1.0)
        assert probe.count(TOPIC_DEFORMED_PREOP) == n_deformed

        # a malformed mesh marker: one ERROR diagnostic and one ERROR line, and the node carries on
        bad = Marker(type=Marker.TRIANGLE_LIST, points=[Point(x=0.1, y=0.0, z=0.0)] * 4)
        bad.header.frame_id = "ct"
        mark = probe.count("/diagnostics")
        probe.node.create_publisher(Marker, TOPIC_PREOP_MESH, rclpy_qos(TOPIC_PREOP_MESH)).publish(bad)
        errors = probe.wait_for(
            lambda: [s for s, _ in probe.diagnostics(mark, PREOP_DIAG_NAME) if level_of(s) == ERROR]
        )
        assert errors and "bad /preop/mesh" in errors[0].message, register.stderr()
        lines = [line for line in clean_stderr(register.stderr()) if "/preop/mesh" in line]
        assert len(lines) == 1 and "[ERROR]" in lines[0], lines
        assert register.alive() and probe.reregister().success
    finally:
        if loader is not None:
            loader.stop()
        register.stop()
        probe.close()
