"""Bitwise the same pose and diagnostics for the same inputs: fresh process, after unrelated work, on another thread."""

import json
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import torch
from determinism_frames import PARAMS, REFERENCE_FRAMES, frame_output, reference_outputs

from liver_p2p_reg.config import Config
from liver_p2p_reg.registration.threads import default_threads, pin_threads
from liver_p2p_reg.stream.core import NodeCore

HERE = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def fresh_process_outputs():
    """The reference frames registered in a fresh Python process (nothing else ran there before)."""
    script = HERE / "determinism_frames.py"
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    outputs = json.loads(done.stdout)
    assert all(o["pose"] is not None for o in outputs), outputs
    return outputs


def unrelated_work(core: NodeCore) -> None:
    """What a long-running node does between two surgeries: other models, other frames, parameter changes,
    and someone else's torch thread count."""
    torch.set_num_threads(1)  # e.g. a training step or a benchmark worker earlier in the process
    core.reconfigure({"method": "fpfh-ransac-icp", "voxel_size_norm": 0.03})
    frame_output(core, "insilico_L9000001_D00_T007_random", 0)
    core.reconfigure({"method": "learned-p2p-icp", "k": 3, "track_previous_pose": True, "mode": "continuous"})
    frame_output(core, "sweep_insilico_9000002", 3)
    frame_output(core, "insilico_L9000000_D01_T001_camera", 0)
    core.reconfigure({**Config().to_dict(), **PARAMS})  # back to where the references were made


def test_the_same_frames_give_bitwise_the_same_output_everywhere(fresh_process_outputs):
    core = NodeCore(Config(**PARAMS))
    first = [frame_output(core, bag, index) for bag, index in REFERENCE_FRAMES]
    assert first == fresh_process_outputs  # this process (other tests ran before) = a fresh one
    unrelated_work(core)
    assert [frame_output(core, bag, index) for bag, index in REFERENCE_FRAMES] == fresh_process_outputs
    on_worker = {}
    thread = threading.Thread(target=lambda: on_worker.setdefault("outputs", reference_outputs()))
    thread.start()
    thread.join()
    assert on_worker["outputs"] == fresh_process_outputs  # as register_node registers: on its worker thread


def test_pinning_sets_the_count_it_says():
    assert pin_threads(1) == 1 and torch.get_num_threads() == 1
    assert pin_threads(0) == default_threads() == torch.get_num_threads()


@pytest.mark.parametrize("method", ["fpfh-ransac", "fgr", "icp"])
def test_open3d_registration_runs_on_the_configured_openmp_threads(method, monkeypatch):
    # Open3D's RANSAC threads share one sample generator: on more than one thread the seed alone no longer
    # decides the pose, so every Open3D registration call runs on `open3d_threads` whatever torch's count is
    from synthetic_cases import partial_case
    from threadpoolctl import threadpool_info

    from liver_p2p_reg.o3d import o3d_module
    from liver_p2p_reg.registration.registrar import Registrar

    reg = o3d_module().pipelines.registration
    name = {
        "fpfh-ransac": "registration_ransac_based_on_correspondence",
        "fgr": "registration_fgr_based_on_feature_matching",
        "icp": "registration_icp",
    }[method]
    seen, original = [], getattr(reg, name)

    def recording(*args, **kwargs):  # Open3D's own call, with the OpenMP count of the runtime it shares
        seen.append({i["num_threads"] for i in threadpool_info() if i["filepath"].endswith("/libgomp.so.1")})
        return original(*args, **kwargs)

    monkeypatch.setattr(reg, name, recording)
    source, target, *_ = partial_case(np.random.default_rng(3), share=0.3)
    try:
        for open3d_threads in (1, 2):
            Registrar(Config(method=method, num_threads=2, open3d_threads=open3d_threads)).register(source, target)
            assert seen[-1] == {open3d_threads}
            assert torch.get_num_threads() == 2  # torch's own count is not what Open3D runs on
        outside = {i["num_threads"] for i in threadpool_info() if i["filepath"].endswith("/libgomp.so.1")}
        assert outside == {2}  # restored after the call
    finally:
        pin_threads(0)
