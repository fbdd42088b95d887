"""Measure the node core: per-frame register latency over the bundled bags, and memory with 1M-point clouds at 30 Hz.

    OMP_NUM_THREADS=2 .venv/bin/python scripts/bench_node.py [--seconds 20] [--method fpfh-p2p]

Latency: every bundled bag is replayed through NodeCore (all frames); p50/p95 of the core's
`runtime_ms.total` per registration, once as the node runs by default (continuous mode tracks
from the previous pose) and once with a full registration on every frame. Memory: a producer thread hands 1M-point PointCloud2
messages (16 MB each, a fresh buffer per message as a subscriber would receive) to the core at
30 Hz while a worker thread registers the latest one as fast as the rate limit allows; the
process's resident memory is sampled throughout (peak VmHWM reported).
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time
from pathlib import Path

import numpy as np

from liver_p2p_reg.bags.io import read_messages, rosbags_types
from liver_p2p_reg.bags.replay import replay_bags
from liver_p2p_reg.config import Config
from liver_p2p_reg.ros.messages import feed_intraop_msg, feed_preop_msg
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_m, points_to_cloud
from liver_p2p_reg.ros.topics import TOPIC_INTRAOP, TOPIC_PREOP
from liver_p2p_reg.stream.core import NodeCore

ROOT = Path(__file__).resolve().parents[1]


def rss_mb(field: str = "VmRSS") -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


def latency(config: Config) -> dict:
    bags = sorted(p for p in (ROOT / "bags").iterdir() if (p / "metadata.yaml").is_file())
    rows = replay_bags(bags, config, progress=False)
    ms = np.array([v for row in rows for v in row.runtime_ms])
    return {
        "track_previous_pose": config.track_previous_pose,
        "bags": len(bags),
        "registrations": int(len(ms)),
        "tracked": sum(row.tracked for row in rows),
        "rms_tre_mm_mean": round(float(np.mean([row.rms_tre_mm for row in rows])), 2),
        "register_ms_p50": round(float(np.percentile(ms, 50)), 1),
        "register_ms_p95": round(float(np.percentile(ms, 95)), 1),
        "register_ms_max": round(float(ms.max()), 1),
    }


def memory(config: Config, seconds: float, n_points: int = 1_000_000, rate_hz: float = 30.0) -> dict:
    bag = sorted((ROOT / "bags").glob("insilico_*"))[0]
    msgs = {m.topic: m.msg for m in read_messages(bag)}
    frame_m = cloud_to_points_m(msgs[TOPIC_INTRAOP])
    rng = np.random.default_rng(0)
    # a dense depth-camera-like cloud: the frame's surface resampled to 1M points with 0.5 mm jitter
    dense = frame_m[rng.integers(0, len(frame_m), n_points)] + rng.normal(0, 0.0005, (n_points, 3))
    template = points_to_cloud(dense, rosbags_types(), frame_id="camera", stamp_ns=1)
    core = NodeCore(config)
    feed_preop_msg(core, msgs[TOPIC_PREOP])
    stop = threading.Event()
    samples: list[float] = []
    outputs = []

    def worker() -> None:
        while not stop.is_set():
            out = core.process_pending()
            if out is None:
                time.sleep(0.005)
            else:
                outputs.append(out.level)

    thread = threading.Thread(target=worker)
    thread.start()
    base_mb = rss_mb()
    start = time.monotonic()
    sent = 0
    while time.monotonic() - start < seconds:
        msg = template
        # a new 16 MB buffer per message, like a deserialized subscription message
        msg = type(template)(**{**template.__dict__, "data": template.data.copy()})
        feed_intraop_msg(core, msg)
        sent += 1
        samples.append(rss_mb())
        time.sleep(max(0.0, start + sent / rate_hz - time.monotonic()))
    stop.set()
    thread.join()
    return {
        "points_per_cloud": n_points,
        "rate_hz": rate_hz,
        "seconds": seconds,
        "clouds_sent": sent,
        "registered": len(outputs),
        "dropped_latest_only": core.dropped,
        "levels": sorted({int(x) for x in outputs}),
        "rss_before_mb": round(base_mb, 1),
        "rss_max_sampled_mb": round(max(samples), 1),
        "peak_rss_vmhwm_mb": round(rss_mb("VmHWM"), 1),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--method")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--skip-latency", action="store_true")
    args = parser.parse_args()
    config = Config(method=args.method) if args.method else Config()
    report = {"method": config.method, "omp_threads": os.environ.get("OMP_NUM_THREADS", "unset")}
    # memory first: the peak (VmHWM) must not include the bag replay's own allocations
    report["memory_1M_30Hz"] = memory(config, args.seconds)
    if not args.skip_latency:
        report["latency"] = latency(config)  # as the node runs by default (continuous mode tracks)
        report["latency_every_frame_full"] = latency(config.replace(track_previous_pose=False))
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
