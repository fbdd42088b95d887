"""Helpers of the real-rclpy tests: bundled bag messages as rclpy clouds, a shared register_node graph."""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from liver_p2p_reg.bags.player import read_raw
from liver_p2p_reg.livegraph.graph import GraphProbe, NodeProcess, level_of, set_isolated_environment, values_of
from liver_p2p_reg.ros.topics import TOPIC_INTRAOP, TOPIC_INTRAOP_FIDUCIALS, TOPIC_PREOP, TOPIC_PREOP_FIDUCIALS
from liver_p2p_reg.stream.outputs import DIAG_NAME, PREOP_DIAG_NAME

BAGS = Path(__file__).resolve().parents[1] / "bags"
BAG_A = BAGS / "insilico_L9000001_D00_T007_random"  # visibility 0.9: quick and OK
BAG_B = BAGS / "insilico_L9000000_D00_T000_camera"  # visibility 0.2, another liver
# rcutils console lines: "[INFO] [1712345678.123] [register_node]: text"
LOG_LINE = re.compile(r"^\[(DEBUG|INFO|WARN|ERROR|FATAL)\] \[[0-9.]+\] \[([\w.]+)\]: ")


def bag_raw(bag: Path) -> dict[str, list[bytes]]:
    """topic -> CDR bytes of each message, in bag order."""
    out: dict[str, list[bytes]] = {}
    for topic, _, _, raw in read_raw(bag):
        out.setdefault(topic, []).append(raw)
    return out


def bag_frames_m(bag: Path) -> tuple[np.ndarray, list[np.ndarray]]:
    """The bag's preop points and intraop frames as (N, 3) metres."""
    from liver_p2p_reg.bags.io import model_and_clouds

    return model_and_clouds(bag, metres=True)


def stop_executor(executor) -> None:
    """Shut `executor` down and wait for the callbacks its threads are still running.

    Why: rclpy 7.1.6's Executor.shutdown() tests the flag it has just set, so it never waits; a
    MultiThreadedExecutor's callback still running in its pool then met destroy_node() ("cannot use
    Destroyable"), and the unretrieved exception was printed when the interpreter exited.
    """
    executor.shutdown()
    pool = getattr(executor, "_executor", None)  # MultiThreadedExecutor's ThreadPoolExecutor (rclpy-private)
    if pool is not None:
        pool.shutdown(wait=True)


def clean_stderr(text: str) -> list[str]:
    """Lines of a node's stderr that are not INFO log lines (a traceback, a warning, anything else)."""
    bad = []
    for line in text.splitlines():
        match = LOG_LINE.match(line)
        if not line.strip() or (match and match.group(1) in ("INFO", "DEBUG")):
            continue
        bad.append(line)
    return bad


def latest_status(probe: GraphProbe, since: int = 0) -> dict[str, str]:
    """The values of register_node's latest periodic status since `since` ({} before one)."""
    statuses = [values_of(s) for s, _ in probe.diagnostics(since, DIAG_NAME) if "received_clouds" in values_of(s)]
    return statuses[-1] if statuses else {}


def preop_fiducials_held(probe: GraphProbe) -> str:
    """How many preop fiducials register_node holds, by its latest periodic status ('' before one)."""
    return latest_status(probe).get("preop_fiducials", "")


def wait_for_fiducial_paths(probe: GraphProbe, n_preop: int, timeout_s: float = 60.0) -> bool:
    """Until register_node holds the model's `n_preop` fiducials (a loader's latched topic, discovered on its
    own) and hears /intraop/fiducials: an oracle cloud sent before either is refused (no fiducials)."""
    held = probe.wait_for(lambda: preop_fiducials_held(probe) == str(n_preop), timeout_s)
    return bool(held) and probe.wait_for_subscriber(TOPIC_INTRAOP_FIDUCIALS, timeout_s)


@dataclass
class Graph:
    """A register_node process and the probe that talks to it."""

    node: NodeProcess
    probe: GraphProbe

    def mark(self) -> int:
        return self.probe.count("/diagnostics")

    def attempts(self, since: int) -> list:
        """Registration diagnostics (not the periodic status) since `since`."""
        return [s for s, _ in self.probe.diagnostics(since, DIAG_NAME) if "received_clouds" not in values_of(s)]

    def wait_attempts(self, since: int, n: int = 1, timeout_s: float = 60.0) -> list:
        return self.probe.wait_for(lambda: (a := self.attempts(since)) and len(a) >= n and a, timeout_s) or []

    def counters(self, since: int = 0) -> dict[str, int]:
        """The node's own cloud counters (received, registered, dropped) in its latest periodic status."""
        return {k: int(v) for k, v in latest_status(self.probe, since).items() if k.endswith("_clouds")}

    def preop_diags(self, since: int) -> list:
        return [s for s, _ in self.probe.diagnostics(since, PREOP_DIAG_NAME)]

    def send_model(self, bag: Path, timeout_s: float = 120.0):
        """Publish a bag's preop model (+ fiducials); wait for the node's preop diagnostic."""
        raw = bag_raw(bag)
        since = self.mark()
        self.probe.publish(TOPIC_PREOP, raw[TOPIC_PREOP][0])
        if TOPIC_PREOP_FIDUCIALS in raw:
            self.probe.publish(TOPIC_PREOP_FIDUCIALS, raw[TOPIC_PREOP_FIDUCIALS][0])
        diags = self.probe.wait_for(lambda: self.preop_diags(since), timeout_s)
        assert diags, f"no preop diagnostic for {bag.name}"
        return diags[-1]

    def send_frame(self, bag: Path, index: int = 0, fiducials: bool = True) -> float:
        raw = bag_raw(bag)
        if fiducials:
            self.probe.publish(TOPIC_INTRAOP_FIDUCIALS, raw[TOPIC_INTRAOP_FIDUCIALS][index])
        return self.probe.publish(TOPIC_INTRAOP, raw[TOPIC_INTRAOP][index])

    def set(self, **values) -> None:
        results = self.probe.set_parameters(values)
        assert all(r.successful for r in results), [r.reason for r in results]

    def alive(self) -> bool:
        return self.node.alive() and self.probe.reregister(timeout_s=30) is not None


def start_graph(log_dir: Path, params: dict | None = None, wait_loaded: bool = True) -> Graph:
    env = set_isolated_environment()
    node = NodeProcess("register_node", params or {}, env=env, log_dir=log_dir)
    probe = GraphProbe()
    graph = Graph(node, probe)
    # /intraop/fiducials is volatile: sent before its own subscription is matched (discovered apart from /intraop)
    # they would be lost and the cloud's TRE missing
    for topic in (TOPIC_INTRAOP, TOPIC_INTRAOP_FIDUCIALS):
        assert probe.wait_for_subscriber(topic, 90.0), node.stderr()
    if wait_loaded:
        assert probe.wait_for(lambda: "loaded in" in node.stderr() or not node.alive(), 120.0) and node.alive(), (
            node.stderr()
        )
    return graph


def stop_graph(graph: Graph) -> None:
    graph.node.stop()
    graph.probe.close()


def levels(statuses: list) -> list[int]:
    return [level_of(s) for s in statuses]


def settle(seconds: float) -> None:
    time.sleep(seconds)
