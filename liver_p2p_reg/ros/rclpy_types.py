"""rclpy's message classes for the binding-neutral conversions of ros.messages (RCLPY_TYPES), shared by the nodes."""

from __future__ import annotations

import array

from builtin_interfaces.msg import Duration, Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Transform, TransformStamped, Vector3
from sensor_msgs.msg import CompressedImage, PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MeshFile

from liver_p2p_reg.ros.messages import MarkerTypes, OutputTypes
from liver_p2p_reg.ros.pointcloud2 import MessageTypes

RCLPY_TYPES = OutputTypes(
    cloud=MessageTypes(PointCloud2, PointField, Header, Time, wrap_bytes=lambda raw: array.array("B", raw)),
    PoseStamped=PoseStamped,
    Pose=Pose,
    Point=Point,
    Quaternion=Quaternion,
    TransformStamped=TransformStamped,
    Transform=Transform,
    Vector3=Vector3,
    DiagnosticArray=DiagnosticArray,
    DiagnosticStatus=DiagnosticStatus,
    KeyValue=KeyValue,
    level=lambda level: bytes([level]),  # DiagnosticStatus.level is a `byte` field: bytes in rclpy
)
RCLPY_MARKER_TYPES = MarkerTypes(
    RCLPY_TYPES.cloud, Marker, Point, Pose, Quaternion, Vector3, ColorRGBA, Duration, CompressedImage, MeshFile
)
