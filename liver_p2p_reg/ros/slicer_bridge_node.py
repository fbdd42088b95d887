"""rclpy adapter: slicer_bridge_node serves the registration to 3D Slicer over OpenIGTLink (SlicerLink does the work)."""

from __future__ import annotations

from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from visualization_msgs.msg import Marker

from liver_p2p_reg.igtl.bridge import SlicerBridge, open_endpoint
from liver_p2p_reg.igtl.link import SlicerLink
from liver_p2p_reg.ros.node_main import log_at, parameters_from, run_node
from liver_p2p_reg.ros.topics import (
    TOPIC_DEFORMED_PREOP,
    TOPIC_DIAGNOSTICS,
    TOPIC_INTRAOP,
    TOPIC_POSE,
    TOPIC_PREOP,
    TOPIC_PREOP_MESH,
    TOPIC_STRUCTURE_LABELS,
    TOPIC_STRUCTURES,
    rclpy_qos,
)
from liver_p2p_reg.slicer_config import SlicerConfig

STATUS_NAME = "liver_p2p_reg: slicer bridge"
STATUS_PERIOD_S = 1.0


def slicer_config_from_parameters(node: Node) -> SlicerConfig:
    """Declare one ROS parameter per SlicerConfig field (defaults from SlicerConfig) and read them."""
    return parameters_from(node, SlicerConfig, lambda f: f"{f.name}; see msg_docs/parameters_slicer_bridge.md")


class SlicerBridgeNode(Node):
    """Subscribes to the registration's inputs and outputs; never waits on Slicer (the endpoint has its own thread)."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("slicer_bridge_node", **node_kwargs)  # node_kwargs: e.g. parameter_overrides (tests)
        config = slicer_config_from_parameters(self)
        self.endpoint = open_endpoint(config, self._log)
        self.link = SlicerLink(SlicerBridge(config, self.endpoint), self._log)
        self.create_subscription(PointCloud2, TOPIC_PREOP, self.link.on_preop_msg, rclpy_qos(TOPIC_PREOP))
        self.create_subscription(Marker, TOPIC_PREOP_MESH, self.link.on_mesh_msg, rclpy_qos(TOPIC_PREOP_MESH))
        if config.cloud_rate_hz > 0:  # raw: decimated straight from the CDR bytes, no message object per cloud
            self.create_subscription(
                PointCloud2, TOPIC_INTRAOP, self.link.on_intraop_cdr, rclpy_qos(TOPIC_INTRAOP), raw=True
            )
        self.create_subscription(PoseStamped, TOPIC_POSE, self.link.on_pose_msg, rclpy_qos(TOPIC_POSE))
        # the structures moved by each pose, one POLYDATA per label (named by /preop/structure_labels)
        labels_qos = rclpy_qos(TOPIC_STRUCTURE_LABELS)
        self.create_subscription(String, TOPIC_STRUCTURE_LABELS, self.link.on_structure_labels_msg, labels_qos)
        structures_qos = rclpy_qos(TOPIC_STRUCTURES)
        self.create_subscription(PointCloud2, TOPIC_STRUCTURES, self.link.on_structures_msg, structures_qos)
        # the preop surface after the non-rigid stage (register_node's `deform`), on /preop/mesh's triangles
        deformed_qos = rclpy_qos(TOPIC_DEFORMED_PREOP)
        self.create_subscription(PointCloud2, TOPIC_DEFORMED_PREOP, self.link.on_deformed_msg, deformed_qos)
        diagnostics_qos = rclpy_qos(TOPIC_DIAGNOSTICS)
        self.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS, self.link.on_diagnostics_msg, diagnostics_qos)
        self.status_pub = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, diagnostics_qos)
        self.create_timer(STATUS_PERIOD_S, self._publish_status)
        where = f"listening on {config.host}:{self.endpoint.port}" if config.role == "server" else "connecting to"
        if config.role == "client":
            where += f" {config.host}:{config.port}"
        self.get_logger().info(
            f"OpenIGTLink {config.role} {where}: {config.transform_device} (TRANSFORM), "
            f"{config.model_device}, {config.deformed_model_device}, {config.cloud_device} "
            "and one per structure label (POLYDATA), "
            f"{config.status_device} (STRING); "
            f"ct frame in {config.ct_convention}"
        )

    def _log(self, level: int, text: str) -> None:
        log_at(self.get_logger(), level, text)

    def _publish_status(self) -> None:
        self.link.tick()  # a cloud the rate limit held back, if no newer pose came since
        stats = {**self.endpoint.stats(), **self.link.counters}
        peers = stats["peers"]
        status = DiagnosticStatus(
            level=bytes([0]),
            name=STATUS_NAME,
            message=f"{peers} OpenIGTLink peer{'s' if peers != 1 else ''} connected",
            hardware_id="liver_p2p_reg",
            values=[KeyValue(key=k, value=str(v)) for k, v in stats.items()],
        )
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.status_pub.publish(msg)

    def destroy_node(self) -> None:
        self.endpoint.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """`ros2 run liver_p2p_reg slicer_bridge_node --ros-args -p port:=18944`; the exit status.

    Bad parameters, a port taken or fastcrc missing: one fatal line and status 1.
    """
    return run_node(SlicerBridgeNode, "slicer_bridge_node", args, exit_process=False)


if __name__ == "__main__":
    raise SystemExit(main())
