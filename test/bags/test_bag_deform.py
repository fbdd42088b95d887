"""Bags carry the preop mesh (/preop/mesh); replay and the flight recorder with the non-rigid stage on (deform: true)."""

from pathlib import Path

import numpy as np
import pytest
import yaml
from ros_support import BAGS

from liver_p2p_reg.bags.flight_replay import read_recording, rerun_recording
from liver_p2p_reg.bags.io import MARKER, bag_topics, read_messages
from liver_p2p_reg.bags.make import START_NS, make_case_bag
from liver_p2p_reg.bags.mesh import decimated_mesh
from liver_p2p_reg.bags.replay import format_table, replay_bag
from liver_p2p_reg.config import Config
from liver_p2p_reg.registration.mechanics.solid import closed_solid
from liver_p2p_reg.ros.messages import mesh_marker_mm
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm
from liver_p2p_reg.ros.topics import TOPIC_DEFORMED_PREOP, TOPIC_DIAGNOSTICS, TOPIC_PREOP, TOPIC_PREOP_MESH

DEFORM_BAG = BAGS / "phantom_sim_02_vis0.36"  # the stage is applied on its first frames (bags/README.md)


def ellipsoid(subdivisions: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """A closed ellipsoid mesh (mm, liver-sized): 20 x 4^subdivisions triangles."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_icosahedron(1.0).subdivide_loop(subdivisions)
    vertices = np.asarray(mesh.vertices) / np.linalg.norm(np.asarray(mesh.vertices), axis=1, keepdims=True)
    return vertices * [90.0, 60.0, 45.0], np.asarray(mesh.triangles)


@pytest.fixture(scope="module")
def mesh_bag(tmp_path_factory):
    vertices, triangles = ellipsoid()
    target = vertices[vertices[:, 2] > 0] + [0.0, 0.0, 250.0]
    out = tmp_path_factory.mktemp("mesh") / "mesh_bag"
    return (
        make_case_bag(out, vertices, target, source_triangles=triangles, max_mesh_triangles=3000),
        vertices,
        triangles,
    )


def test_a_made_bag_carries_the_decimated_closed_preop_mesh_latched_with_the_models_stamp(mesh_bag):
    bag, vertices, triangles = mesh_bag
    assert len(triangles) == 20480 and bag_topics(bag)[TOPIC_PREOP_MESH] == (MARKER, 1)
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    qos = {t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"][0] for t in meta["topics_with_message_count"]}  # fmt: skip
    assert qos[TOPIC_PREOP_MESH]["durability"] == "transient_local"  # latched, as the loader publishes it
    messages = list(read_messages(bag, [TOPIC_PREOP_MESH, TOPIC_PREOP]))
    assert [m.topic for m in messages] == [TOPIC_PREOP_MESH, TOPIC_PREOP]  # the mesh first: one elastic model build
    mesh, points = messages[0].msg, messages[1].msg
    assert mesh.header.frame_id == points.header.frame_id == "ct"
    assert mesh.header.stamp == points.header.stamp and points.header.stamp.sec * 10**9 == START_NS
    welded, tris = mesh_marker_mm(mesh)
    assert 500 <= len(tris) <= 3000 and len(welded) < len(vertices)
    # still closed: the elastic model's voxel solid holds (nearly) the full mesh's volume
    full = closed_solid(vertices, triangles).volume_mm3
    assert abs(closed_solid(welded, tris).volume_mm3 - full) < 0.05 * full
    assert np.abs(np.linalg.norm(welded / [90.0, 60.0, 45.0], axis=1) - 1).max() < 0.1  # on the surface


def test_decimation_is_deterministic_and_leaves_a_small_mesh_as_it_is():
    vertices, triangles = ellipsoid(3)
    again = decimated_mesh(vertices, triangles, 400), decimated_mesh(vertices, triangles, 400)
    assert np.array_equal(again[0][0], again[1][0]) and np.array_equal(again[0][1], again[1][1])
    assert 100 <= len(again[0][1]) <= 400 and again[0][1].max() == len(again[0][0]) - 1  # no unused vertex
    kept = decimated_mesh(vertices, triangles, len(triangles))
    assert np.array_equal(kept[0], vertices) and np.array_equal(kept[1], triangles)


@pytest.fixture(scope="module")
def deform_replay(tmp_path_factory):
    """A bundled bag replayed (2 frames) with the stage on and a structure, into an output bag and a flight
    recording."""
    from liver_p2p_reg.bags.io import model_and_clouds
    from liver_p2p_reg.structures_io import Structure

    out = tmp_path_factory.mktemp("deform")
    preop_mm = model_and_clouds(DEFORM_BAG, metres=True)[0] * 1e3
    tumour = Structure("tumour", 0.5 * (preop_mm[:30] + preop_mm.mean(axis=0)), 0)  # halfway to the centre
    row = replay_bag(
        DEFORM_BAG, Config(deform=True), out_path=out / "out", record_path=out / "rec.mcap", max_frames=2,
        structures=[tumour],
    )  # fmt: skip
    return row, out


def test_replay_with_deform_writes_the_deformed_preop_and_the_deformed_tre(deform_replay):
    row, out = deform_replay
    assert row.deform and row.registered == 2 and row.deform_applied == 2
    assert np.isfinite(row.deformed_rms_tre_mm) and row.deformed_rms_tre_mm < row.rms_tre_mm
    assert all(f["deform_applied"] and np.isfinite(f["deformed_rms_tre_mm"]) for f in row.per_frame)
    welded, _ = mesh_marker_mm(next(read_messages(DEFORM_BAG, [TOPIC_PREOP_MESH])).msg)
    clouds = [m.msg for m in read_messages(out / "out", [TOPIC_DEFORMED_PREOP])]  # the real bag, read back
    assert len(clouds) == 2 and all(c.header.frame_id == "camera" for c in clouds)
    assert len(cloud_to_points_mm(clouds[0])) == len(welded)  # the stage ran on the mesh: its vertices, deformed
    values = [
        {kv.key: kv.value for kv in s.values}
        for m in read_messages(out / "out", [TOPIC_DIAGNOSTICS])
        for s in m.msg.status
    ]
    registered = [v for v in values if "deform_applied" in v]
    assert len(registered) == 2 and all(v["deform_surface"] == "mesh" for v in registered)
    assert any(v.get("deform_model") == "ready" and v.get("deform_surface") == "mesh" for v in values)
    table = format_table([row])
    assert "deformed RMS-TRE mm (mean)" in table and "2/2" in table.splitlines()[-1]


def test_the_default_table_has_no_deform_columns(deform_replay):
    row, _ = deform_replay
    row_off = type(row)(**{**row.__dict__, "deform": False})
    assert "deform" not in format_table([row_off]) and "deform applied" in format_table([row_off, row])


def test_the_flight_recorder_keeps_the_mesh_and_the_deformed_surface_and_re_runs_them_bitwise(deform_replay):
    _, out = deform_replay
    recorded: dict[str, list] = {}
    for item in read_recording(out / "rec.mcap"):
        recorded.setdefault(item.topic, []).append(item)
    assert len(recorded[TOPIC_PREOP_MESH]) == 1 and len(recorded[TOPIC_DEFORMED_PREOP]) == 2
    mesh, _ = mesh_marker_mm(recorded[TOPIC_PREOP_MESH][0].msg)
    original, _ = mesh_marker_mm(next(read_messages(DEFORM_BAG, [TOPIC_PREOP_MESH])).msg)
    assert np.array_equal(mesh, original)  # the exact millimetres the node kept
    commits = [item.values for item in recorded["/flight_recorder/registration"]]
    assert all(c["deformation"]["deform_applied"] == "true" and c["deformed_preop_sha256"] for c in commits)
    assert float(commits[0]["deformation"]["deformed_rms_tre_mm"]) > 0
    report = rerun_recording(out / "rec.mcap")
    assert report.ok and report.identical + report.roundoff == 2 and report.deformed == 2
    assert report.deformed_identical + report.deformed_roundoff == 2, report  # round-off: another summation order
    assert "deformed preop surfaces bitwise identical" in report.summary()
    # the structure's deformed positions and their bounds, placed again as the node placed them
    assert report.structures == 2 and report.structures_identical + report.structures_roundoff == 2, report


def test_a_re_run_whose_deformed_surface_differs_is_reported(deform_replay, tmp_path):
    import json

    _, out = deform_replay
    raw = (out / "rec.mcap").read_bytes()
    items = list(read_recording(out / "rec.mcap"))
    first = json.loads(next(i.msg.data for i in items if i.topic == "/flight_recorder/registration"))
    digest = first["deformed_preop_sha256"].encode()
    surface = bytes(next(i.msg for i in items if i.topic == TOPIC_DEFORMED_PREOP).data)
    head = surface[:64]  # the first points' float32 metres: once in the file (uncompressed chunks)
    assert raw.count(digest) == 1 and raw.count(head) == 1
    moved = np.frombuffer(head, dtype="<f4").copy()
    moved[0] += 0.01  # 10 mm on one point's x
    # a digest that does not match but a recorded surface that does: the digest alone is not a difference
    only_digest = tmp_path / "digest.mcap"
    only_digest.write_bytes(raw.replace(digest, b"0" * len(digest), 1))  # same length: the file stays readable
    report = rerun_recording(only_digest)
    assert report.ok and report.deformed_identical == 1 and report.deformed_roundoff == 1, report
    assert "1 more within round-off (0.001 mm)" in report.summary()
    # the surface itself recorded 10 mm elsewhere: reported
    changed = tmp_path / "changed.mcap"
    changed.write_bytes(only_digest.read_bytes().replace(head, moved.tobytes(), 1))
    report = rerun_recording(changed)
    assert not report.ok and report.deformed_identical == 1 and report.deformed_roundoff == 0
    assert "deformed preop surface differs (not bitwise the same)" in report.differences[0]


def test_bundled_bags_carry_the_mesh():
    bags = sorted(p for p in Path(BAGS).iterdir() if (p / "metadata.yaml").is_file())
    assert bags and all(bag_topics(b).get(TOPIC_PREOP_MESH) == (MARKER, 1) for b in bags)
