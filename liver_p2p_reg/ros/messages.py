"""Build the output messages (pose, transform, diagnostics) from core outputs, for rclpy or rosbags classes."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from liver_p2p_reg.ros.pointcloud2 import MessageTypes, make_header
from liver_p2p_reg.stream.core import Diagnostic, PoseOutput


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


def rosbags_output_types() -> OutputTypes:
    """Output message classes from the rosbags Jazzy typestore."""
    from liver_p2p_reg.bags.io import rosbags_types, typestore

    t = typestore().types
    return OutputTypes(
        cloud=rosbags_types(),
        PoseStamped=t["geometry_msgs/msg/PoseStamped"],
        Pose=t["geometry_msgs/msg/Pose"],
        Point=t["geometry_msgs/msg/Point"],
        Quaternion=t["geometry_msgs/msg/Quaternion"],
        TransformStamped=t["geometry_msgs/msg/TransformStamped"],
        Transform=t["geometry_msgs/msg/Transform"],
        Vector3=t["geometry_msgs/msg/Vector3"],
        DiagnosticArray=t["diagnostic_msgs/msg/DiagnosticArray"],
        DiagnosticStatus=t["diagnostic_msgs/msg/DiagnosticStatus"],
        KeyValue=t["diagnostic_msgs/msg/KeyValue"],
        level=int,
    )


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
