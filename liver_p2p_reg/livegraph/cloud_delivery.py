"""rclpy adapter: how many large /intraop/points clouds reach a subscriber in another process, with a given Fast DDS
profile or without one (the transports decide, not the node: `config/fastdds_large_clouds.xml`)."""

from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

# Fast DDS 2.x (ROS 2 Jazzy's) reads FASTRTPS_DEFAULT_PROFILES_FILE only; Fast DDS 3 reads the FASTDDS_ name. The
# probe sets the one the docs tell a Jazzy user to export, and removes both (and what else would change the
# transports) from the "defaults" runs.
PROFILE_VARIABLE = "FASTRTPS_DEFAULT_PROFILES_FILE"
STRIPPED = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE", "SKIP_DEFAULT_XML",
            "FASTDDS_BUILTIN_TRANSPORTS", "ROS_DISCOVERY_SERVER", "RMW_FASTRTPS_USE_QOS_FROM_XML")  # fmt: skip
SHM_GLOB = "/dev/shm/fastrtps_*"
BUNDLED_PROFILE = Path(__file__).resolve().parents[2] / "config" / "fastdds_large_clouds.xml"
START_S = 20.0  # a subscriber waits this long for the publisher to start and match
AFTER_S = 4.0  # ... and this long after the last cloud was due
BYTES_PER_POINT = 12  # float32 x, y, z (metres), as a depth camera driver publishes


@dataclass
class Delivery:
    """One run: clouds published, received (any), received complete, and the largest Fast DDS shared-memory
    segment the publisher created itself (MiB: 0.5 by default, 67 with the bundled profile's 64 MiB)."""

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

    before = set(glob.glob(SHM_GLOB))  # the subscriber's segments exist already (it said it was ready)
    rclpy.init()
    node = rclpy.create_node("liver_p2p_cloud_publisher")
    try:
        pub = node.create_publisher(PointCloud2, TOPIC_INTRAOP, rclpy_qos(TOPIC_INTRAOP))
        msg = cloud(points)
        deadline = time.monotonic() + START_S
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        matched = pub.get_subscription_count()
        if matched == 0:  # discovery failed: not a lost cloud
            return {"published": 0, "matched": 0, "shm_segment_mb": own_shm_segment_mb(before)}
        time.sleep(0.5)  # discovery settles on both sides before the first cloud
        start = time.monotonic()
        for i in range(count):
            msg.header.stamp.sec = i
            pub.publish(msg)
            time.sleep(max(0.0, start + (i + 1) / rate_hz - time.monotonic()))
        time.sleep(0.5)  # the last fragments leave before the participant goes
        return {"published": count, "matched": matched, "shm_segment_mb": own_shm_segment_mb(before)}
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
        print(json.dumps({"ready": True}), flush=True)  # its participant (and segment) exists: the publisher may start
        deadline = time.monotonic() + START_S + count / rate_hz + AFTER_S
        while time.monotonic() < deadline and sum(n == BYTES_PER_POINT * points for n in sizes) < count:
            rclpy.spin_once(node, timeout_sec=0.05)
        return {"received": len(sizes), "complete": sum(n == BYTES_PER_POINT * points for n in sizes)}
    finally:
        node.destroy_node()
        rclpy.shutdown()


def delivery(points: int, count: int, rate_hz: float, profile: str | Path | None, env: dict[str, str]) -> Delivery:
    """A subscriber and then a publisher process on `env`'s isolated graph, both with `profile` in
    FASTRTPS_DEFAULT_PROFILES_FILE (None: Fast DDS's defaults; the profile variables of this environment removed).
    RuntimeError (one line) when a side fails or the publisher never matched the subscriber."""
    base = {k: v for k, v in os.environ.items() if k not in STRIPPED} | env | {"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}
    if profile is not None:
        base[PROFILE_VARIABLE] = str(profile)
    command = [sys.executable, "-m", "liver_p2p_reg.livegraph.cloud_delivery", str(points), str(count), str(rate_hz)]
    timeout_s = START_S + count / rate_hz + AFTER_S + 30.0
    with tempfile.TemporaryFile("w+") as sub_err:
        sub = subprocess.Popen([*command, "--role", "sub"], env=base, stdout=subprocess.PIPE, stderr=sub_err, text=True)
        try:
            if not sub.stdout.readline().strip():  # its participant exists before the publisher's starts
                raise RuntimeError(f"cloud delivery probe: the subscriber ended before it was ready ({_tail(sub_err)})")
            pub = subprocess.run(
                [*command, "--role", "pub"], env=base, capture_output=True, text=True, timeout=timeout_s
            )
            if pub.returncode != 0:
                raise RuntimeError(f"cloud delivery probe: the publisher failed ({pub.stderr.strip()[-300:]})")
            sent = _last_json(pub.stdout)
            if not sent.get("matched"):
                raise RuntimeError("cloud delivery probe: the publisher never matched the subscriber (discovery)")
            out, _ = sub.communicate(timeout=timeout_s)
            if sub.returncode != 0:
                raise RuntimeError(f"cloud delivery probe: the subscriber failed ({_tail(sub_err)})")
        finally:
            if sub.poll() is None:
                sub.kill()
                sub.wait()
    got = _last_json(out)
    return Delivery(
        points, rate_hz, str(profile or ""), sent["published"], got["received"], got["complete"], sent["shm_segment_mb"]
    )


def _last_json(text: str) -> dict:
    """The last line of a probe's stdout that is a JSON result (Fast DDS may print around it)."""
    for line in reversed(text.strip().splitlines()):
        try:
            value = json.loads(line)
        except ValueError:
            continue
        if isinstance(value, dict) and "ready" not in value:
            return value
    raise RuntimeError(f"cloud delivery probe: no result in its output ({text.strip()[-200:]!r})")


def _tail(file: Any) -> str:
    file.seek(0)
    return file.read().strip()[-300:]


def own_shm_segment_mb(before: set[str]) -> float:
    """The largest Fast DDS shared-memory segment (MiB; 0 when none) this process maps that did not exist before
    its participant: its own, where its clouds go (another participant's segment is mapped too, to read from it)."""
    sizes = [0]
    with open("/proc/self/maps") as maps:
        for line in maps:
            fields = line.split()
            path = fields[-1] if len(fields) >= 6 else ""
            if path.startswith("/dev/shm/fastrtps_") and "port" not in path and path not in before:
                try:
                    sizes.append(os.path.getsize(path))
                except OSError:  # removed since
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
