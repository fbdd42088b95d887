"""rclpy adapter: the register_node wiring topics, parameters, QoS, the ~/reregister service and tf to NodeCore."""

from __future__ import annotations

import array
import dataclasses
import time
from typing import Any

import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Transform, TransformStamped, Vector3
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from ..config import Config
from ..errors import LiverP2PError
from ..registrar import Registrar
from .messages import OutputTypes, diagnostic_array, pose_stamped, transform_stamped
from .node_core import CoreOutput, NodeCore
from .pointcloud2 import M_PER_MM, MessageTypes, points_to_cloud

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
# Late joiners (register_node started after the loader) still get the preop model.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
SCHEDULER_PERIOD_S = 0.02  # how often the worker checks for a due cloud (rate limit lives in the core)
DIAGNOSTICS_PERIOD_S = 1.0


def config_from_parameters(node: Node) -> Config:
    """Declare one ROS parameter per Config field (defaults from Config: one source of truth) and read them."""
    defaults = Config()
    values = {}
    # dynamic typing: `-p max_rate_hz:=2` (an integer) is coerced by Config instead of rejected
    descriptor = ParameterDescriptor(dynamic_typing=True)
    for f in dataclasses.fields(Config):
        node.declare_parameter(f.name, getattr(defaults, f.name), descriptor)
        values[f.name] = node.get_parameter(f.name).value
    return Config.from_dict(values)


class RegisterNode(Node):
    """Registers the preop model to each intraop cloud (per the mode) and publishes pose, tf, diagnostics."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("register_node", **node_kwargs)  # node_kwargs: e.g. parameter_overrides (tests)
        self.core = NodeCore(config_from_parameters(self))
        self.add_on_set_parameters_callback(self._on_parameters)
        io_group = ReentrantCallbackGroup()  # cheap callbacks: never blocked by a registration
        work_group = MutuallyExclusiveCallbackGroup()  # the one registration worker
        self.create_subscription(PointCloud2, "/preop/points", self._on_preop, LATCHED_QOS, callback_group=io_group)
        self.create_subscription(
            PointCloud2, "/preop/fiducials", self.core.on_preop_fiducials_msg, LATCHED_QOS, callback_group=io_group
        )
        self.create_subscription(
            PointCloud2, "/intraop/points", self._on_intraop, qos_profile_sensor_data, callback_group=io_group
        )
        self.create_subscription(
            PointCloud2, "/intraop/fiducials", self.core.on_intraop_fiducials_msg, 10, callback_group=io_group
        )
        self.pose_pub = self.create_publisher(PoseStamped, "/registration/pose", 10)
        self.transform_pub = self.create_publisher(TransformStamped, "/registration/transform", 10)
        self.cloud_pub = self.create_publisher(PointCloud2, "/registration/registered_preop", 1)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_service(Trigger, "~/reregister", self._on_reregister, callback_group=io_group)
        # survey mode (issue 19): start the fused surface over
        self.create_service(Trigger, "~/reset_survey", self._on_reset_survey, callback_group=io_group)
        self.create_timer(SCHEDULER_PERIOD_S, self._work, callback_group=work_group)
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_status, callback_group=io_group)
        self.tf_broadcaster = None
        try:  # /tf is optional: tf2_ros may be absent in minimal installs
            from tf2_ros import TransformBroadcaster

            self.tf_broadcaster = TransformBroadcaster(self)
        except ImportError:
            self.get_logger().warning("tf2_ros not importable: publishing /registration/transform only")
        cfg = self.core.config
        self.get_logger().info(
            f"register_node ready: method={cfg.method} mode={cfg.mode} max_rate_hz={cfg.max_rate_hz}"
        )

    # ---------------------------------------------------------------- callbacks (io group)
    def _on_preop(self, msg: PointCloud2) -> None:
        diag = self.core.on_preop_msg(msg)
        self.get_logger().info(diag.message)
        self.diag_pub.publish(diagnostic_array([diag], self._now_ns(), RCLPY_TYPES))

    def _on_intraop(self, msg: PointCloud2) -> None:
        diags = self.core.on_intraop_msg(msg)  # O(1): decoding happens in the worker
        if diags:
            self.diag_pub.publish(diagnostic_array(diags, self._now_ns(), RCLPY_TYPES))

    def _on_reregister(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        output = self.core.reregister(time.monotonic())
        self._publish(output)
        response.success = output.pose is not None
        response.message = output.summary
        return response

    def _on_reset_survey(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        # survey mode (issue 19): NodeCore.reset_survey waits for a registration in progress
        response.message = self.core.reset_survey()
        response.success = True
        self.get_logger().info(response.message)
        return response

    def _publish_status(self) -> None:
        self.diag_pub.publish(diagnostic_array([self.core.status()], self._now_ns(), RCLPY_TYPES))

    def _on_parameters(self, params: list[Any]) -> SetParametersResult:
        try:
            config = self.core.config.replace(**{p.name: p.value for p in params})
        except LiverP2PError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.core.config = config
        self.core.registrar = Registrar(config)
        return SetParametersResult(successful=True)

    # ---------------------------------------------------------------- worker (work group)
    def _work(self) -> None:
        output = self.core.process_pending(time.monotonic())
        if output is not None:
            self._publish(output)

    def _publish(self, output: CoreOutput) -> None:
        stamp_ns = output.pose.stamp_ns if output.pose is not None else self._now_ns()
        for diag in output.diagnostics:
            log = self.get_logger().info if diag.level == 0 else self.get_logger().warning
            log(f"{diag.level_name}: {diag.message}")
        if output.pose is not None:
            self.pose_pub.publish(pose_stamped(output.pose, RCLPY_TYPES))
            transform = transform_stamped(output.pose, RCLPY_TYPES)
            self.transform_pub.publish(transform)
            if self.tf_broadcaster is not None:
                self.tf_broadcaster.sendTransform(transform)
            cloud = points_to_cloud(
                output.registered_preop_mm * M_PER_MM,
                RCLPY_TYPES.cloud,
                frame_id=output.pose.frame_id,
                stamp_ns=stamp_ns,
            )
            self.cloud_pub.publish(cloud)
        self.diag_pub.publish(diagnostic_array(output.diagnostics, stamp_ns, RCLPY_TYPES))

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds


def main(args: list[str] | None = None) -> int:
    """`ros2 run liver_p2p_reg register_node` (Jazzy idiom: rclpy.init() returns None)."""
    rclpy.init(args=args)
    node = None
    try:
        node = RegisterNode()
        executor = MultiThreadedExecutor(num_threads=4)
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except LiverP2PError as exc:  # bad parameters: one fatal line, no traceback
        get_logger("register_node").fatal(str(exc))
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
