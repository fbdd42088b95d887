"""A node's process tells its OpenMP runtimes to wait passively, before the first of them loads; a user's choice is kept."""

import json
import os
import subprocess
import sys
import time

import pytest
from conftest import require_rclpy

require_rclpy()

# Records OMP_WAIT_POLICY at the moment each OpenMP-carrying package is first imported (libgomp
# reads it then, once), imports a node module the way `ros2 run` does, then the lazily loaded ones.
PROBE = """
import json, os, sys
seen = {}
class Spy:
    def find_spec(self, name, path=None, target=None):
        if name in ("torch", "open3d", "pykdtree") and name not in seen:
            seen[name] = os.environ.get("OMP_WAIT_POLICY")
sys.meta_path.insert(0, Spy())
import liver_p2p_reg.ros.register_node
import torch, open3d
print(json.dumps(seen))
"""


@pytest.mark.parametrize(("given", "expected"), [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_wait_policy_is_set_before_any_openmp_runtime_loads(given, expected):
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if given is not None:
        env["OMP_WAIT_POLICY"] = given
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    assert seen == {"pykdtree": expected, "torch": expected, "open3d": expected}


def test_a_node_told_to_spin_without_pause_says_so_once(tmp_path):
    # OMP_WAIT_POLICY=ACTIVE is kept (a user's choice), but on the live graph it made a full registration
    # ~6x slower and the idle node take more than a core; the node says it in one WARN line at start-up
    from liver_p2p_reg.livegraph.graph import NodeProcess, set_isolated_environment

    env = {**set_isolated_environment(), "OMP_WAIT_POLICY": "ACTIVE"}
    node = NodeProcess("register_node", {}, env=env, log_dir=tmp_path)
    try:
        end = time.monotonic() + 90.0
        while "register_node ready" not in node.stderr() and node.alive() and time.monotonic() < end:
            time.sleep(0.2)
        assert "register_node ready" in node.stderr() and node.alive(), node.stderr()
        warned = [line for line in node.stderr().splitlines() if "OMP_WAIT_POLICY=ACTIVE" in line]
        assert len(warned) == 1 and "[WARN]" in warned[0] and "GOMP_SPINCOUNT" in warned[0], node.stderr()
    finally:
        node.stop()
