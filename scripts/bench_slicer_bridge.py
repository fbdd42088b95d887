"""Benchmark the Slicer bridge: pose -> TRANSFORM on the wire latency and the bridge's CPU at a given rate.

Two measurements (run on an idle machine; targets: p95 <= 5 ms, <= 2 % of one core at 10 Hz):
1. in process, no ROS: SlicerLink.send_pose -> the TRANSFORM's last byte read by a loopback peer;
2. the real graph: slicer_bridge_node as its own process on an isolated domain; this process
   publishes /intraop/points (a bundled bag's cloud), /registration/pose and /diagnostics at
   --rate-hz, and a loopback peer times each TRANSFORM from the pose's publish (DDS hop included).
   The bridge's CPU is its user + system time from /proc over the run, as % of one core.
"""

from __future__ import annotations

import argparse
import os
import random
import re
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from liver_p2p_reg.bags.io import read_messages
from liver_p2p_reg.igtl.bridge import SlicerBridge, open_endpoint
from liver_p2p_reg.igtl.link import SlicerLink
from liver_p2p_reg.igtl.wire import StreamReader
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_m
from liver_p2p_reg.slicer_config import SlicerConfig

ROOT = Path(__file__).resolve().parents[1]


class Peer:
    """A loopback OpenIGTLink peer that notes when each TRANSFORM arrived (monotonic s), by its stamp in us."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.arrivals: dict[int, float] = {}
        self.counts: dict[str, int] = {}
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        reader = StreamReader(max_body_bytes=1 << 30)
        try:
            while data := self.sock.recv(1 << 20):
                now = time.monotonic()
                for m in reader.feed(data):
                    self.counts[m.device] = self.counts.get(m.device, 0) + 1
                    if m.type_name == "TRANSFORM":
                        self.arrivals[round(m.stamp_ns / 1000)] = now
        except OSError:
            pass


def percentiles(latencies_s: list[float]) -> str:
    ms = np.asarray(latencies_s) * 1e3
    if len(ms) == 0:
        return "no samples"
    return (
        f"p50 {np.percentile(ms, 50):.2f} ms, p95 {np.percentile(ms, 95):.2f} ms, max {ms.max():.2f} ms (n={len(ms)})"
    )


def in_process(n: int, rate_hz: float) -> str:
    config = SlicerConfig(host="127.0.0.1", port=0)
    endpoint = open_endpoint(config)
    link = SlicerLink(SlicerBridge(config, endpoint))
    peer = Peer(endpoint.port)
    endpoint.wait_for_peers(1, 10.0)
    sent: dict[int, float] = {}
    T = np.eye(4)
    for i in range(n):
        stamp_us = 1_700_000_000_000_000 + i * 1000
        T[:3, 3] = [i * 0.01, 2.0, 300.0]
        sent[stamp_us] = time.monotonic()
        link.send_pose(T, stamp_us * 1000)
        time.sleep(1.0 / rate_hz)
    time.sleep(0.5)
    endpoint.close()
    return percentiles([peer.arrivals[s] - t for s, t in sent.items() if s in peer.arrivals])


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def graph(bag: Path, rate_hz: float, seconds: float, cloud_points: int, idle_s: float, params: list[str]) -> list[str]:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from sensor_msgs.msg import PointCloud2

    from liver_p2p_reg.ros.pointcloud2 import points_to_cloud
    from liver_p2p_reg.ros.register_node import RCLPY_TYPES
    from liver_p2p_reg.ros.topics import TOPIC_DIAGNOSTICS, TOPIC_INTRAOP, TOPIC_POSE, TOPIC_PREOP, rclpy_qos
    from liver_p2p_reg.stream.outputs import DIAG_NAME

    env = {"ROS_DOMAIN_ID": str(random.SystemRandom().randint(1, 100)), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    os.environ.update(env)
    preop_m = cloud_m = None
    for item in read_messages(bag, [TOPIC_PREOP, TOPIC_INTRAOP]):
        if item.topic == TOPIC_PREOP:
            preop_m = cloud_to_points_m(item.msg)
        elif cloud_m is None:
            cloud_m = cloud_to_points_m(item.msg)
    if cloud_points:
        reps = int(np.ceil(cloud_points / len(cloud_m)))
        cloud_m = (np.tile(cloud_m, (reps, 1)) + np.random.default_rng(0).normal(0, 1e-4, (reps * len(cloud_m), 3)))[
            :cloud_points
        ]
    args = [sys.executable, "-m", "liver_p2p_reg.ros.slicer_bridge_node", "--ros-args", "-p", "host:=127.0.0.1"]
    for param in ["port:=0", *params]:
        args += ["-p", param]
    proc = subprocess.Popen(
        args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, **env}
    )
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True).start()
    context = Context()
    rclpy.init(context=context)
    node = rclpy.create_node("bench_slicer_player", context=context)
    out = []
    try:
        port = None
        end = time.monotonic() + 60
        while port is None and time.monotonic() < end:
            port = next(
                (int(m.group(1)) for m in (re.search(r"listening on 127\.0\.0\.1:(\d+)", x) for x in lines) if m), None
            )
            time.sleep(0.05)
        assert port, "".join(lines)
        pubs = {
            "preop": node.create_publisher(PointCloud2, TOPIC_PREOP, rclpy_qos(TOPIC_PREOP)),
            "cloud": node.create_publisher(PointCloud2, TOPIC_INTRAOP, rclpy_qos(TOPIC_INTRAOP)),
            "pose": node.create_publisher(PoseStamped, TOPIC_POSE, rclpy_qos(TOPIC_POSE)),
            "diag": node.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, rclpy_qos(TOPIC_DIAGNOSTICS)),
        }
        end = time.monotonic() + 60
        while any(p.get_subscription_count() == 0 for p in pubs.values()) and time.monotonic() < end:
            time.sleep(0.05)
        peer = Peer(port)
        pubs["preop"].publish(points_to_cloud(preop_m, RCLPY_TYPES.cloud, frame_id="ct"))
        cloud = points_to_cloud(cloud_m, RCLPY_TYPES.cloud, frame_id="camera")
        time.sleep(2.0)
        idle_start = cpu_s(proc.pid)
        time.sleep(idle_s)
        idle = (cpu_s(proc.pid) - idle_start) / idle_s * 100
        sent: dict[int, float] = {}
        n = int(seconds * rate_hz)
        start_cpu, start_wall = cpu_s(proc.pid), time.monotonic()
        for i in range(n):
            tick = start_wall + i / rate_hz
            time.sleep(max(0.0, tick - time.monotonic()))
            stamp_us = time.time_ns() // 1000
            sec, nanosec = divmod(stamp_us * 1000, 1_000_000_000)
            cloud.header.stamp.sec, cloud.header.stamp.nanosec = sec, nanosec
            pubs["cloud"].publish(cloud)
            pose = PoseStamped()
            pose.header.frame_id, pose.header.stamp.sec, pose.header.stamp.nanosec = "camera", sec, nanosec
            pose.pose.position.x, pose.pose.position.z, pose.pose.orientation.w = i * 1e-5, 0.3, 1.0
            time.sleep(0.002)  # the pose follows its cloud (register_node publishes it after registering)
            sent[stamp_us] = time.monotonic()
            pubs["pose"].publish(pose)
            status = DiagnosticStatus(level=bytes([0]), name=DIAG_NAME, message="registered: residual 1.00 mm")
            status.values = [KeyValue(key="stamp_ns", value=str(stamp_us * 1000))]
            diag = DiagnosticArray(status=[status])
            diag.header.stamp = pose.header.stamp
            pubs["diag"].publish(diag)
        wall = time.monotonic() - start_wall
        busy = (cpu_s(proc.pid) - start_cpu) / wall * 100
        time.sleep(1.0)
        latencies = [peer.arrivals[s] - t for s, t in sent.items() if s in peer.arrivals]
        out.append(f"graph, publish /registration/pose -> TRANSFORM read by the peer: {percentiles(latencies)}")
        out.append(
            f"bridge CPU at {rate_hz:g} Hz (pose + diagnostics + a {len(cloud_m)}-point cloud each): {busy:.2f} % of one core over {wall:.0f} s"
        )
        out.append(
            f"bridge CPU idle (a peer connected, no traffic): {idle:.2f} % of one core over {idle_s:.0f} s; RSS {rss_mb(proc.pid):.0f} MB"
        )
        out.append(f"received: {peer.counts}")
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        proc.send_signal(2)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bag", default=str(ROOT / "bags" / "insilico_L9000001_D00_T007_random"))
    parser.add_argument("--rate-hz", type=float, default=10.0)
    parser.add_argument("--seconds", type=float, default=60.0, help="length of the graph run")
    parser.add_argument("--idle-seconds", type=float, default=10.0)
    parser.add_argument("--cloud-points", type=int, default=0, help="resize the published cloud (0: the bag's)")
    parser.add_argument("--poses", type=int, default=600, help="poses of the in-process run")
    parser.add_argument("--skip-graph", action="store_true", help="only the in-process run (no rclpy needed)")
    parser.add_argument(
        "--param", action="append", default=[], metavar="NAME:=VALUE", help="a bridge parameter (repeatable)"
    )
    args = parser.parse_args()
    print(
        f"in process, SlicerLink.send_pose -> TRANSFORM read by the peer at {args.rate_hz:g} Hz: {in_process(args.poses, args.rate_hz)}"
    )
    if not args.skip_graph:
        for line in graph(Path(args.bag), args.rate_hz, args.seconds, args.cloud_points, args.idle_seconds, args.param):
            print(line)
    print(
        f"machine: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} (the numbers are only valid on an idle machine)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
