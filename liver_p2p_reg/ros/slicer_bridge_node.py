"""rclpy adapter: slicer_bridge_node serves the registration to 3D Slicer over OpenIGTLink (SlicerLink does the work)."""

from __future__ import annotations

import dataclasses
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import Marker

from liver_p2p_reg.bags.make import TOPIC_INTRAOP, TOPIC_PREOP
from liver_p2p_reg.config import SlicerConfig
from liver_p2p_reg.errors import LiverP2PError
from liver_p2p_reg.igtl.bridge import SlicerBridge, open_endpoint
from liver_p2p_reg.igtl.link import SlicerLink
from liver_p2p_reg.ros.rcl_log import log_at

LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
TOPIC_MESH = "/preop/mesh"
STATUS_NAME = "liver_p2p_reg: slicer bridge"
STATUS_PERIOD_S = 1.0


def slicer_config_from_parameters(node: Node) -> SlicerConfig:
    """Declare one ROS parameter per SlicerConfig field (defaults from SlicerConfig) and read them."""
    defaults = SlicerConfig()
    values = {}
    for f in dataclasses.fields(SlicerConfig):
        # a descriptor each (rclpy writes the name into the one it gets); dynamic typing: `-p cloud_rate_hz:=2`
        # (an integer) is coerced by SlicerConfig instead of rejected
        descriptor = ParameterDescriptor(description=f"{f.name}; see msg_docs/parameters_slicer_bridge.md")
        descriptor.dynamic_typing = True
        node.declare_parameter(f.name, getattr(defaults, f.name), descriptor)
        values[f.name] = node.get_parameter(f.name).value
    return SlicerConfig.from_dict(values)


class SlicerBridgeNode(Node):
    """Subscribes to the registration's inputs and outputs; never waits on Slicer (the endpoint has its own thread)."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("slicer_bridge_node", **node_kwargs)  # node_kwargs: e.g. parameter_overrides (tests)
        config = slicer_config_from_parameters(self)
        self.endpoint = open_endpoint(config, self._log)
        self.link = SlicerLink(SlicerBridge(config, self.endpoint), self._log)
        self.create_subscription(PointCloud2, TOPIC_PREOP, self.link.on_preop_msg, LATCHED_QOS)
        self.create_subscription(Marker, TOPIC_MESH, self.link.on_mesh_msg, LATCHED_QOS)
        if config.cloud_rate_hz > 0:  # raw: decimated straight from the CDR bytes, no message object per cloud
            self.create_subscription(
                PointCloud2, TOPIC_INTRAOP, self.link.on_intraop_cdr, qos_profile_sensor_data, raw=True
            )
        self.create_subscription(PoseStamped, "/registration/pose", self.link.on_pose_msg, 10)
        self.create_subscription(DiagnosticArray, "/diagnostics", self.link.on_diagnostics_msg, 10)
        self.status_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(STATUS_PERIOD_S, self._publish_status)
        where = f"listening on {config.host}:{self.endpoint.port}" if config.role == "server" else "connecting to"
        if config.role == "client":
            where += f" {config.host}:{config.port}"
        self.get_logger().info(
            f"OpenIGTLink {config.role} {where}: {config.transform_device} (TRANSFORM), "
            f"{config.model_device} and {config.cloud_device} (POLYDATA), {config.status_device} (STRING); "
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
    """`ros2 run liver_p2p_reg slicer_bridge_node --ros-args -p port:=18944` (Jazzy idiom: rclpy.init() returns None)."""
    rclpy.init(args=args)
    node = None
    try:
        node = SlicerBridgeNode()
        executor = SingleThreadedExecutor()  # every callback is short: no second thread needed
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except LiverP2PError as exc:  # bad parameters, port taken, fastcrc missing: one fatal line
        get_logger("slicer_bridge_node").fatal(str(exc))
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
