"""The bundled weights' poses on bundled-bag frames (the default method); run as a script to rewrite the reference."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

BAGS = Path(__file__).resolve().parents[1] / "bags"
REFERENCE = Path(__file__).resolve().parent / "data" / "learned_reference_poses.json"
# (bag, intraop frame): a small camera view, two random crops, a sensor-noise copy, a phantom frame
FRAMES = [
    ("insilico_L9000000_D00_T000_camera", 0),
    ("insilico_L9000000_D00_T002_random", 0),
    ("insilico_L9000001_D00_T007_random", 0),
    ("insilico_L9000001_D01_T003_random_noise3mm", 0),
    ("phantom_sim_01_vis0.30", 0),
]


def frame_pose(bag: str, index: int) -> tuple[np.ndarray, np.ndarray]:
    """(pose 4x4 mm, preop points mm) of one frame registered by the default method with the bundled weights."""
    from liver_p2p_reg.bags.io import model_and_clouds
    from liver_p2p_reg.config import Config
    from liver_p2p_reg.registration.registrar import Registrar

    preop, frames = model_and_clouds(BAGS / bag)
    result = Registrar(Config(num_threads=1)).register(preop, frames[index])
    return np.asarray(result.T_target_source, dtype=np.float64), preop


def write_reference() -> None:
    """Register every frame and store the poses with the weights' hash."""
    from liver_p2p_reg.config import Config
    from liver_p2p_reg.registration.weights_id import weights_sha256

    poses = {f"{bag}#{i}": frame_pose(bag, i)[0].tolist() for bag, i in FRAMES}
    REFERENCE.write_text(json.dumps({"weights_sha256": weights_sha256(Config()), "poses": poses}, indent=1) + "\n")
    print(f"wrote {REFERENCE}: {len(poses)} poses")


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    write_reference()
