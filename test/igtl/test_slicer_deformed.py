"""The deformed preop model to Slicer: a POLYDATA of its own, sensor frame, on the /preop/mesh's triangles.

The surface comes from NodeCore's non-rigid stage run on a procedural liver's mesh (real arithmetic), through
the link's two paths: the bag replay's observer (on_input, on_output) and slicer_bridge_node's callbacks
(/preop/mesh, /registration/deformed_preop as ROS messages, here rosbags objects).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from igtl_support import STAGE_STAMP_NS, Recorder, deformed_stage

from liver_p2p_reg.bags.io import rosbags_types
from liver_p2p_reg.igtl.bridge import SlicerBridge, open_endpoint
from liver_p2p_reg.igtl.link import SlicerLink
from liver_p2p_reg.ros.pointcloud2 import points_to_cloud
from liver_p2p_reg.ros.topics import TOPIC_PREOP, TOPIC_PREOP_MESH
from liver_p2p_reg.slicer_config import SlicerConfig

MAX_MODEL_POINTS = 3000  # below the model's points: the points fallback is decimated


@pytest.fixture(scope="module")
def stage():
    return deformed_stage()


@pytest.fixture
def served():
    config = SlicerConfig(host="127.0.0.1", port=0, max_model_points=MAX_MODEL_POINTS, point_size_mm=1.0)
    endpoint = open_endpoint(config)
    link = SlicerLink(SlicerBridge(config, endpoint))
    slicer = Recorder.connect(endpoint.port)
    assert endpoint.wait_for_peers(1, 10.0)  # live from here: every message, not only each device's latest
    yield link, slicer
    slicer.close()
    endpoint.close()


def rigidly_moved(points_mm: np.ndarray, T: np.ndarray) -> np.ndarray:
    return points_mm @ T[:3, :3].T + T[:3, 3]


def test_the_replayed_stage_goes_to_slicer_as_the_mesh_deformed(stage, served) -> None:
    link, slicer = served
    output = stage.output
    assert len(output.deformed_preop_mm) == len(stage.vertices_mm) < len(stage.points_mm)
    link.on_input(TOPIC_PREOP_MESH, stage.marker)  # what replay_bag hands its observer for every message read
    assert len(slicer.wait_for("PreopModel")[0].value.polygons) == len(stage.triangles)
    link.on_output(output)
    (received,) = slicer.wait_for("DeformedModel")
    model = received.value
    assert received.type_name == "POLYDATA" and model.vertices == 0
    # the deformed vertices as they are (sensor frame: no RAS flip, no CTToSensor), in the welded order ...
    np.testing.assert_array_equal(model.points, output.deformed_preop_mm.astype(np.float32))
    # ... on the mesh's own triangles: the deformed mesh
    assert [p.tolist() for p in model.polygons] == stage.triangles.tolist()
    assert received.timestamp_s == pytest.approx(STAGE_STAMP_NS * 1e-9, abs=1e-6)  # the pose's stamp
    # the stage moved it off the rigid pose (where PreopModel under CTToSensor shows the model)
    rigid = rigidly_moved(stage.vertices_mm, output.pose.T_sensor_ct_mm)
    shift_mm = np.linalg.norm(model.points - rigid, axis=1)
    assert 0.01 < shift_mm.max() < 25.0
    assert link.counters["deformed_sent"] == 1 and link.counters["bad_messages"] == 0


def test_a_surface_that_is_not_the_meshs_goes_as_points(stage, served) -> None:
    """The stage on the surface rebuilt from /preop/points (or another model's mesh held): never those triangles."""
    link, slicer = served
    link.on_input(TOPIC_PREOP_MESH, stage.marker)
    slicer.wait_for("PreopModel")
    on_points = stage.output.result.deformation.deformed_position_mm(stage.points_mm)  # the points' count, not V's
    link.on_output(dataclasses.replace(stage.output, deformed_preop_mm=on_points))
    model = slicer.wait_for("DeformedModel")[0].value
    kept = on_points[np.linspace(0, len(on_points) - 1, MAX_MODEL_POINTS).round().astype(np.int64)]
    assert len(model.points) == 3 * MAX_MODEL_POINTS and len(model.polygons) == MAX_MODEL_POINTS  # drawn as points
    np.testing.assert_array_equal(model.points[:MAX_MODEL_POINTS], kept.astype(np.float32))
    assert link.counters["deformed_sent"] == 1 and link.counters["bad_messages"] == 0
    # another model's /preop/points: the mesh held is not its surface, even for a cloud of its vertex count
    other = points_to_cloud(stage.points_mm * 1e-3, rosbags_types(), frame_id="ct", stamp_ns=99)
    link.on_input(TOPIC_PREOP, other)
    slicer.wait_for("PreopModel", 2)
    link.on_output(stage.output)
    again = slicer.wait_for("DeformedModel", 2)[1].value
    assert len(again.points) == 3 * MAX_MODEL_POINTS and len(again.polygons) == MAX_MODEL_POINTS


def test_the_live_topics_pair_the_deformed_cloud_with_the_meshs_triangles(stage, served) -> None:
    """slicer_bridge_node's callbacks: /preop/mesh, then /registration/deformed_preop (float32 metres)."""
    link, slicer = served
    output, types = stage.output, rosbags_types()
    cloud = points_to_cloud(output.deformed_preop_mm * 1e-3, types, frame_id="camera", stamp_ns=STAGE_STAMP_NS)
    link.on_deformed_msg(cloud)  # before any mesh: as points
    first = slicer.wait_for("DeformedModel")[0].value
    assert len(stage.vertices_mm) > MAX_MODEL_POINTS  # decimated like any model without mesh
    assert len(first.points) == 3 * MAX_MODEL_POINTS and len(first.polygons) == MAX_MODEL_POINTS
    link.on_mesh_msg(stage.marker)
    slicer.wait_for("PreopModel")
    link.on_deformed_msg(cloud)
    model = slicer.wait_for("DeformedModel", 2)[1].value
    np.testing.assert_allclose(model.points, output.deformed_preop_mm, rtol=0, atol=1e-4)  # via float32 metres
    assert [p.tolist() for p in model.polygons] == stage.triangles.tolist()
    assert link.counters["deformed_sent"] == 2
    # a cloud of no finite point, an empty one: counted and logged, never raised, nothing sent
    nan_cloud = points_to_cloud(np.full((len(stage.vertices_mm), 3), np.nan), types, frame_id="camera", stamp_ns=7)
    link.on_deformed_msg(nan_cloud)
    link.on_deformed_msg(points_to_cloud(np.zeros((0, 3)), types, frame_id="camera", stamp_ns=8))
    assert link.counters["bad_messages"] == 2 and link.counters["deformed_sent"] == 2


def test_a_mesh_vertex_that_is_not_finite_is_one_bad_message(stage, served) -> None:
    """As many points as the mesh has vertices, one of them NaN: the triangles cannot skip it, so nothing is sent."""
    link, _ = served
    link.on_mesh_msg(stage.marker)
    broken = stage.output.deformed_preop_mm.copy()
    broken[3] = np.nan
    link.on_output(dataclasses.replace(stage.output, deformed_preop_mm=broken))
    assert link.counters["bad_messages"] == 1 and link.counters["deformed_sent"] == 0
