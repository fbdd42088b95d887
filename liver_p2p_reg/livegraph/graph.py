"""rclpy adapter: run the nodes as processes on an isolated domain and talk to them (demo, tests, benchmark)."""

from __future__ import annotations

import atexit
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TransformStamped
from rcl_interfaces.msg import Log
from rcl_interfaces.srv import DescribeParameters, GetParameters, ListParameters, SetParameters, SetParametersAtomically
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from liver_p2p_reg.bags.player import played_qos
from liver_p2p_reg.ros.pointcloud2 import stamp_to_ns
from liver_p2p_reg.ros.topics import (
    INPUT_TOPICS,
    TOPIC_DEFORMED_PREOP,
    TOPIC_DIAGNOSTICS,
    TOPIC_POSE,
    TOPIC_REGISTERED,
    TOPIC_STRUCTURES,
    TOPIC_TRANSFORM,
)

NODE_MODULES = {
    "register_node": "liver_p2p_reg.ros.register_node",
    "preop_loader_node": "liver_p2p_reg.ros.preop_loader_node",
    "register_lifecycle_node": "liver_p2p_reg.ros.register_lifecycle_node",
    "preop_loader_lifecycle_node": "liver_p2p_reg.ros.preop_loader_lifecycle_node",
}
LEVEL_OF = {b"\x00": 0, b"\x01": 1, b"\x02": 2, b"\x03": 3}


def domain_in_use(domain_id: int) -> bool:
    """Whether a DDS participant already listens on this domain here (its first unicast discovery port)."""
    port = 7410 + 250 * domain_id  # RTPS: PB 7400 + DG 250 * domain + offset 10 + 2 * participant 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return True
    return False


def isolated_env(domain_id: int | None = None) -> dict[str, str]:
    """Environment variables that keep a graph to itself: a random unused domain, localhost-only discovery."""
    if domain_id is None:
        candidates = list(range(1, 101))  # 0 is everyone's default; above 101 the ports clash
        random.SystemRandom().shuffle(candidates)
        domain_id = next((d for d in candidates if not domain_in_use(d)), candidates[0])
    return {
        "ROS_DOMAIN_ID": str(domain_id),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
    }


_STARTED: list[NodeProcess] = []


@atexit.register
def _kill_leftovers() -> None:
    """A node this process started must not outlive it (it would answer on its domain forever)."""
    for node in _STARTED:
        if node.alive():
            node.proc.kill()


class NodeProcess:
    """One node started as `python -m liver_p2p_reg.ros.<node> --ros-args -p k:=v ...` with logs to files."""

    def __init__(
        self,
        node: str,
        params: dict[str, Any] | None = None,
        *,
        env: dict[str, str] | None = None,
        log_dir: str | Path,
        name: str | None = None,
    ) -> None:
        self.name = name or node
        args = [sys.executable, "-m", NODE_MODULES[node], "--ros-args"]
        for key, value in (params or {}).items():
            text = str(value).lower() if isinstance(value, bool) else str(value)
            args += ["-p", f"{key}:={text}"]
        log_dir = Path(log_dir)
        log_dir.mkdir(parents=True, exist_ok=True)
        self.stdout_path = log_dir / f"{self.name}.stdout"
        self.stderr_path = log_dir / f"{self.name}.stderr"
        self._out = open(self.stdout_path, "wb")  # noqa: SIM115 (closed in wait/stop)
        self._err = open(self.stderr_path, "wb")  # noqa: SIM115
        full_env = {**os.environ, **(env or {}), "RCUTILS_COLORIZED_OUTPUT": "0", "PYTHONUNBUFFERED": "1"}
        self.started_s = time.monotonic()
        self.proc = subprocess.Popen(args, stdout=self._out, stderr=self._err, stdin=subprocess.DEVNULL, env=full_env)
        _STARTED.append(self)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stderr(self) -> str:
        if not self._err.closed:
            self._err.flush()
        return self.stderr_path.read_text(errors="replace")

    def rss_mb(self, field: str = "VmRSS") -> float:
        """Resident memory (VmRSS) or its peak (VmHWM) of the process, MB."""
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
        return float("nan")

    def cpu_s(self) -> float:
        """User + system CPU time of the process so far, s."""
        fields = Path(f"/proc/{self.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def wait(self, timeout_s: float) -> int | None:
        try:
            return self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            return None
        finally:
            if self.proc.poll() is not None:
                self._out.close()
                self._err.close()

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 10.0) -> tuple[int | None, float]:
        """Send `sig`, wait; (exit status or None if it did not end, seconds it took). Kills a hung one."""
        if not self.alive():
            return self.proc.returncode, 0.0
        start = time.monotonic()
        self.proc.send_signal(sig)
        code = self.wait(timeout_s)
        took = time.monotonic() - start
        if code is None:
            self.proc.kill()
            self.wait(5.0)
        return code, took


