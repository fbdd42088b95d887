"""rclpy adapter: how many large /intraop/points clouds reach a subscriber in another process, with a given Fast DDS
profile or without one (the transports decide, not the node: `config/fastdds_large_clouds.xml`)."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

PROFILE_VARIABLES = ("FASTDDS_DEFAULT_PROFILES_FILE", "FASTRTPS_DEFAULT_PROFILES_FILE")  # Fast DDS 2.x reads both
BUNDLED_PROFILE = Path(__file__).resolve().parents[2] / "config" / "fastdds_large_clouds.xml"
START_S = 20.0  # a subscriber waits this long for the publisher to start and match
AFTER_S = 4.0  # ... and this long after the last cloud was due
BYTES_PER_POINT = 12  # float32 x, y, z (metres), as a depth camera driver publishes


@dataclass
class Delivery:
    """One run: clouds published, received (any), received complete, and the largest Fast DDS shared-memory
    segment the publisher mapped (MB: 0.5 by default, 64 with the bundled profile)."""

    points: int
    rate_hz: float
    profile: str
    published: int
    received: int
    complete: int
    shm_segment_mb: float


def cloud(points: int, frame_id: str = "camera", seed: int = 0):
    """A PointCloud2 of `points` random float32 points (metres, x y z), as a camera driver publishes one."""
    from sensor_msgs.msg import PointCloud2, PointField

    msg = PointCloud2()
    msg.header.frame_id = frame_id
    msg.height, msg.width = 1, points
    msg.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate("xyz")]
    msg.point_step, msg.row_step, msg.is_dense = BYTES_PER_POINT, BYTES_PER_POINT * points, True
    msg.data = (np.random.default_rng(seed).normal(0.0, 0.05, (points, 3)).astype(np.float32)).tobytes()
    return msg


def _publish(points: int, count: int, rate_hz: float) -> dict:
    """Wait for a subscriber, then publish `count` clouds at `rate_hz` with /intraop/points' QoS."""
    import rclpy
    from sensor_msgs.msg import PointCloud2

    from liver_p2p_reg.ros.topics import TOPIC_INTRAOP, rclpy_qos

    rclpy.init()
    node = rclpy.create_node("liver_p2p_cloud_publisher")
    try:
        pub = node.create_publisher(PointCloud2, TOPIC_INTRAOP, rclpy_qos(TOPIC_INTRAOP))
        msg = cloud(points)
        deadline = time.monotonic() + START_S
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)  # discovery settles on both sides before the first cloud
        start = time.monotonic()
        for i in range(count):
            msg.header.stamp.sec = i
            pub.publish(msg)
            time.sleep(max(0.0, start + (i + 1) / rate_hz - time.monotonic()))
        time.sleep(0.5)  # the last fragments leave before the participant goes
        return {"published": count, "shm_segment_mb": largest_shm_segment_mb()}
    finally:
        node.destroy_node()
        rclpy.shutdown()


def _receive(points: int, count: int, rate_hz: float) -> dict:
    """Count the /intraop/points clouds that arrive, and the complete ones, until all came or the time is up."""
    import rclpy
    from sensor_msgs.msg import PointCloud2

    from liver_p2p_reg.ros.topics import TOPIC_INTRAOP, rclpy_qos

    rclpy.init()
    node = rclpy.create_node("liver_p2p_cloud_subscriber")
    sizes: list[int] = []
    try:
        node.create_subscription(
            PointCloud2, TOPIC_INTRAOP, lambda m: sizes.append(len(m.data)), rclpy_qos(TOPIC_INTRAOP)
        )
        deadline = time.monotonic() + START_S + count / rate_hz + AFTER_S
        while time.monotonic() < deadline and sum(n == BYTES_PER_POINT * points for n in sizes) < count:
            rclpy.spin_once(node, timeout_sec=0.05)
        return {"received": len(sizes), "complete": sum(n == BYTES_PER_POINT * points for n in sizes)}
    finally:
        node.destroy_node()
        rclpy.shutdown()


def delivery(points: int, count: int, rate_hz: float, profile: str | Path | None, env: dict[str, str]) -> Delivery:
    """A subscriber and a publisher process on `env`'s isolated graph, both with `profile` (None: Fast DDS's
    defaults, any profile variable of this environment removed)."""
    base = {k: v for k, v in os.environ.items() if k not in PROFILE_VARIABLES} | env
    if profile is not None:
        base |= {name: str(profile) for name in PROFILE_VARIABLES}
    command = [sys.executable, "-m", "liver_p2p_reg.livegraph.cloud_delivery", str(points), str(count), str(rate_hz)]
    timeout_s = START_S + count / rate_hz + AFTER_S + 30.0
    sub = subprocess.Popen(
        [*command, "--role", "sub"], env=base, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        pub = subprocess.run([*command, "--role", "pub"], env=base, capture_output=True, text=True, timeout=timeout_s)
        out, err = sub.communicate(timeout=timeout_s)
    finally:
        if sub.poll() is None:
            sub.kill()
            sub.wait()
    if pub.returncode != 0 or sub.returncode != 0:
        raise RuntimeError(f"cloud delivery probe failed: {(pub.stderr or err).strip().splitlines()[-1:]}")
    got, sent = json.loads(out.strip().splitlines()[-1]), json.loads(pub.stdout.strip().splitlines()[-1])
    return Delivery(
        points, rate_hz, str(profile or ""), sent["published"], got["received"], got["complete"], sent["shm_segment_mb"]
    )


def largest_shm_segment_mb() -> float:
    """The largest Fast DDS shared-memory segment this process maps (MB; 0 when none): where its clouds go."""
    sizes = [0]
    with open("/proc/self/maps") as maps:
        for line in maps:
            path = line.split()[-1] if len(line.split()) >= 6 else ""
            if path.startswith("/dev/shm/fastrtps_") and "port" not in path:
                try:
                    sizes.append(os.path.getsize(path))
                except OSError:  # removed since (another participant's, gone)
                    pass
    return max(sizes) / 2**20


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="one side of the cloud delivery probe (delivery() runs both)")
    ap.add_argument("points", type=int)
    ap.add_argument("count", type=int)
    ap.add_argument("rate_hz", type=float)
    ap.add_argument("--role", choices=("pub", "sub"), required=True)
    args = ap.parse_args(argv)
    run = _publish if args.role == "pub" else _receive
    print(json.dumps(run(args.points, args.count, args.rate_hz)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
