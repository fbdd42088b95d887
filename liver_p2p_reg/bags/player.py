"""rclpy adapter: `liver-p2p bag play` publishes a bag's messages with recorded timing, original stamps, documented QoS."""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from builtin_interfaces.msg import Time
from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.ros.topics import INPUT_TOPICS, LOADER_INPUT_TOPICS, RELIABLE, Qos, qos_of

CLOCK_QOS = 10  # /clock as ros2 bag play offers it: reliable, volatile
# what `bag play` publishes unless --all-topics: register_node's inputs. A flight recording or a `replay --out` bag
# also holds the node's outputs (/registration/*, /diagnostics, /flight_recorder/*): played beside a live node they
# would mix recorded poses with its own.
PLAYED_TOPICS = INPUT_TOPICS + LOADER_INPUT_TOPICS


def played_qos(topic: str) -> Qos:
    """The QoS a topic is played with: an input topic's as msg_docs/ documents it, any other reliable, depth 10."""
    return qos_of(topic) if topic in PLAYED_TOPICS else RELIABLE


@dataclass
class Played:
    """One published message: topic, its header stamp (ns, 0 without a header) and when (monotonic s)."""

    topic: str
    stamp_ns: int
    published_s: float


def message_class(msgtype: str) -> type:
    """The rclpy message class of a ROS type name ('sensor_msgs/msg/PointCloud2')."""
    package, kind, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ImportError, AttributeError):
        raise InputError(f"message type {msgtype} is not installed for rclpy") from None


def read_raw(path: str | Path, topics: Iterable[str] | None = None) -> list[tuple[str, str, int, bytes]]:
    """(topic, msgtype, log time ns, CDR bytes) of a rosbag2 directory or .mcap file, in log-time order."""
    from rosbags.highlevel import AnyReader

    from liver_p2p_reg.bags.io import is_bag_error, typestore, unreadable

    path = Path(path)
    if not path.exists():
        raise InputError(f"bag not found: {path}")
    wanted = None if topics is None else set(topics)
    try:
        with AnyReader([path], default_typestore=typestore()) as reader:
            conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
            return [(c.topic, c.msgtype, int(t), bytes(raw)) for c, t, raw in reader.messages(connections=conns)]
    except Exception as exc:  # rosbags raises its own error classes per storage backend
        if not is_bag_error(exc):
            raise
        raise unreadable(path, exc) from None


def _header_stamp_ns(msgtype: str, raw: bytes) -> int:
    """The header stamp of a stamped message's CDR bytes (sec, nanosec lead the message), else 0."""
    if not msgtype.startswith(("sensor_msgs/", "geometry_msgs/", "diagnostic_msgs/")) or len(raw) < 12:
        return 0
    order = "little" if raw[1] == 1 else "big"  # CDR encapsulation: 0x0001 little-endian
    sec = int.from_bytes(raw[4:8], order, signed=True)
    nanosec = int.from_bytes(raw[8:12], order)
    return sec * 1_000_000_000 + nanosec


class BagPlayer:
    """Publishes a bag's raw messages through rclpy publishers of `node` (what `ros2 bag play` does)."""

    def __init__(
        self, node: Node, path: str | Path, topics: Iterable[str] | None = None, *, clock: bool = False
    ) -> None:
        self.node = node
        self.messages = read_raw(path, topics)
        if not self.messages:
            raise InputError(f"bag {path} has no messages" + ("" if topics is None else " on the chosen topics"))
        self.publishers: dict[str, Any] = {}
        for topic, msgtype, _, _ in self.messages:
            if topic not in self.publishers:
                qos = played_qos(topic).rclpy_profile()
                self.publishers[topic] = node.create_publisher(message_class(msgtype), topic, qos)
        # clock: /clock from the bag's log times (what `ros2 bag play --clock` does), for use_sim_time nodes;
        # each loop starts the clock again at the bag's first time: a jump back the nodes must survive
        self.clock_pub = node.create_publisher(Clock, "/clock", CLOCK_QOS) if clock else None

    def wait_for_subscribers(self, timeout_s: float, topics: Iterable[str] | None = None) -> bool:
        """Wait until each publisher (or the given topics') has a matched subscriber."""
        chosen = [self.publishers[t] for t in (topics or self.publishers) if t in self.publishers]
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if all(p.get_subscription_count() > 0 for p in chosen):
                return True
            time.sleep(0.02)
        return all(p.get_subscription_count() > 0 for p in chosen)

    def play(
        self,
        rate: float = 1.0,
        *,
        loop: bool = False,
        on_publish: Callable[[Played], None] | None = None,
        should_stop: Callable[[], bool] = lambda: False,
    ) -> list[Played]:
        """Publish every message at its recorded time offset divided by `rate`; `loop` repeats forever
        (until `should_stop`). Messages keep their original header stamps (the raw bytes are sent)."""
        if not rate > 0:
            raise InputError(f"--rate must be > 0, got {rate}")
        played: list[Played] = []
        first_ns = self.messages[0][2]
        while True:
            start = time.monotonic()
            for topic, msgtype, log_ns, raw in self.messages:
                delay = start + (log_ns - first_ns) * 1e-9 / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                if should_stop():
                    return played
                if self.clock_pub is not None:
                    self.clock_pub.publish(Clock(clock=Time(sec=log_ns // 10**9, nanosec=log_ns % 10**9)))
                self.publishers[topic].publish(raw)
                item = Played(topic, _header_stamp_ns(msgtype, raw), time.monotonic())
                played.append(item)
                if on_publish is not None:
                    on_publish(item)
            if not loop or should_stop():
                return played


def split_topics(topics: Iterable[str], all_topics: bool = False) -> tuple[list[str], list[str]]:
    """(played, skipped) of a bag's topics: register_node's inputs only (PLAYED_TOPICS), or all of them."""
    topics = sorted(topics)
    if all_topics:
        return topics, []
    return [t for t in topics if t in PLAYED_TOPICS], [t for t in topics if t not in PLAYED_TOPICS]


def main_play(path: str, rate: float, loop: bool, delay_s: float, clock: bool = False, all_topics: bool = False) -> int:
    """`liver-p2p bag play BAG`: its own rclpy context and node; Ctrl-C stops it (exit 0)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from liver_p2p_reg.bags.io import bag_topics

    chosen, skipped = split_topics(bag_topics(path), all_topics)
    if not chosen:
        raise InputError(
            f"bag {path} holds none of register_node's input topics (it holds {', '.join(skipped)}); "
            "--all-topics plays them"
        )
    rclpy.init()
    node = rclpy.create_node("liver_p2p_bag_player")
    try:
        player = BagPlayer(node, path, chosen, clock=clock)
        topics = ", ".join(sorted(player.publishers))
        extra = " and /clock" if clock else ""
        left = f" (not playing {', '.join(skipped)}: no input of register_node; --all-topics plays them)"
        print(
            f"playing {path}: {len(player.messages)} messages on {topics}{extra} at rate {rate}"
            + (left if skipped else ""),
            flush=True,
        )
        player.wait_for_subscribers(delay_s)
        played = player.play(rate, loop=loop, should_stop=lambda: not rclpy.ok())
        print(f"published {len(played)} messages", flush=True)
        time.sleep(0.2)  # let reliable samples leave before the publishers go
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
