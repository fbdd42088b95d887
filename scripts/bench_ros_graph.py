"""Measure the live ROS 2 graph on the bundled bags: latency, full registration, start-up, warm-up, idle CPU, memory.

    OMP_NUM_THREADS=2 .venv/bin/python scripts/bench_ros_graph.py [--readme docs/results/ros_graph.md]

Everything goes through real topics: register_node and preop_loader_node run as processes on
an isolated domain (random ROS_DOMAIN_ID, localhost-only discovery) and this script plays the
bags' /intraop/* topics into them in real time, as `make demo` does. Run it on an idle machine;
timings taken while other work loads the cores are not worth reporting.

- start-up: a loader already publishes the first bag's model and its frames loop at 2 Hz; then
  register_node starts: process start -> first /registration/pose received;
- publish -> pose: every bundled bag's clouds (continuous mode, defaults: tracking on), p50/p95
  of the time from publishing a cloud to receiving its pose;
- full registration: `runtime_ms.total` of every untracked registration (each bag's first frame
  and each ~/reregister call), p50;
- warm-up: `warm_up_ms` of each new preop model (every bag after the first), p50 and max;
- idle CPU: register_node's CPU time over `--idle-s` seconds with nothing arriving;
- memory: register_node's peak RSS (VmHWM) after all bags and after a flood of 1 M-point clouds
  at 10 Hz for `--flood-s` seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from liver_p2p_reg.bags.player import read_raw  # noqa: E402
from liver_p2p_reg.bench.sysinfo import cpu_model  # noqa: E402
from liver_p2p_reg.livegraph.demo import model_files, run_bag  # noqa: E402
from liver_p2p_reg.livegraph.graph import GraphProbe, NodeProcess, set_isolated_environment, values_of  # noqa: E402
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_m, points_to_cloud  # noqa: E402
from liver_p2p_reg.ros.register_node import RCLPY_TYPES  # noqa: E402
from liver_p2p_reg.ros.topics import TOPIC_INTRAOP, TOPIC_INTRAOP_FIDUCIALS  # noqa: E402
from liver_p2p_reg.stream.outputs import DIAG_NAME  # noqa: E402

# The targets (2 threads, idle machine): name -> (limit, unit, lower is better)
TARGETS = {
    "publish_to_pose_ms_p50": (150, "ms"),
    "publish_to_pose_ms_p95": (400, "ms"),
    "full_registration_ms_p50": (200, "ms"),
    "start_to_first_pose_s": (10, "s"),
    "new_model_warm_up_ms_p50": (1500, "ms"),
    "new_model_warm_up_ms_max": (1500, "ms"),
    "idle_cpu_percent": (1, "% of a core"),
    "rss_peak_mb_bags_and_flood": (1000, "MB"),
}
BEGIN, END = "<!-- ROS-GRAPH-BENCH:START -->", "<!-- ROS-GRAPH-BENCH:END -->"


def start_up(probe: GraphProbe, bag: Path, out: Path, env: dict) -> tuple[NodeProcess, float]:
    """register_node started while the model is latched and clouds arrive: process start -> first pose."""
    model, fiducials, _ = model_files(bag, out / "startup")  # points only, as it was measured
    params = {"model_path": str(model), "units": "m", **({"fiducials_path": str(fiducials)} if fiducials else {})}
    loader = NodeProcess("preop_loader_node", params, env=env, log_dir=out / "logs", name="loader_startup")
    assert probe.wait_for(lambda: "published" in loader.stderr(), 120), loader.stderr()
    frames = [raw for topic, _, _, raw in read_raw(bag, [TOPIC_INTRAOP])]
    stop = threading.Event()

    def stream() -> None:  # the sensor keeps publishing at 2 Hz
        k = 0
        while not stop.is_set():
            probe.publish(TOPIC_INTRAOP, frames[k % len(frames)])
            k += 1
            stop.wait(0.5)

    thread = threading.Thread(target=stream, daemon=True)
    thread.start()
    node = NodeProcess("register_node", {}, env=env, log_dir=out / "logs")
    got = probe.wait_for(lambda: probe.since("/registration/pose"), 180)
    took = got[0].received_s - node.started_s if got else float("nan")
    stop.set()
    thread.join()
    loader.stop(signal.SIGINT)
    time.sleep(1.0)  # let the last streamed cloud be registered before the bags start
    return node, took


def flood(probe: GraphProbe, bag: Path, seconds: float) -> int:
    frame = cloud_to_points_m(next(m for m in _messages(bag) if m.topic == TOPIC_INTRAOP).msg)
    rng = np.random.default_rng(0)
    dense = frame[rng.integers(0, len(frame), 1_000_000)] + rng.normal(0, 0.0005, (1_000_000, 3))
    msg = points_to_cloud(dense, RCLPY_TYPES.cloud, frame_id="camera", stamp_ns=1)
    start, sent = time.monotonic(), 0
    while time.monotonic() - start < seconds:
        msg.header.stamp.sec = 100 + sent
        probe.publish(TOPIC_INTRAOP, msg)
        sent += 1
        time.sleep(max(0.0, start + sent / 10.0 - time.monotonic()))
    time.sleep(3.0)
    return sent


def _messages(bag: Path):
    from liver_p2p_reg.bags.io import read_messages

    return read_messages(bag, [TOPIC_INTRAOP, TOPIC_INTRAOP_FIDUCIALS])


def measure(out: Path, idle_s: float, flood_s: float) -> dict:
    bags = sorted(p for p in (ROOT / "bags").iterdir() if (p / "metadata.yaml").is_file())
    env = set_isolated_environment()
    probe = GraphProbe("bench_probe")
    node = None
    try:
        node, startup_s = start_up(probe, bags[0], out, env)
        since = probe.count("/diagnostics")
        rows = [run_bag(probe, bag, out / bag.name, out / "logs", env) for bag in bags]
        attempts = [
            values_of(s) for s, _ in probe.diagnostics(since, DIAG_NAME) if "received_clouds" not in values_of(s)
        ]
        full_ms = [
            float(v["runtime_ms.total"]) for v in attempts if v.get("tracked") == "false" and "runtime_ms.total" in v
        ]
        latency = [v for r in rows for v in r.latency_ms]
        warm = [r.warm_up_ms for r in rows[1:]]  # the first bag's model is the start-up one again (cached)
        rss_bags = node.rss_mb("VmHWM")
        time.sleep(2.0)
        cpu0, t0 = node.cpu_s(), time.monotonic()
        time.sleep(idle_s)
        idle = 100 * (node.cpu_s() - cpu0) / (time.monotonic() - t0)
        low_vis = min(rows, key=lambda r: r.visibility if np.isfinite(r.visibility) else 9).bag
        clouds = flood(probe, ROOT / "bags" / low_vis, flood_s)
        rss_flood = node.rss_mb("VmHWM")
        code, stop_s = node.stop(signal.SIGINT)
    finally:
        if node is not None and node.alive():
            node.stop(signal.SIGKILL)
        probe.close()
    return {
        "bags": len(rows),
        "clouds": sum(r.frames for r in rows),
        "poses": sum(r.registered for r in rows),
        "publish_to_pose_ms_p50": round(float(np.percentile(latency, 50)), 1),
        "publish_to_pose_ms_p95": round(float(np.percentile(latency, 95)), 1),
        "full_registrations": len(full_ms),
        "full_registration_ms_p50": round(float(np.median(full_ms)), 1),
        "start_to_first_pose_s": round(startup_s, 2),
        "new_model_warm_up_ms_p50": round(float(np.median(warm)), 1),
        "new_model_warm_up_ms_max": round(float(np.max(warm)), 1),
        "idle_cpu_percent": round(idle, 2),
        "rss_peak_mb_bags": round(rss_bags, 1),
        "flood_clouds_1M_points_10Hz": clouds,
        "rss_peak_mb_bags_and_flood": round(rss_flood, 1),
        "sigint_exit_status": code,
        "sigint_exit_s": round(stop_s, 2),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS", "unset"),
        "cpus": os.cpu_count(),
        "cpu": cpu_model(),
    }


def table(report: dict) -> str:
    lines = ["| measure | target | measured | met |", "|---|---|---|---|"]
    for key, (limit, unit) in TARGETS.items():
        value = report[key]
        lines.append(f"| {key} | <= {limit} {unit} | {value} | {'yes' if value <= limit else '**no**'} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/bench_ros_graph", help="node logs, recorded bags, report.json")
    parser.add_argument("--idle-s", type=float, default=10.0)
    parser.add_argument("--flood-s", type=float, default=10.0)
    parser.add_argument("--readme", help="rewrite the block between the ROS-GRAPH-BENCH markers of this file")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = measure(out, args.idle_s, args.flood_s)
    (out / "report.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    text = table(report)
    print(text)
    if args.readme:
        command = f"OMP_NUM_THREADS=2 .venv/bin/python scripts/bench_ros_graph.py --readme {args.readme}"
        block = (
            f"{BEGIN}\nMeasured with `{command}` on {report['cpus']} CPUs ({report['cpu']}), OMP_NUM_THREADS={report['omp_num_threads']}, "
            f"{report['poses']}/{report['clouds']} clouds of {report['bags']} bags got a pose, "
            f"{report['full_registrations']} full registrations, "
            f"{report['flood_clouds_1M_points_10Hz']} clouds of 1 M points in the flood; SIGINT: exit "
            f"{report['sigint_exit_status']} in {report['sigint_exit_s']} s.\n\n{text}\n{END}"
        )
        readme = Path(args.readme)
        current = readme.read_text()
        pattern = re.compile(re.escape(BEGIN) + ".*?" + re.escape(END), re.S)
        if not pattern.search(current):
            raise SystemExit(f"{readme} has no {BEGIN} ... {END} block")
        readme.write_text(pattern.sub(lambda _: block, current))
        print(f"updated {readme}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
