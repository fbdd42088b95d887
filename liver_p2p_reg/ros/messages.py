"""ROS messages <-> the stream core, for rclpy or rosbags objects: input clouds into NodeCore, its outputs as messages."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.ros.pointcloud2 import (
    M_PER_MM,
    MM_PER_M,
    MessageTypes,
    cloud_to_points_mm,
    cloud_to_structures,
    make_header,
    stamp_to_ns,
    structures_to_cloud,
)
from liver_p2p_reg.ros.topics import TOPIC_PREOP_MESH, TOPIC_PREOP_STRUCTURES, TOPIC_STRUCTURE_LABELS
from liver_p2p_reg.stream.core import NodeCore
from liver_p2p_reg.stream.deformation import MAX_MESH_TRIANGLES
from liver_p2p_reg.stream.outputs import DIAG_NAME, ERROR, PREOP_DIAG_NAME, WARN, Diagnostic, PoseOutput
from liver_p2p_reg.structures_io import PlacedStructure, Structure, stacked_placement, stacked_points

MARKER_TRIANGLE_LIST = 11  # visualization_msgs/Marker.TRIANGLE_LIST


def feed_preop_msg(core: NodeCore, msg: Any, *, warm_up: bool = True) -> Diagnostic:
    """A /preop/points PointCloud2 (metres) into the core; its diagnostic."""
    try:
        points = cloud_to_points_mm(msg)
    except InputError as exc:
        return Diagnostic(ERROR, PREOP_DIAG_NAME, f"bad /preop/points: {exc}")
    return core.set_preop(points, msg.header.frame_id, stamp_to_ns(msg.header.stamp), warm_up=warm_up)


def mesh_marker_mm(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """(welded vertices (V, 3) mm, triangles (F, 3) int64) of a /preop/mesh Marker TRIANGLE_LIST (three `points`
    per triangle, metres, in its header's frame; pose and scale are not applied: the loader's are identity and 1).
    Equal corners become one vertex. InputError (one line) when the marker is not such a mesh."""
    if int(msg.type) != MARKER_TRIANGLE_LIST:
        raise InputError(f"marker type {msg.type} is not TRIANGLE_LIST ({MARKER_TRIANGLE_LIST})")
    if len(msg.points) > 3 * MAX_MESH_TRIANGLES:  # before welding: seconds of the executor's time per million
        raise InputError(f"{len(msg.points) // 3} triangles (more than {MAX_MESH_TRIANGLES}); decimate the mesh")
    corners = np.array([(p.x, p.y, p.z) for p in msg.points], dtype=np.float64).reshape(-1, 3) * MM_PER_M
    if len(corners) == 0 or len(corners) % 3:
        raise InputError(f"{len(corners)} points (a positive multiple of 3 needed)")
    if not np.isfinite(corners).all():
        raise InputError("non-finite point coordinates")
    vertices, corner_vertex = np.unique(corners, axis=0, return_inverse=True)
    return vertices, corner_vertex.reshape(-1, 3).astype(np.int64)


@dataclass(frozen=True)
class MarkerTypes:
    """The classes a visualization_msgs/Marker is built of, in one binding (rclpy or rosbags, which wants every field)."""

    cloud: MessageTypes  # Header, Time and how uint8[] data is stored
    Marker: type
    Point: type
    Pose: type
    Quaternion: type
    Vector3: type
    ColorRGBA: type
    Duration: type
    CompressedImage: type
    MeshFile: type


PREOP_MESH_RGBA = (0.8, 0.45, 0.35, 1.0)


def triangle_list_marker(
    vertices_m: np.ndarray, triangles: np.ndarray, types: MarkerTypes, frame_id: str, stamp_ns: int
) -> Any:
    """/preop/mesh: a Marker TRIANGLE_LIST of these triangles (three `points` per triangle, metres, in `frame_id`),
    identity pose, scale 1, what `mesh_marker_mm` reads back; the loader and the bags build it here."""
    corners = np.asarray(vertices_m, dtype=np.float64)[np.asarray(triangles, dtype=np.int64).reshape(-1)]
    empty = types.cloud.wrap_bytes(b"")
    r, g, b, a = PREOP_MESH_RGBA
    return types.Marker(
        header=make_header(types.cloud, frame_id, stamp_ns),
        ns="preop",
        id=0,
        type=MARKER_TRIANGLE_LIST,
        action=0,  # ADD
        pose=types.Pose(
            position=types.Point(x=0.0, y=0.0, z=0.0), orientation=types.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
        ),
        scale=types.Vector3(x=1.0, y=1.0, z=1.0),
        color=types.ColorRGBA(r=r, g=g, b=b, a=a),
        lifetime=types.Duration(sec=0, nanosec=0),
        frame_locked=True,
        points=[types.Point(x=x, y=y, z=z) for x, y, z in corners.tolist()],
        colors=[],
        texture_resource="",
        texture=types.CompressedImage(header=make_header(types.cloud, "", 0), format="", data=empty),
        uv_coordinates=[],
        text="",
        mesh_resource="",
        mesh_file=types.MeshFile(filename="", data=empty),
        mesh_use_embedded_materials=False,
    )


def feed_preop_mesh_msg(core: NodeCore, msg: Any) -> Diagnostic:
    """A /preop/mesh Marker into the core (the non-rigid stage's surface); an ERROR diagnostic when it is not a mesh."""
    try:
        vertices, triangles = mesh_marker_mm(msg)
        return core.set_preop_mesh(vertices, triangles, msg.header.frame_id, stamp_to_ns(msg.header.stamp))
    except InputError as exc:
        return Diagnostic(ERROR, PREOP_DIAG_NAME, f"bad {TOPIC_PREOP_MESH}: {exc}; ignored")


def _feed_fiducials(
    store: Callable[[np.ndarray, int], None], msg: Any, diag_name: str, topic: str
) -> Diagnostic | None:
    """Fiducials of a PointCloud2 into `store(points_mm, stamp_ns)`; a WARN diagnostic when they cannot be used."""
    try:
        store(cloud_to_points_mm(msg), stamp_to_ns(msg.header.stamp))
    except InputError as exc:
        return Diagnostic(WARN, diag_name, f"ignoring bad {topic}: {exc}")
    return None


def feed_preop_fiducials_msg(core: NodeCore, msg: Any) -> Diagnostic | None:
    """A /preop/fiducials PointCloud2 into the core; a WARN diagnostic when it cannot be used."""
    return _feed_fiducials(core.set_preop_fiducials, msg, PREOP_DIAG_NAME, "/preop/fiducials")


def feed_intraop_fiducials_msg(core: NodeCore, msg: Any) -> Diagnostic | None:
    """A /intraop/fiducials PointCloud2 into the core; a WARN diagnostic when it cannot be used."""
    return _feed_fiducials(core.set_intraop_fiducials, msg, DIAG_NAME, "/intraop/fiducials")


def feed_intraop_msg(core: NodeCore, msg: Any, now_s: float | None = None) -> list[Diagnostic]:
    """A /intraop/points PointCloud2 into the core; O(1): it is decoded only when registered."""
    return core.on_intraop_cloud(msg.header.frame_id, stamp_to_ns(msg.header.stamp), lambda: decode_cloud(msg), now_s)


def feed_structures_msg(core: NodeCore, msg: Any) -> Diagnostic | None:
    """A /preop/structures PointCloud2 (metres, label_id per point) into the core; a WARN diagnostic when unusable."""
    try:
        points_m, label_ids, _ = cloud_to_structures(msg)
        core.structures.set_points(points_m * MM_PER_M, label_ids, stamp_to_ns(msg.header.stamp))
    except InputError as exc:
        return Diagnostic(WARN, PREOP_DIAG_NAME, f"ignoring bad {TOPIC_PREOP_STRUCTURES}: {exc}")
    return None


def feed_structure_labels_msg(core: NodeCore, text: str) -> Diagnostic | None:
    """The JSON of a /preop/structure_labels std_msgs/String into the core; a WARN diagnostic when unusable."""
    try:
        names, stamp_ns = parse_structure_labels(text)
    except InputError as exc:
        return Diagnostic(WARN, PREOP_DIAG_NAME, f"ignoring bad {TOPIC_STRUCTURE_LABELS}: {exc}")
    core.structures.set_names(names, stamp_ns)
    return None


def structure_labels_json(structures: Sequence[Structure], stamp_ns: int) -> str:
    """The /preop/structure_labels text: {"labels": [name per label id], "stamp_ns": the structures' stamp}."""
    names = [""] * (max((s.label_id for s in structures), default=-1) + 1)
    for s in structures:
        names[s.label_id] = s.label
    return json.dumps({"labels": names, "stamp_ns": int(stamp_ns)})


def parse_structure_labels(text: str) -> tuple[list[str], int | None]:
    """(names, stamp_ns or None) of a /preop/structure_labels JSON text; InputError when it is not one."""
    try:
        data = json.loads(text)
    except (ValueError, RecursionError) as exc:  # "[" * 200000 overflowed the parser's recursion: a crash
        raise InputError(f"not JSON ({str(exc) or type(exc).__name__})") from None
    names = data.get("labels") if isinstance(data, dict) else None
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise InputError('expected {"labels": [string, ...], "stamp_ns": int}')
    stamp = data.get("stamp_ns")
    if stamp is not None and (not isinstance(stamp, int) or isinstance(stamp, bool)):
        raise InputError(f"stamp_ns must be an integer, got {stamp!r}")
    return names, stamp


def preop_structures_cloud(structures: Sequence[Structure], types: MessageTypes, frame_id: str, stamp_ns: int) -> Any:
    """/preop/structures: every structure's points (preop frame, metres) with its label_id (empty: none)."""
    points, ids = stacked_points(structures)
    return structures_to_cloud(points * M_PER_MM, ids, types, frame_id=frame_id, stamp_ns=stamp_ns)


def registered_structures_cloud(
    structures: Sequence[PlacedStructure], types: MessageTypes, frame_id: str, stamp_ns: int
) -> Any:
    """/registration/structures: the structures moved into the sensor frame (metres; their deformed positions
    when the non-rigid stage was applied), label_id and error_bound (m; of the positions given)."""
    ids, points, bounds = stacked_placement(structures)
    return structures_to_cloud(
        points * M_PER_MM, ids, types, frame_id=frame_id, stamp_ns=stamp_ns, error_bound_m=bounds * M_PER_MM
    )


def decode_cloud(msg: Any) -> tuple[np.ndarray, int]:
    """(finite points in mm, raw point count width x height) of a PointCloud2; InputError when unreadable."""
    n_raw = int(msg.width) * int(msg.height)
    return cloud_to_points_mm(msg), n_raw


@dataclass(frozen=True)
class OutputTypes:
    """Message classes of one binding; `level` converts an int level (rclpy wants bytes)."""

    cloud: MessageTypes
    PoseStamped: type
    Pose: type
    Point: type
    Quaternion: type
    TransformStamped: type
    Transform: type
    Vector3: type
    DiagnosticArray: type
    DiagnosticStatus: type
    KeyValue: type
    level: Callable[[int], Any]


def pose_stamped(pose: PoseOutput, types: OutputTypes) -> Any:
    """geometry_msgs/PoseStamped: pose of the ct frame in the sensor frame (metres)."""
    x, y, z = (float(v) for v in pose.translation_m)
    qx, qy, qz, qw = (float(v) for v in pose.quaternion_xyzw)
    return types.PoseStamped(
        header=make_header(types.cloud, pose.frame_id, pose.stamp_ns),
        pose=types.Pose(position=types.Point(x=x, y=y, z=z), orientation=types.Quaternion(x=qx, y=qy, z=qz, w=qw)),
    )


def transform_stamped(pose: PoseOutput, types: OutputTypes) -> Any:
    """geometry_msgs/TransformStamped sensor <- ct (header.frame_id = sensor, child = ct)."""
    x, y, z = (float(v) for v in pose.translation_m)
    qx, qy, qz, qw = (float(v) for v in pose.quaternion_xyzw)
    return types.TransformStamped(
        header=make_header(types.cloud, pose.frame_id, pose.stamp_ns),
        child_frame_id=pose.child_frame_id,
        transform=types.Transform(
            translation=types.Vector3(x=x, y=y, z=z), rotation=types.Quaternion(x=qx, y=qy, z=qz, w=qw)
        ),
    )


def diagnostic_array(diagnostics: list[Diagnostic], stamp_ns: int, types: OutputTypes) -> Any:
    """diagnostic_msgs/DiagnosticArray from plain diagnostics."""
    status = [
        types.DiagnosticStatus(
            level=types.level(d.level),
            name=d.name,
            message=d.message,
            hardware_id=d.hardware_id,
            values=[types.KeyValue(key=k, value=str(v)) for k, v in d.values.items()],
        )
        for d in diagnostics
    ]
    return types.DiagnosticArray(header=make_header(types.cloud, "", stamp_ns), status=status)
