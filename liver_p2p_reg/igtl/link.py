"""ROS-free glue from ROS messages (rclpy or rosbags objects, or CDR bytes) and node-core outputs to the Slicer bridge.

slicer_bridge_node (rclpy), `liver-p2p replay --slicer` (rosbags) and the tests drive this same
object. Bad input messages are counted and logged, never raised: the link must outlive them. The
deformed preop surface goes out on the last /preop/mesh's triangles when it has as many points as that
mesh has welded vertices (the non-rigid stage ran on it: register_node welds it alike), else as points.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from liver_p2p_reg.bags.io import POINTCLOUD2, typestore
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.igtl.bridge import SlicerBridge
from liver_p2p_reg.ros.messages import mesh_marker_mm, parse_structure_labels
from liver_p2p_reg.ros.pointcloud2 import MM_PER_M, cloud_to_points_mm, cloud_to_structures, stamp_to_ns
from liver_p2p_reg.ros.topics import (
    TOPIC_DEFORMED_PREOP,
    TOPIC_INTRAOP,
    TOPIC_POSE,
    TOPIC_PREOP,
    TOPIC_PREOP_MESH,
    TOPIC_STRUCTURE_LABELS,
    TOPIC_STRUCTURES,
)
from liver_p2p_reg.stream.outputs import DIAG_NAME, LEVEL_NAMES, CoreOutput
from liver_p2p_reg.stream.structures import fallback_label

LOG = logging.getLogger("liver_p2p_reg.slicer")
# NodeCore.status() adds these counters to the last registration's diagnostic for its periodic
# (1 Hz) summary; a status carrying them repeats a registration already forwarded.
PERIODIC_STATUS_KEY = "received_clouds"
KEPT_CLOUDS = 64  # decimated intraop clouds kept to pair with the pose of the same stamp (2 s at 30 Hz)


def decimated_points_mm(msg: Any, max_points: int) -> np.ndarray:
    """x/y/z of at most `max_points` evenly spread points of a PointCloud2 (mm), decoding only those."""
    width, height = int(msg.width), int(msg.height)
    n = width * height
    if n <= max_points:
        return cloud_to_points_mm(msg)
    point_step = int(msg.point_step)
    row_step = max(int(msg.row_step), width * point_step)
    index = np.linspace(0, n - 1, max_points).round().astype(np.int64)
    raw = np.frombuffer(memoryview(msg.data).cast("B"), dtype=np.uint8)
    if raw.size < (height - 1) * row_step + width * point_step:
        raise InputError(f"PointCloud2 data is truncated: {raw.size} bytes for {height}x{width} points")
    if row_step == width * point_step:  # no row padding: whole points are rows of one 2-D view
        rows = raw[: n * point_step].reshape(n, point_step)[index]
    else:
        starts = (index // width) * row_step + (index % width) * point_step
        rows = raw[starts[:, None] + np.arange(point_step)]
    view = SimpleNamespace(
        fields=msg.fields,
        height=1,
        width=max_points,
        point_step=point_step,
        row_step=point_step * max_points,
        is_bigendian=msg.is_bigendian,
        data=rows.reshape(-1),
    )
    return cloud_to_points_mm(view)


def pose_to_T_mm(pose: Any) -> np.ndarray:
    """geometry_msgs/Pose (metres, quaternion) -> 4x4 T (mm)."""
    q = pose.orientation
    quaternion = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    position = np.array([pose.position.x, pose.position.y, pose.position.z], dtype=np.float64)
    if not (np.isfinite(quaternion).all() and np.isfinite(position).all()) or not np.linalg.norm(quaternion) > 0:
        raise InputError("pose has a non-finite position or a zero/non-finite quaternion")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(quaternion).as_matrix()
    T[:3, 3] = position * MM_PER_M
    return T


def level_of(level: Any) -> int:
    """DiagnosticStatus.level as an int (rclpy gives bytes, rosbags an int)."""
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)


class SlicerLink:
    """Feeds a SlicerBridge from the registration's topics: model, clouds, poses, diagnostics."""

    def __init__(self, bridge: SlicerBridge, log: Callable[[int, str], None] | None = None) -> None:
        self.bridge = bridge
        self.config = bridge.config
        self._log = log or (lambda level, text: LOG.log(level, text))
        self._lock = threading.Lock()
        self._clouds: OrderedDict[int, np.ndarray] = OrderedDict()  # stamp -> decimated points (sensor, mm)
        self._mesh_stamp: int | None = None  # header stamp of the last mesh sent (its points need no resend)
        # the last mesh's triangles and vertex count: a deformed surface of as many points is that mesh deformed
        self._mesh: tuple[np.ndarray, int] | None = None
        self._deformed_kind = ""  # how the last deformed model went (mesh or points): logged when it changes
        self._last_cloud_s = -np.inf
        self._deferred: tuple[np.ndarray, int] | None = None  # a pose's cloud held back by cloud_rate_hz
        self._structure_names: dict[int, str] = {}  # label id -> name (/preop/structure_labels)
        self.counters = {
            "models_sent": 0,
            "poses_sent": 0,
            "clouds_sent": 0,
            "clouds_missing": 0,  # a pose whose cloud was not received (best-effort QoS) or no longer kept
            "clouds_superseded": 0,  # held back by cloud_rate_hz, then replaced by a newer pose's
            "statuses_sent": 0,
            "structures_sent": 0,  # POLYDATA messages, one per structure and pose
            "deformed_sent": 0,  # the deformed model, once per applied non-rigid stage
            "bad_messages": 0,
        }

    # ---------------------------------------------------------------- ROS messages
    def on_preop_msg(self, msg: Any) -> None:
        """/preop/points: sent as the model unless the mesh of the same model (same stamp) was."""
        stamp = stamp_to_ns(msg.header.stamp)
        if self._mesh_stamp == stamp:
            return

        def send() -> None:
            self._send_model(cloud_to_points_mm(msg), None, stamp)
            self._mesh = None  # another model: the mesh held is not its surface (its own mesh may follow)

        self._guard(TOPIC_PREOP, send)

    def on_mesh_msg(self, msg: Any) -> None:
        """/preop/mesh (visualization_msgs/Marker TRIANGLE_LIST, metres): the model as a mesh."""

        def send() -> None:
            vertices, triangles = mesh_marker_mm(msg)  # welded; InputError when it is not a TRIANGLE_LIST mesh
            stamp = stamp_to_ns(msg.header.stamp)
            self._send_model(vertices, triangles, stamp)
            self._mesh_stamp = stamp
            self._mesh = (triangles, len(vertices))  # welded as register_node welds it: same vertex order

        self._guard(TOPIC_PREOP_MESH, send)

    def on_intraop_msg(self, msg: Any) -> None:
        """/intraop/points: decimated now (bounded work and memory) and kept until its pose arrives."""

        def keep() -> None:
            points = decimated_points_mm(msg, self.config.max_cloud_points)
            with self._lock:
                self._clouds[stamp_to_ns(msg.header.stamp)] = points
                while len(self._clouds) > KEPT_CLOUDS:
                    self._clouds.popitem(last=False)

        self._guard(TOPIC_INTRAOP, keep)

    def on_intraop_cdr(self, raw: bytes) -> None:
        """/intraop/points as serialized CDR bytes (an rclpy raw subscription skips deserializing clouds)."""
        try:
            msg = typestore().deserialize_cdr(raw, POINTCLOUD2)
        except Exception as exc:  # rosbags raises its own error types for malformed CDR
            self._bad(TOPIC_INTRAOP, f"not a PointCloud2 ({type(exc).__name__})")
            return
        self.on_intraop_msg(msg)

    def on_pose_msg(self, msg: Any) -> None:
        """/registration/pose: the CTToSensor TRANSFORM, then the cloud that was registered."""
        self._guard(TOPIC_POSE, lambda: self.send_pose(pose_to_T_mm(msg.pose), stamp_to_ns(msg.header.stamp)))

    def on_structure_labels_msg(self, msg: Any) -> None:
        """/preop/structure_labels (std_msgs/String, JSON): the names of the structures' label ids."""

        def keep() -> None:
            names, _ = parse_structure_labels(msg.data)
            self._structure_names = dict(enumerate(names))

        self._guard(TOPIC_STRUCTURE_LABELS, keep)

    def on_structures_msg(self, msg: Any) -> None:
        """/registration/structures (sensor frame, label_id per point): a POLYDATA per structure, named by its label."""

        def send() -> None:
            points_m, ids, _ = cloud_to_structures(msg)
            groups = [(int(i), points_m[ids == i] * MM_PER_M) for i in np.unique(ids)]
            labels = [self._structure_names.get(i) or fallback_label(i) for i, _ in groups]
            self.send_structures(labels, [points for _, points in groups], stamp_to_ns(msg.header.stamp))

        self._guard(TOPIC_STRUCTURES, send)

    def on_deformed_msg(self, msg: Any) -> None:
        """/registration/deformed_preop (sensor frame): the deformed model, on the last mesh's triangles if it fits."""
        self._guard(
            TOPIC_DEFORMED_PREOP, lambda: self.send_deformed(cloud_to_points_mm(msg), stamp_to_ns(msg.header.stamp))
        )

    def on_diagnostics_msg(self, msg: Any) -> None:
        """/diagnostics: a STRING for each registration attempt (not for the periodic summary)."""
        stamp = stamp_to_ns(msg.header.stamp)
        for status in msg.status:
            if status.name != DIAG_NAME or any(kv.key == PERIODIC_STATUS_KEY for kv in status.values):
                continue
            level = LEVEL_NAMES.get(level_of(status.level), str(level_of(status.level)))
            self.bridge.send_status(level, status.message, stamp)
            self.counters["statuses_sent"] += 1

    # ---------------------------------------------------------------- bag replay (bags/replay.py observer)
    def on_input(self, topic: str, msg: Any) -> None:
        if topic == TOPIC_PREOP:
            self.on_preop_msg(msg)
        elif topic == TOPIC_PREOP_MESH:  # a bag carrying the mesh: the model as a mesh, its triangles kept
            self.on_mesh_msg(msg)
        elif topic == TOPIC_INTRAOP:
            self.on_intraop_msg(msg)

    def on_output(self, output: CoreOutput) -> None:
        stamp = output.pose.stamp_ns if output.pose is not None else 0
        if output.pose is not None:
            self._guard("pose", lambda: self.send_pose(output.pose.T_sensor_ct_mm, stamp))
            placed = output.structures
            if placed:  # where the non-rigid stage put them when it was applied
                positions = [s.current_position_mm for s in placed]
                self._guard("structures", lambda: self.send_structures([s.label for s in placed], positions, stamp))
            deformed = output.deformed_preop_mm
            if deformed is not None:  # only when the non-rigid stage was applied
                self._guard("deformed preop", lambda: self.send_deformed(deformed, stamp))
        for diag in output.diagnostics:
            if diag.name == DIAG_NAME:
                self.bridge.send_status(diag.level_name, diag.message, stamp)
                self.counters["statuses_sent"] += 1

    # ---------------------------------------------------------------- sending
    def send_pose(self, T_sensor_ct_mm: np.ndarray, stamp_ns: int) -> None:
        self.bridge.send_pose(T_sensor_ct_mm, stamp_ns)  # first: the latency that matters
        self.counters["poses_sent"] += 1
        with self._lock:
            cloud = self._clouds.get(stamp_ns)
            self.counters["clouds_superseded"] += self._deferred is not None
            self.counters["clouds_missing"] += cloud is None
            self._deferred = None if cloud is None else (cloud, stamp_ns)
        self.tick()

    def send_structures(self, labels: list[str], points_sensor_mm: list[np.ndarray], stamp_ns: int) -> None:
        """Each structure (sensor frame, mm) as a POLYDATA under a device named after its label."""
        for device, points in zip(self.bridge.structure_devices(labels), points_sensor_mm, strict=True):
            self.bridge.send_structure(device, points, stamp_ns)
            self.counters["structures_sent"] += 1

    def send_deformed(self, points_sensor_mm: np.ndarray, stamp_ns: int) -> None:
        """The deformed surface (sensor frame, mm) on the held mesh's triangles if it has as many points, else as points."""
        points = np.asarray(points_sensor_mm, dtype=np.float64).reshape(-1, 3)
        mesh = self._mesh
        triangles = mesh[0] if mesh is not None and mesh[1] == len(points) else None
        sent = self.bridge.send_deformed_model(points, triangles, stamp_ns)
        self.counters["deformed_sent"] += 1
        kind = f"mesh of {len(triangles)} triangles" if triangles is not None else "points"
        if kind != self._deformed_kind:  # once per change, not per frame
            self._deformed_kind = kind
            device = self.config.deformed_model_device
            self._log(logging.INFO, f"deformed preop model sent to Slicer as {device}: {sent} {kind}")

    def tick(self, force: bool = False) -> None:
        """Send the last pose's cloud if cloud_rate_hz allows it now (or `force`); call it now and then."""
        now = time.monotonic()
        rate_hz = self.config.cloud_rate_hz
        with self._lock:
            if self._deferred is None or rate_hz == 0 or (not force and now - self._last_cloud_s < 1.0 / rate_hz):
                return
            (cloud, stamp_ns), self._deferred = self._deferred, None
            self._last_cloud_s = now
        self.bridge.send_cloud(cloud, stamp_ns)
        self.counters["clouds_sent"] += 1

    def _send_model(self, points_mm: np.ndarray, triangles: np.ndarray | None, stamp_ns: int) -> None:
        sent = self.bridge.send_model(points_mm, triangles, stamp_ns)
        self.counters["models_sent"] += 1
        kind = f"mesh of {len(triangles)} triangles" if triangles is not None else "points"
        self._log(logging.INFO, f"preop model sent to Slicer as {self.config.model_device}: {sent} {kind}")

    def _guard(self, topic: str, action: Callable[[], None]) -> None:
        try:
            action()
        except (InputError, ValueError) as exc:
            self._bad(topic, str(exc))

    def _bad(self, topic: str, reason: str) -> None:
        self.counters["bad_messages"] += 1
        self._log(logging.WARNING, f"ignoring {topic} message: {reason}")
