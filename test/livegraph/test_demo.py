"""`liver-p2p demo`: the live graph where rclpy imports, else one line and the ROS-free replay."""

import os
import subprocess
import sys

from conftest import require_rclpy

BAG = "phantom_sim_04_vis0.36"


def demo(tmp_path, *args, env=None):
    cmd = [sys.executable, "-m", "liver_p2p_reg", "demo", "--bags", BAG, "--out", str(tmp_path / "out"), *args]
    return subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, **(env or {})}, timeout=600)


def test_demo_runs_the_live_graph(tmp_path):
    require_rclpy()
    proc = demo(tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    out = proc.stdout
    assert "Live ROS 2 graph" in out and "latency ms p50" in out and "replay RMS-TRE mm" in out
    row = next(line for line in out.splitlines() if line.startswith(f"| {BAG}"))
    assert "/5" in row and ("OK" in row or "WARN" in row)
    assert f"{BAG}: ~/reregister -> pose: registered" in out
    assert (tmp_path / "out" / BAG / "recorded" / "metadata.yaml").is_file()
    assert (tmp_path / "out" / "logs" / "register_node.stderr").is_file()


def test_demo_without_rclpy_says_so_in_one_line_and_replays(tmp_path):
    fake = tmp_path / "no_rclpy" / "rclpy"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError('rclpy hidden by the test')\n")
    proc = demo(tmp_path, env={"PYTHONPATH": str(fake.parent)})
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    notes = [line for line in lines if "rclpy not importable" in line]
    assert len(notes) == 1 and "ROS-free replay" in notes[0]
    assert "Live ROS 2 graph" not in proc.stdout
    assert any(line.startswith(f"| {BAG}") for line in lines) and "runtime ms (p50)" in proc.stdout


def test_demo_deform_adds_the_deformed_tre_to_the_replay_table(tmp_path):
    proc = demo(tmp_path, "--replay", "--deform")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    assert any("deformed RMS-TRE mm (mean)" in line and "deform applied" in line for line in lines)
    row = [c.strip() for c in next(line for line in lines if line.startswith(f"| {BAG}")).strip("|").split("|")]
    applied, registered = (int(n) for n in row[-1].split("/"))
    assert registered == 5 and applied >= 1 and 0 < float(row[-2]) < 20  # the stage ran on the bag's mesh
