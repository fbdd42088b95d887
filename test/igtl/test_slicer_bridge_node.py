"""slicer_bridge_node under real rclpy: a bundled bag's registration, played on an isolated domain, reaches a Slicer stand-in.

The bag is first replayed through the node core (its output bag then holds the poses and
diagnostics the registration published); this process plays those messages as serialized CDR
through rclpy publishers with the documented QoS to the node, started as its own process.
"""

from __future__ import annotations

import dataclasses
import os
import random
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import require_rclpy
from igtl_support import Recorder, assert_wire_equal, expected_transform, hung_up

rclpy = require_rclpy()

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import Point, PoseStamped  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from visualization_msgs.msg import Marker  # noqa: E402

from liver_p2p_reg.bags.io import typestore  # noqa: E402
from liver_p2p_reg.bags.replay import replay_bag  # noqa: E402
from liver_p2p_reg.config import Config  # noqa: E402
from liver_p2p_reg.igtl.link import level_of, pose_to_T_mm  # noqa: E402
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm, stamp_to_ns  # noqa: E402
from liver_p2p_reg.ros.slicer_bridge_node import STATUS_NAME  # noqa: E402
from liver_p2p_reg.ros.topics import rclpy_qos  # noqa: E402
from liver_p2p_reg.slicer_config import SlicerConfig  # noqa: E402
from liver_p2p_reg.stream.outputs import DIAG_NAME, LEVEL_NAMES, PREOP_DIAG_NAME  # noqa: E402

BAG = Path(__file__).resolve().parents[2] / "bags" / "insilico_L9000001_D00_T007_random"
TYPES = {
    "/preop/points": PointCloud2,
    "/preop/mesh": Marker,
    "/intraop/points": PointCloud2,
    "/registration/pose": PoseStamped,
    "/registration/deformed_preop": PointCloud2,
    "/diagnostics": DiagnosticArray,
}
MAX_CLOUD_POINTS = SlicerConfig().max_cloud_points


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The registration of a bundled bag: its preop model and, per frame, cloud + pose + diagnostics as CDR."""
    out = tmp_path_factory.mktemp("slicer_node") / "replayed"
    replay_bag(BAG, Config(method="icp"), out_path=out, max_frames=3)  # the quickest method: any pose will do
    raw: list[tuple[str, bytes]] = []
    with AnyReader([out], default_typestore=typestore()) as reader:
        wanted = [c for c in reader.connections if c.topic in TYPES]
        raw = [(c.topic, bytes(data)) for c, _, data in reader.messages(connections=wanted)]
    preop = next(data for topic, data in raw if topic == "/preop/points")
    groups: list[dict] = []
    for topic, data in raw:
        if topic == "/intraop/points":
            groups.append({"/intraop/points": data})
        elif topic in ("/registration/pose", "/diagnostics") and groups:
            groups[-1].setdefault(topic, data)
    registered = [g for g in groups if "/registration/pose" in g]
    assert len(registered) == 3, [list(g) for g in groups]
    return {"preop": preop, "frames": registered, "bag": out}


def isolated_env() -> dict[str, str]:
    return {"ROS_DOMAIN_ID": str(random.SystemRandom().randint(1, 100)), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}


def start_node(env: dict[str, str], *params: str) -> tuple[subprocess.Popen, list[str]]:
    args = [sys.executable, "-m", "liver_p2p_reg.ros.slicer_bridge_node", "--ros-args"]
    for param in ("host:=127.0.0.1", "port:=0", *params):
        args += ["-p", param]
    full_env = {**os.environ, **env, "RCUTILS_COLORIZED_OUTPUT": "0", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=full_env)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True).start()  # keeps the pipe drained
    return proc, lines


def bridge_port(proc: subprocess.Popen, lines: list[str], timeout_s: float = 90.0) -> int:
    """The port a bridge started with port:=0 says it listens on."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and proc.poll() is None:
        found = (re.search(r"listening on 127\.0\.0\.1:(\d+)", line) for line in lines)
        port = next((int(m.group(1)) for m in found if m), None)
        if port:
            return port
        time.sleep(0.05)
    raise AssertionError("the bridge did not say its port:\n" + "".join(lines))


