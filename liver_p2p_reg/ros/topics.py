"""The ROS interface's topic names and QoS profiles (msg_docs/), one definition each; rclpy only imported when asked."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

TOPIC_PREOP = "/preop/points"
TOPIC_PREOP_FIDUCIALS = "/preop/fiducials"
TOPIC_PREOP_MESH = "/preop/mesh"
TOPIC_PREOP_STRUCTURES = "/preop/structures"  # sensor_msgs/PointCloud2: x y z, label_id
TOPIC_STRUCTURE_LABELS = "/preop/structure_labels"  # std_msgs/String: {"labels": [...], "stamp_ns": ...}
TOPIC_INTRAOP = "/intraop/points"
TOPIC_INTRAOP_FIDUCIALS = "/intraop/fiducials"
TOPIC_POSE = "/registration/pose"
TOPIC_TRANSFORM = "/registration/transform"
TOPIC_REGISTERED = "/registration/registered_preop"
TOPIC_STRUCTURES = "/registration/structures"  # sensor_msgs/PointCloud2: x y z, label_id, error_bound
TOPIC_DEFORMED_PREOP = "/registration/deformed_preop"  # sensor_msgs/PointCloud2: preop after the non-rigid stage
TOPIC_DIAGNOSTICS = "/diagnostics"
# register_node's inputs, the topics a recorded case carries
INPUT_TOPICS = (TOPIC_PREOP, TOPIC_PREOP_FIDUCIALS, TOPIC_INTRAOP, TOPIC_INTRAOP_FIDUCIALS)
# register_node's other inputs from the loader (not all PointCloud2): bags carry and play them latched too
LOADER_INPUT_TOPICS = (TOPIC_PREOP_MESH, TOPIC_PREOP_STRUCTURES, TOPIC_STRUCTURE_LABELS)


@dataclass(frozen=True)
class Qos:
    """A QoS profile in msg_docs/' words: keep last `depth`, reliable or best effort, volatile or transient local."""

    depth: int
    reliable: bool = True
    latched: bool = False  # transient local: a subscriber joining later still gets the last message

    def rclpy_profile(self) -> Any:
        """This profile as an rclpy QoSProfile (equal to rclpy's preset where one exists, e.g. sensor data)."""
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        return QoSProfile(
            depth=self.depth,
            reliability=ReliabilityPolicy.RELIABLE if self.reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if self.latched else DurabilityPolicy.VOLATILE,
        )


# Late joiners (register_node started after the loader) still get the preop model.
LATCHED = Qos(depth=1, latched=True)
SENSOR_DATA = Qos(depth=5, reliable=False)  # rclpy's qos_profile_sensor_data; reliable publishers also match
RELIABLE = Qos(depth=10)  # every topic without a profile of its own
NEWEST_ONLY = Qos(depth=1)  # a viewer wants the newest registered cloud, not a backlog
QOS_OF_TOPIC = {
    TOPIC_PREOP: LATCHED,
    TOPIC_PREOP_FIDUCIALS: LATCHED,
    TOPIC_PREOP_MESH: LATCHED,
    TOPIC_PREOP_STRUCTURES: LATCHED,
    TOPIC_STRUCTURE_LABELS: LATCHED,
    TOPIC_INTRAOP: SENSOR_DATA,
    TOPIC_INTRAOP_FIDUCIALS: RELIABLE,
    TOPIC_POSE: RELIABLE,
    TOPIC_TRANSFORM: RELIABLE,
    TOPIC_REGISTERED: NEWEST_ONLY,
    TOPIC_STRUCTURES: RELIABLE,  # every pose's structures (a few hundred points): none lost
    TOPIC_DEFORMED_PREOP: NEWEST_ONLY,  # like the registered cloud: a viewer wants the newest
    TOPIC_DIAGNOSTICS: RELIABLE,
}


def qos_of(topic: str) -> Qos:
    """The documented QoS of a topic (RELIABLE for any other)."""
    return QOS_OF_TOPIC.get(topic, RELIABLE)


def rclpy_qos(topic: str) -> Any:
    """The rclpy QoSProfile of a topic."""
    return qos_of(topic).rclpy_profile()
