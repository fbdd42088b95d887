"""Large depth-camera clouds over Fast DDS between two processes, with and without config/fastdds_large_clouds.xml.

    .venv/bin/python scripts/bench_dds_clouds.py [--count 50] [--rate-hz 10] [--repeats 2] \
        [--readme docs/results/ros_graph.md]

A publisher process sends `--count` /intraop/points clouds (float32 x y z, a 640 x 480 depth frame's 307 200 points
and 1 M points) at `--rate-hz` with the topic's QoS (best effort, keep last 5) to a subscriber process on an isolated
localhost-only graph, as a camera driver and register_node would; the subscriber counts the complete clouds. Each
size runs with Fast DDS's defaults and with the bundled profile (in FASTRTPS_DEFAULT_PROFILES_FILE, which Fast
DDS 2.x reads), `--repeats` times, alternating. Run it on an idle
machine: a busy one loses more without the profile.
"""

from __future__ import annotations

import argparse
import os
from datetime import datetime, timezone

from tqdm import tqdm

from liver_p2p_reg.bench.readme import write_headline
from liver_p2p_reg.bench.sysinfo import cpu_model
from liver_p2p_reg.livegraph.cloud_delivery import BUNDLED_PROFILE, BYTES_PER_POINT, delivery
from liver_p2p_reg.livegraph.graph import isolated_env

SIZES = (307_200, 1_000_000)
MARK = "DDS-CLOUDS"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=50)
    ap.add_argument("--rate-hz", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--readme", help=f"write the table into this file's {MARK} block")
    args = ap.parse_args()
    runs = [(points, profile) for _ in range(args.repeats) for points in SIZES for profile in (None, BUNDLED_PROFILE)]
    results: dict[tuple[int, bool], list] = {}
    for points, profile in tqdm(runs, desc="cloud delivery", unit="run"):
        run = delivery(points, args.count, args.rate_hz, profile, isolated_env())
        results.setdefault((points, profile is not None), []).append(run)
    lines = [
        "| points per cloud | MB per cloud | Fast DDS profile | complete clouds received, per run | "
        "the publisher's own shared-memory segment (MiB) |",
        "|---|---|---|---|---|",
    ]
    for (points, profiled), got in results.items():
        name = "`config/fastdds_large_clouds.xml`" if profiled else "none (defaults)"
        counts = ", ".join(f"{r.complete} of {r.published}" for r in got)
        segment = max(r.shm_segment_mb for r in got)
        lines.append(f"| {points:,} | {points * BYTES_PER_POINT / 1e6:.1f} | {name} | {counts} | {segment:.1f} |")
    load = os.getloadavg()[0]
    caption = (
        f"Generated {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC on {os.cpu_count()} CPUs ({cpu_model()}), load "
        f"average at the end {load:.2f}; {args.count} clouds at {args.rate_hz:g} Hz per run, best effort, keep last 5, "
        "localhost-only discovery; the profile given to both processes in FASTRTPS_DEFAULT_PROFILES_FILE (the name Fast "
        "DDS 2.x, ROS 2 Jazzy's, reads).\n\nCommand: `.venv/bin/python scripts/bench_dds_clouds.py"
        + (f" --readme {args.readme}`" if args.readme else "`")
    )
    write_headline(caption, lines, args.readme, MARK)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