class Player:
    """An rclpy node of this process that publishes CDR bytes and listens to /diagnostics."""

    def __init__(self, env: dict[str, str]) -> None:
        os.environ.update(env)
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("slicer_test_player", context=self.context)
        self.publishers = {t: self.node.create_publisher(TYPES[t], t, rclpy_qos(t)) for t in TYPES}
        self.statuses: list = []  # the bridge's own
        self.registration: list = []  # register_node's registration statuses, periodic ones included
        self.models: list = []  # register_node's preop-model statuses
        self.poses: list = []
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._diag, 10)
        self.node.create_subscription(PoseStamped, "/registration/pose", self.poses.append, 10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # context shut down by close()
            pass

    def _diag(self, msg: DiagnosticArray) -> None:
        self.statuses += [s for s in msg.status if s.name == STATUS_NAME]
        self.registration += [s for s in msg.status if s.name == DIAG_NAME]
        self.models += [s for s in msg.status if s.name == PREOP_DIAG_NAME]

    def bridge_stats(self) -> dict[str, str]:
        return {kv.key: kv.value for kv in self.statuses[-1].values} if self.statuses else {}

    def wait_for_bridge(self, timeout_s: float = 60.0) -> None:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if all(p.get_subscription_count() > 0 for t, p in self.publishers.items() if t != "/diagnostics"):
                return
            time.sleep(0.05)
        raise AssertionError("slicer_bridge_node did not subscribe to the topics")

    def publish(self, topic: str, data) -> None:
        self.publishers[topic].publish(data)

    def play(self, frame: dict, pause_s: float = 0.3) -> None:
        for topic in ("/intraop/points", "/registration/pose", "/diagnostics"):
            self.publish(topic, frame[topic])
            time.sleep(0.05)
        time.sleep(pause_s)

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self.thread.join(2.0)


@pytest.fixture(scope="module")
def graph():
    env = isolated_env()
    proc, lines = start_node(env, "cloud_rate_hz:=100.0")
    player = None
    try:
        port = bridge_port(proc, lines)
        player = Player(env)
        player.wait_for_bridge()
        yield {"proc": proc, "lines": lines, "port": port, "player": player}
    finally:
        if player is not None:
            player.close()
        proc.send_signal(signal.SIGINT)
        try:
            code = proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = None
    assert code == 0, "".join(lines)
    bad = [line for line in lines if not line.startswith("[INFO]") and line.strip()]
    assert bad == [], "".join(lines)  # no traceback, no warning beyond the expected garbage line


def decode(topic: str, data: bytes):
    return typestore().deserialize_cdr(data, {"/intraop/points": "sensor_msgs/msg/PointCloud2",
                                              "/registration/pose": "geometry_msgs/msg/PoseStamped",
                                              "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
                                              "/preop/points": "sensor_msgs/msg/PointCloud2"}[topic])  # fmt: skip


def registration_texts(diagnostics: bytes) -> list[str]:
    msg = decode("/diagnostics", diagnostics)
    return [f"{LEVEL_NAMES[level_of(s.level)]}: {s.message}" for s in msg.status if s.name == DIAG_NAME]


def test_bag_through_rclpy_reaches_slicer(graph: dict, frames: dict) -> None:
    player: Player = graph["player"]
    slicer = Recorder.connect(graph["port"])
    try:
        player.publish("/preop/points", frames["preop"])
        model = slicer.wait_for("PreopModel")[0].value
        preop = cloud_to_points_mm(decode("/preop/points", frames["preop"]))
        assert len(model.polygons) == len(preop)  # 19134 points, each drawn as a triangle
        np.testing.assert_allclose(model.points[: len(preop)], (preop * [-1, -1, 1]).astype(np.float32), atol=0)
        expected_texts = []
        for i, frame in enumerate(frames["frames"]):
            player.play(frame)
            pose = decode("/registration/pose", frame["/registration/pose"])
            transform = slicer.wait_for("CTToSensor", i + 1)[i]
            # the published pose, in mm, composed with LPS -> RAS: equal within float32's 1e-6
            assert_wire_equal(transform.value, expected_transform(pose_to_T_mm(pose.pose)))
            assert transform.timestamp_s == pytest.approx(stamp_to_ns(pose.header.stamp) * 1e-9, abs=1e-6)
            cloud = slicer.wait_for("IntraopCloud", i + 1)[i].value
            full = cloud_to_points_mm(decode("/intraop/points", frame["/intraop/points"]))
            kept = full[np.linspace(0, len(full) - 1, MAX_CLOUD_POINTS).round().astype(int)]
            np.testing.assert_allclose(cloud.points[:MAX_CLOUD_POINTS], kept.astype(np.float32), atol=0)
            expected_texts += registration_texts(frame["/diagnostics"])
        texts = [m.value for m in slicer.wait_for("RegistrationStatus", len(expected_texts))]
        assert texts == expected_texts and len(texts) == 3
        assert all(re.match(r"(OK|WARN|ERROR): ", t) for t in texts)
    finally:
        slicer.close()


def test_late_joiner_and_reconnect_get_the_current_state(graph: dict, frames: dict) -> None:
    player: Player = graph["player"]
    last = frames["frames"][-1]
    player.publish("/preop/points", frames["preop"])
    player.play(last)
    late = Recorder.connect(graph["port"])
    late.wait_for("PreopModel")
    pose = decode("/registration/pose", last["/registration/pose"])
    assert_wire_equal(late.wait_for("CTToSensor")[0].value, expected_transform(pose_to_T_mm(pose.pose)))
    assert late.wait_for("RegistrationStatus")[0].value == registration_texts(last["/diagnostics"])[-1]
    late.close()
    again = Recorder.connect(graph["port"])  # reconnects: the state again, then the stream
    try:
        again.wait_for("PreopModel")
        again.wait_for("CTToSensor")
        first = frames["frames"][0]
        player.play(first)
        pose = decode("/registration/pose", first["/registration/pose"])
        assert_wire_equal(again.wait_for("CTToSensor", 2)[1].value, expected_transform(pose_to_T_mm(pose.pose)))
    finally:
        again.close()


def test_garbage_from_a_client_does_not_harm_the_node(graph: dict, frames: dict) -> None:
    player: Player = graph["player"]
    good = Recorder.connect(graph["port"])
    try:
        before = len(good.of("CTToSensor"))
        player.play(frames["frames"][0])
        good.wait_for("CTToSensor", before + 1)
        rude = socket.create_connection(("127.0.0.1", graph["port"]), timeout=10)
        rude.sendall(os.urandom(8192))
        assert hung_up(rude)
        rude.close()
        frame = frames["frames"][1]
        before = len(good.of("CTToSensor"))
        player.play(frame)
        pose = decode("/registration/pose", frame["/registration/pose"])
        received = good.wait_for("CTToSensor", before + 1)[-1].value
        assert_wire_equal(received, expected_transform(pose_to_T_mm(pose.pose)))
        assert graph["proc"].poll() is None
        end = time.monotonic() + 10
        while player.bridge_stats().get("garbage_disconnections") != "1" and time.monotonic() < end:
            time.sleep(0.1)
        assert player.bridge_stats()["garbage_disconnections"] == "1"
        assert any("not OpenIGTLink" in line for line in graph["lines"])
        graph["lines"][:] = [line for line in graph["lines"] if "not OpenIGTLink" not in line]
    finally:
        good.close()


def test_mesh_from_the_loader_is_sent_as_a_mesh(graph: dict) -> None:
    player: Player = graph["player"]
    # a tetrahedron-shaped "liver" (mm in the ct frame): 4 faces of the mesh topic, then its points
    corners_mm = np.array([[0, 0, 0], [80, 0, 0], [0, 60, 0], [0, 0, 40]], dtype=float)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    stamp = player.node.get_clock().now().to_msg()
    mesh = Marker(type=Marker.TRIANGLE_LIST, action=Marker.ADD)
    mesh.header.frame_id, mesh.header.stamp = "ct", stamp
    mesh.points = [Point(x=x * 1e-3, y=y * 1e-3, z=z * 1e-3) for x, y, z in corners_mm[faces.reshape(-1)]]
    slicer = Recorder.connect(graph["port"])
    try:
        player.publish("/preop/mesh", mesh)
        end = time.monotonic() + 20  # first the state (an earlier test's model, if any), then the mesh
        while not any(len(m.value.polygons) == 4 for m in slicer.of("PreopModel")) and time.monotonic() < end:
            time.sleep(0.05)
        model = slicer.of("PreopModel")[-1].value
        assert len(model.points) == 4 and len(model.polygons) == 4
        received = {tuple(np.round(model.points[c], 3).ravel()) for c in model.polygons}
        flipped = corners_mm * [-1, -1, 1]
        assert received == {tuple(np.round(flipped[f], 3).ravel()) for f in faces}
    finally:
        slicer.close()


def test_the_deformed_preop_goes_out_on_the_meshs_triangles(graph: dict) -> None:
    """/registration/deformed_preop (sensor frame): DeformedModel on the last /preop/mesh's triangles when it has
    as many points as that mesh has welded vertices, else as points; not flipped to RAS (it is no ct frame)."""
    from liver_p2p_reg.ros.pointcloud2 import points_to_cloud
    from liver_p2p_reg.ros.rclpy_types import RCLPY_TYPES

    player: Player = graph["player"]
    corners_mm = np.array([[0, 0, 0], [70, 0, 0], [0, 50, 0], [0, 0, 30]], dtype=float)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    mesh = Marker(type=Marker.TRIANGLE_LIST, action=Marker.ADD)
    mesh.header.frame_id, mesh.header.stamp = "ct", player.node.get_clock().now().to_msg()
    mesh.points = [Point(x=x * 1e-3, y=y * 1e-3, z=z * 1e-3) for x, y, z in corners_mm[faces.reshape(-1)]]
    welded = np.unique(corners_mm, axis=0)  # the documented vertex order: the corners (mm) welded and sorted
    triangles = [[int(np.flatnonzero((welded == corners_mm[i]).all(axis=1))[0]) for i in f] for f in faces]
    deformed_mm = welded + [[5.0, -3.0, 120.0]] + np.arange(12).reshape(4, 3) * 0.25  # where the stage put them
    slicer = Recorder.connect(graph["port"])
    try:
        player.publish("/preop/mesh", mesh)
        end = time.monotonic() + 20  # the mesh taken (its triangles kept) before the deformed cloud comes
        while not any(len(m.value.polygons) == 4 and len(m.value.points) == 4 for m in slicer.of("PreopModel")):
            assert time.monotonic() < end, "the mesh never reached Slicer"
            time.sleep(0.05)
        cloud = points_to_cloud(
            deformed_mm * 1e-3, RCLPY_TYPES.cloud, frame_id="camera", stamp_ns=1_700_000_003 * 10**9
        )
        player.publish("/registration/deformed_preop", cloud)
        model = slicer.wait_for("DeformedModel")[0]
        np.testing.assert_allclose(model.value.points, deformed_mm, rtol=0, atol=1e-4)  # sensor frame, as sent
        assert [c.tolist() for c in model.value.polygons] == triangles
        assert model.timestamp_s == pytest.approx(1_700_000_003.0, abs=1e-6)
        five = np.vstack([deformed_mm, [[1.0, 2.0, 3.0]]])  # not the mesh's vertex count: as points, no crash
        player.publish(
            "/registration/deformed_preop", points_to_cloud(five * 1e-3, RCLPY_TYPES.cloud, frame_id="camera")
        )
        points = slicer.wait_for("DeformedModel", 2)[1].value
        assert len(points.points) == 15 and len(points.polygons) == 5
        np.testing.assert_allclose(points.points[:5], five, rtol=0, atol=1e-4)
        end = time.monotonic() + 10
        while player.bridge_stats().get("deformed_sent") != "2" and time.monotonic() < end:
            time.sleep(0.1)
        assert player.bridge_stats()["deformed_sent"] == "2"
    finally:
        slicer.close()


def test_the_loaders_mesh_file_reaches_slicer_as_a_mesh(graph: dict, tmp_path: Path) -> None:
    from liver_p2p_reg.cloud_io import load_mesh
    from liver_p2p_reg.o3d import o3d_module

    o3d = o3d_module()
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=12)
    mesh.vertices = o3d.utility.Vector3dVector(np.asarray(mesh.vertices) * [90.0, 60.0, 45.0] + [10.0, -20.0, 30.0])
    mesh.compute_triangle_normals()
    stl = tmp_path / "liver.stl"
    assert o3d.io.write_triangle_mesh(str(stl), mesh)
    vertices, triangles = load_mesh(stl)
    slicer = Recorder.connect(graph["port"])
    loader_args = [
        sys.executable,
        "-m",
        "liver_p2p_reg.ros.preop_loader_node",
        "--ros-args",
        "-p",
        f"model_path:={stl}",
    ]
    env = {**os.environ, "RCUTILS_COLORIZED_OUTPUT": "0"}
    loader = subprocess.Popen(loader_args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        end = time.monotonic() + 60
        while time.monotonic() < end:
            models = [m.value for m in slicer.of("PreopModel")]
            if models and len(models[-1].polygons) == len(triangles):
                break
            time.sleep(0.05)
        time.sleep(1.0)  # its /preop/points (same stamp) must not replace the mesh
        last = slicer.of("PreopModel")[-1].value
        assert len(last.polygons) == len(triangles)
        # the same triangles, corners in the same order (the bridge shares the corners the STL repeats), in RAS
        from scipy.spatial import cKDTree

        received = np.stack([last.points[c].ravel() for c in last.polygons])
        expected = (vertices[triangles] * [-1, -1, 1]).reshape(-1, 9)
        distance, index = cKDTree(received).query(expected)
        assert distance.max() < 1e-3 and len(set(index.tolist())) == len(triangles)
        assert len(last.points) == len(np.unique(np.round(vertices, 6), axis=0))
    finally:
        slicer.close()
        loader.send_signal(signal.SIGINT)
        out = loader.communicate(timeout=20)[0]
    assert loader.returncode == 0 and "on /preop/mesh" in out, out


def test_every_setting_is_a_described_ros_parameter(graph: dict) -> None:
    from rcl_interfaces.srv import DescribeParameters, GetParameters

    player: Player = graph["player"]
    names = [f.name for f in dataclasses.fields(SlicerConfig)]

    def call(kind: type, service: str, request):
        client = player.node.create_client(kind, f"/slicer_bridge_node/{service}")
        try:
            assert client.wait_for_service(timeout_sec=30)
            future = client.call_async(request)
            done = threading.Event()
            future.add_done_callback(lambda _: done.set())
            assert done.wait(30)
            return future.result()
        finally:
            player.node.destroy_client(client)

    values = call(GetParameters, "get_parameters", GetParameters.Request(names=names)).values
    got = dict(zip(names, values, strict=True))
    assert got["port"].integer_value == 0 and got["ct_convention"].string_value == "LPS"  # started with port:=0
    assert got["cloud_rate_hz"].double_value == 100.0 and got["max_cloud_points"].integer_value == MAX_CLOUD_POINTS
    descriptors = call(DescribeParameters, "describe_parameters", DescribeParameters.Request(names=names)).descriptors
    assert [d.name for d in descriptors] == names
    assert all("parameters_slicer_bridge.md" in d.description and d.dynamic_typing for d in descriptors)


def test_with_the_real_register_node(tmp_path: Path) -> None:
    """register_node registers the bundled bag's frames; the bridge forwards its poses and verdicts, not its summaries."""
    env = isolated_env()
    bridge, lines = start_node(env)
    full_env = {**os.environ, **env, "RCUTILS_COLORIZED_OUTPUT": "0"}
    register = subprocess.Popen(
        [sys.executable, "-m", "liver_p2p_reg.ros.register_node", "--ros-args", "-p", "method:=icp"],
        stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, env=full_env,
    )  # fmt: skip
    player = Player(env)
    slicer = None
    try:
        end = time.monotonic() + 120
        while player.publishers["/intraop/points"].get_subscription_count() < 2 and time.monotonic() < end:
            time.sleep(0.05)  # both nodes listen
        slicer = Recorder.connect(bridge_port(bridge, lines))
        with AnyReader([BAG], default_typestore=typestore()) as reader:
            wanted = [c for c in reader.connections if c.topic in ("/preop/points", "/intraop/points")]
            raw = [(c.topic, bytes(data)) for c, _, data in reader.messages(connections=wanted)]
        player.publish("/preop/points", next(d for t, d in raw if t == "/preop/points"))
        slicer.wait_for("PreopModel")
        # register_node must hold the model before the first cloud (a cloud before it is an ERROR verdict);
        # its model status reaching this node also says its /diagnostics are discovered by now
        while not player.models and time.monotonic() < end:
            time.sleep(0.05)
        assert player.models, "register_node never reported the preop model"
        # the bridge's /registration/pose subscription known to the graph (this node's and the bridge's): a pose
        # published before register_node has matched it is lost (volatile), and once a clean-clone suite saw none
        while player.node.count_subscribers("/registration/pose") < 2 and time.monotonic() < end:
            time.sleep(0.05)
        time.sleep(0.5)  # the bridge's match to register_node's /diagnostics and pose, discovered alongside
        clouds = [d for t, d in raw if t == "/intraop/points"][:2]
        for i, cloud in enumerate(clouds):
            player.publish("/intraop/points", cloud)
            deadline = time.monotonic() + 120
            while len(player.poses) <= i and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.6)  # register_node's max_rate_hz is 2
        slicer.wait_for("CTToSensor", len(player.poses))
        time.sleep(2.5)  # register_node's 1 Hz summaries come meanwhile: they must not become STRINGs
        assert len(player.poses) == 2
        for pose in player.poses:
            stamp_s = stamp_to_ns(pose.header.stamp) * 1e-9
            sent = [m for m in slicer.of("CTToSensor") if abs(m.timestamp_s - stamp_s) < 1e-6]
            assert len(sent) == 1
            assert_wire_equal(sent[0].value, expected_transform(pose_to_T_mm(pose.pose)))
        verdicts = [s for s in player.registration if not any(kv.key == "received_clouds" for kv in s.values)]
        summaries = [s for s in player.registration if any(kv.key == "received_clouds" for kv in s.values)]
        assert len(verdicts) >= 2 and summaries
        texts = [f"{LEVEL_NAMES[level_of(s.level)]}: {s.message}" for s in verdicts]
        assert [m.value for m in slicer.of("RegistrationStatus")] == texts
    finally:
        if slicer is not None:
            slicer.close()
        player.close()
        for proc in (bridge, register):
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()


def test_bad_parameters_and_a_taken_port_are_one_fatal_line() -> None:
    env = isolated_env()
    with socket.create_server(("127.0.0.1", 0)) as taken:
        for param in ("ct_convention:=RAI", f"port:={taken.getsockname()[1]}"):
            proc, lines = start_node(env, param)
            try:
                code = proc.wait(60)
            finally:
                if proc.poll() is None:
                    proc.kill()
            time.sleep(0.2)  # the reader thread drains the last lines
            fatal = [line for line in lines if line.startswith("[FATAL]")]
            assert code == 1 and len(fatal) == 1, "".join(lines)
            assert "Traceback" not in "".join(lines)