@dataclass
class Received:
    """A message as the probe received it, with the monotonic time of arrival."""

    msg: Any
    received_s: float


class GraphProbe:
    """An rclpy node in this process that feeds the nodes and records what they publish.

    It spins in a background thread on its own context, so callers just wait on conditions.
    """

    RECORDED = {
        TOPIC_POSE: PoseStamped,
        TOPIC_TRANSFORM: TransformStamped,
        TOPIC_REGISTERED: PointCloud2,
        TOPIC_STRUCTURES: PointCloud2,
        TOPIC_DEFORMED_PREOP: PointCloud2,  # deform on: after the non-rigid stage
        TOPIC_DIAGNOSTICS: DiagnosticArray,
        "/rosout": Log,
    }

    def __init__(self, name: str = "liver_p2p_probe", target: str = "register_node") -> None:
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.target = target
        self.lock = threading.Lock()
        self.received: dict[str, list[Received]] = {topic: [] for topic in self.RECORDED}
        rosout_qos = QoSProfile(depth=1000)
        for topic, kind in self.RECORDED.items():
            qos = rosout_qos if topic == "/rosout" else 50
            self.node.create_subscription(kind, topic, self._recorder(topic), qos)
        self.publishers = {  # with the QoS a bag's player gives them
            topic: self.node.create_publisher(PointCloud2, topic, played_qos(topic).rclpy_profile())
            for topic in INPUT_TOPICS
        }
        # Clients live as long as the probe: a client made just before its call may send the request
        # before the service's reply path has discovered it, and the reply is lost (rmw: timeout).
        self._clients: dict[str, Any] = {}
        self._client(Trigger, f"/{target}/reregister")
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._closing = False
        self.spin_error: BaseException | None = None  # why the probe's executor stopped, if it did
        self._thread = threading.Thread(target=self._spin, name="probe", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception as exc:
            if not self._closing:  # close() shutting the context down is no error
                self.spin_error = exc

    def _check_spinning(self) -> None:
        """A probe whose executor died records nothing more: say so instead of reporting silence."""
        if not self._closing and not self._thread.is_alive():
            raise RuntimeError(f"the probe's executor stopped: {self.spin_error!r}")

    def _recorder(self, topic: str) -> Callable[[Any], None]:
        def record(msg: Any) -> None:
            with self.lock:
                self.received[topic].append(Received(msg, time.monotonic()))

        return record

    # ---------------------------------------------------------------- reading what arrived
    def count(self, topic: str) -> int:
        self._check_spinning()
        with self.lock:
            return len(self.received[topic])

    def since(self, topic: str, index: int = 0) -> list[Received]:
        self._check_spinning()
        with self.lock:
            return list(self.received[topic][index:])

    def diagnostics(self, index: int = 0, name: str | None = None) -> list[tuple[Any, float]]:
        """(DiagnosticStatus, received_s) of every status received since `index` (optionally by name)."""
        out = []
        for item in self.since(TOPIC_DIAGNOSTICS, index):
            for status in item.msg.status:
                if name is None or status.name == name:
                    out.append((status, item.received_s))
        return out

    def wait_for(self, condition: Callable[[], Any], timeout_s: float = 30.0, period_s: float = 0.02) -> Any:
        """Poll `condition` until truthy or timeout; returns its last value."""
        end = time.monotonic() + timeout_s
        value = condition()
        while not value and time.monotonic() < end:
            time.sleep(period_s)
            value = condition()
        return value

    # ---------------------------------------------------------------- talking to the node
    def publish(self, topic: str, msg: Any) -> float:
        """Publish on one of the input topics; returns the monotonic time of publishing."""
        self.publishers[topic].publish(msg)
        return time.monotonic()

    def wait_for_subscriber(self, topic: str, timeout_s: float = 20.0) -> bool:
        return bool(self.wait_for(lambda: self.publishers[topic].get_subscription_count() > 0, timeout_s))

    def _client(self, srv_type: type, name: str) -> Any:
        if name not in self._clients:
            self._clients[name] = self.node.create_client(srv_type, name)
        return self._clients[name]

    def call(self, srv_type: type, name: str, request: Any, timeout_s: float = 60.0) -> Any:
        """Call a service and wait for the answer (None on timeout or if it never appears)."""
        client = self._client(srv_type, name)
        if not client.wait_for_service(timeout_sec=timeout_s):
            return None
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        if not done.wait(timeout_s):
            return None
        return future.result()

    def reregister(self, timeout_s: float = 60.0) -> Any:
        return self.call(Trigger, f"/{self.target}/reregister", Trigger.Request(), timeout_s)

    def list_parameters(self) -> list[str]:
        return list(self.call(ListParameters, f"/{self.target}/list_parameters", ListParameters.Request()).result.names)

    def describe_parameters(self, names: list[str]) -> list[Any]:
        return list(self.call(DescribeParameters, f"/{self.target}/describe_parameters", DescribeParameters.Request(names=names)).descriptors)  # fmt: skip

    def get_parameters(self, names: list[str]) -> list[Any]:
        values = self.call(GetParameters, f"/{self.target}/get_parameters", GetParameters.Request(names=names)).values
        return [Parameter.from_parameter_msg(_named(n, v)).value for n, v in zip(names, values, strict=True)]

    def set_parameters(self, values: dict[str, Any]) -> list[Any]:
        """ros2 param set: one result (successful, reason) per parameter."""
        request = SetParameters.Request(
            parameters=[Parameter(k, value=v).to_parameter_msg() for k, v in values.items()]
        )
        return list(self.call(SetParameters, f"/{self.target}/set_parameters", request).results)

    def set_parameters_atomically(self, values: dict[str, Any]) -> Any:
        params = [Parameter(k, value=v).to_parameter_msg() for k, v in values.items()]
        request = SetParametersAtomically.Request(parameters=params)
        return self.call(SetParametersAtomically, f"/{self.target}/set_parameters_atomically", request).result

    def close(self) -> None:
        self._closing = True
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._thread.join(2.0)


def _named(name: str, value: Any) -> Any:
    from rcl_interfaces.msg import Parameter as ParameterMsg

    return ParameterMsg(name=name, value=value)


def level_of(status: Any) -> int:
    """DiagnosticStatus.level as an int (rclpy gives bytes)."""
    level = status.level
    return LEVEL_OF.get(level, level) if isinstance(level, bytes) else int(level)


def values_of(status: Any) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


def stamp_ns(msg: Any) -> int:
    """A stamped message's header stamp, ns."""
    return stamp_to_ns(msg.header.stamp)


def set_isolated_environment(domain_id: int | None = None) -> dict[str, str]:
    """Put this process (and the nodes it starts) on an isolated domain; call before any rclpy.init."""
    env = isolated_env(domain_id)
    os.environ.update(env)
    return env
