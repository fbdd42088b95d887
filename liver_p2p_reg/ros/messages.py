"""ROS messages <-> the stream core, for rclpy or rosbags objects: input clouds into NodeCore, its outputs as messages."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.ros.pointcloud2 import MessageTypes, cloud_to_points_mm, make_header, stamp_to_ns
from liver_p2p_reg.stream.core import NodeCore
from liver_p2p_reg.stream.outputs import DIAG_NAME, ERROR, PREOP_DIAG_NAME, WARN, Diagnostic, PoseOutput


def feed_preop_msg(core: NodeCore, msg: Any, *, warm_up: bool = True) -> Diagnostic:
    """A /preop/points PointCloud2 (metres) into the core; its diagnostic."""
    try:
        points = cloud_to_points_mm(msg)
    except InputError as exc:
        return Diagnostic(ERROR, PREOP_DIAG_NAME, f"bad /preop/points: {exc}")
    return core.set_preop(points, msg.header.frame_id, stamp_to_ns(msg.header.stamp), warm_up=warm_up)


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
