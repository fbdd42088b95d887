"""Time the non-rigid stage's outputs after the rigid pose on the live ROS 2 graph, every bundled bag played into it.

Usage: OMP_NUM_THREADS=2 .venv/bin/python scripts/bench_deform_latency.py [--readme docs/results/deformation.md]

Runs `liver-p2p demo --deform` (register_node and a loader per bag as processes, each bag's /preop/mesh given to
its loader, /intraop/* played in real time), then pairs, in the graph's recordings, every
/registration/deformed_preop with the /registration/pose of the same header stamp: the time from the pose's
arrival to the deformed surface's is what a viewer waits for the deformed outputs. Writes the block
DEFORM-LATENCY of the readme file (idle machine).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

from liver_p2p_reg.bags.io import read_messages
from liver_p2p_reg.bench.readme import replace_readme_block
from liver_p2p_reg.ros.pointcloud2 import stamp_to_ns
from liver_p2p_reg.ros.topics import TOPIC_DEFORMED_PREOP, TOPIC_DIAGNOSTICS, TOPIC_POSE

TARGET_MS = 300.0  # the issue's: deformed outputs <= 300 ms p50 after the rigid pose on the live graph


def bag_delays_ms(recorded: Path) -> tuple[list[float], int, list[float]]:
    """(pose -> deformed surface arrival, ms, per deformed frame; poses; the stage's own deform_ms per frame)."""
    poses: dict[int, int] = {}
    deformed: dict[int, int] = {}
    stage_ms: list[float] = []
    for item in read_messages(recorded, [TOPIC_POSE, TOPIC_DEFORMED_PREOP, TOPIC_DIAGNOSTICS]):
        if item.topic == TOPIC_DIAGNOSTICS:
            for status in item.msg.status:
                values = {kv.key: kv.value for kv in status.values}
                if values.get("deform_applied") == "true" and "received_clouds" not in values:
                    stage_ms.append(float(values["deform_ms"]))
            continue
        (poses if item.topic == TOPIC_POSE else deformed)[stamp_to_ns(item.msg.header.stamp)] = item.timestamp_ns
    delays = [(deformed[s] - poses[s]) * 1e-6 for s in deformed if s in poses]
    return delays, len(poses), stage_ms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/deform_latency")
    parser.add_argument("--readme")
    args = parser.parse_args()
    out = Path(args.out)
    command = [sys.executable, "-m", "liver_p2p_reg", "demo", "--deform", "--out", str(out)]
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    rows, delays, stages, n_poses = [], [], [], 0
    for recorded in sorted(out.glob("*/recorded")):
        mine, poses, stage_ms = bag_delays_ms(recorded)
        delays += mine
        stages += stage_ms
        n_poses += poses
        p50 = f"{np.median(mine):.0f}" if mine else "-"
        rows.append(f"| {recorded.parent.name} | {poses} | {len(mine)} | {p50} |")
    p50, p95 = (float(np.percentile(delays, q)) for q in (50, 95)) if delays else (float("nan"),) * 2
    stage_p50 = float(np.median(stages)) if stages else float("nan")
    block = "\n".join(
        [
            "Deformed outputs after the rigid pose on the live ROS 2 graph (`OMP_NUM_THREADS=2 .venv/bin/python "
            "scripts/bench_deform_latency.py`; every bundled bag played in real time into register_node with "
            "`deform: true`; arrival of /registration/pose to arrival of /registration/deformed_preop, same stamp):",
            "",
            "| bag | poses | deformed | pose -> deformed p50 (ms) |",
            "|---|---|---|---|",
            *rows,
            "",
            f"All bags: {len(delays)} deformed surfaces of {n_poses} poses; pose -> deformed p50 {p50:.0f} ms, "
            f"p95 {p95:.0f} ms (target: <= {TARGET_MS:.0f} ms p50, {'met' if p50 <= TARGET_MS else '**missed**'}); "
            f"the stage itself (`deform_ms`) p50 {stage_p50:.0f} ms.",
        ]
    )
    print(block)
    if args.readme:
        replace_readme_block(Path(args.readme), block, "DEFORM-LATENCY")


if __name__ == "__main__":
    main()
