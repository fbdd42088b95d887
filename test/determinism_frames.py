"""Reference frames of the determinism tests: bundled-bag frames through NodeCore; run as a script in a fresh process."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

BAGS = Path(__file__).resolve().parents[1] / "bags"
# (bag, intraop frame): a camera crop at visibility 0.2, a sweep frame, a phantom frame; each one whose
# pose 1 and 2 torch threads change in the last bits, so a thread count left over would show
REFERENCE_FRAMES = [
    ("insilico_L9000000_D00_T000_camera", 3),
    ("sweep_phantom_sim_9500004", 6),
    ("phantom_sim_04_vis0.36", 0),
]
PARAMS = {"track_previous_pose": False, "mode": "on_demand"}


def frame_output(core, bag_name: str, index: int) -> dict:
    """One reference frame through `core` (a NodeCore): its pose's bytes (hex) and its diagnostic values
    without the timings (wall-clock, so never equal)."""
    from liver_p2p_reg.bags.io import model_and_clouds

    preop, frames = model_and_clouds(BAGS / bag_name)
    core.set_preop(preop, "ct")
    core.on_intraop_points(frames[index], "camera", stamp_ns=index + 1)
    output = core.reregister()
    values = {k: v for k, v in output.diagnostics[0].values.items() if not k.startswith("runtime_ms.")}
    values.pop("model_cache_computed", None)  # what this frame had to compute, not what it computed
    pose = None if output.pose is None else np.asarray(output.pose.T_sensor_ct_mm, dtype=np.float64).tobytes().hex()
    return {"frame": f"{bag_name}#{index}", "pose": pose, "values": values}


def reference_outputs() -> list[dict]:
    """Every reference frame through one fresh NodeCore, in order."""
    from liver_p2p_reg.config import Config
    from liver_p2p_reg.stream.core import NodeCore

    core = NodeCore(Config(**PARAMS))
    return [frame_output(core, bag, index) for bag, index in REFERENCE_FRAMES]


if __name__ == "__main__":
    json.dump(reference_outputs(), sys.stdout)
