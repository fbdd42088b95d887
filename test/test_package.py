"""Packaging: the colcon (ament_python) install layout, package.xml vs setup.py, CLI entry points."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import sysconfig
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "liver_p2p_reg"


def _setup_py_version() -> str:
    match = re.search(r'^VERSION = "([^"]+)"', (ROOT / "setup.py").read_text(), re.M)
    assert match, "setup.py must define VERSION"
    return match.group(1)


def test_package_xml_is_format3_ament_python_and_matches_setup_py() -> None:
    root = ET.parse(ROOT / "package.xml").getroot()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == PACKAGE
    assert root.findtext("version") == _setup_py_version()
    assert root.findtext("export/build_type") == "ament_python"
    exec_deps = {e.text for e in root.findall("exec_depend")}
    for dep in (
        "rclpy",
        "std_msgs",
        "sensor_msgs",
        "geometry_msgs",
        "diagnostic_msgs",
        "std_srvs",
        "builtin_interfaces",
        "python3-numpy",
        "python3-scipy",
    ):
        assert dep in exec_deps, dep
    assert "python3-pytest" in {e.text for e in root.findall("test_depend")}


def test_package_version_matches_module() -> None:
    import liver_p2p_reg

    assert liver_p2p_reg.__version__ == _setup_py_version()


def test_colcon_install_layout(tmp_path: Path) -> None:
    """Run the setuptools command colcon runs for ament_python packages into a temp prefix."""
    build, prefix = tmp_path / "build", tmp_path / "install"
    build.mkdir()
    cmd = [
        sys.executable,
        "setup.py",
        "egg_info",
        "--egg-base",
        str(build),
        "build",
        "--build-base",
        str(build / "build"),
        "install",
        "--prefix",
        str(prefix),
        "--record",
        str(build / "install.log"),
        "--single-version-externally-managed",
    ]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lib = prefix / "lib" / PACKAGE
    managed = ("register_lifecycle_node", "preop_loader_lifecycle_node")
    for exe in ("register_node", "preop_loader_node", "slicer_bridge_node", *managed, "liver-p2p"):
        assert (lib / exe).is_file() and os.access(lib / exe, os.X_OK), f"{exe} missing from lib/{PACKAGE}"
    # The CLI is on PATH (bin/), the node executables are not (ros2 run finds them in lib/<pkg>).
    assert (prefix / "bin" / "liver-p2p").is_file()
    assert not (prefix / "bin" / "register_node").exists()
    share = prefix / "share"
    assert (share / "ament_index" / "resource_index" / "packages" / PACKAGE).is_file()
    assert (share / PACKAGE / "package.xml").is_file()
    assert (share / PACKAGE / "config" / "registration.yaml").is_file()
    assert (share / PACKAGE / "config" / "fastdds_large_clouds.xml").is_file()  # docs/ros2.md names this path
    for launch_file in (ROOT / "launch").glob("*.py"):
        assert (share / PACKAGE / "launch" / launch_file.name).is_file()
    for bag_file in (ROOT / "bags").rglob("*"):
        if bag_file.is_file():
            assert (share / PACKAGE / bag_file.relative_to(ROOT)).is_file(), bag_file
    for weights in (ROOT / PACKAGE / "weights").glob("*.safetensors"):
        site = Path(sysconfig.get_path("purelib", vars={"base": str(prefix), "platbase": str(prefix)}))
        assert (site / PACKAGE / "weights" / weights.name).is_file()
    # The record lists what was installed where (colcon uses it to uninstall/reinstall).
    recorded = (build / "install.log").read_text()
    assert str(lib / "register_node") in recorded
    # The installed CLI runs from the prefix alone.
    site = Path(sysconfig.get_path("purelib", vars={"base": str(prefix), "platbase": str(prefix)}))
    env = {**os.environ, "PYTHONPATH": str(site)}
    out = subprocess.run([str(prefix / "bin" / "liver-p2p"), "--version"], capture_output=True, text=True, env=env)
    assert out.returncode == 0 and "liver-p2p" in out.stdout


@pytest.mark.parametrize("argv", [["-m", PACKAGE, "--help"], ["-m", PACKAGE, "--version"]])
def test_module_entry_point(argv: list[str]) -> None:
    out = subprocess.run([sys.executable, *argv], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "liver-p2p" in out.stdout


def test_console_script_help() -> None:
    exe = Path(sys.executable).with_name("liver-p2p")
    if not exe.exists():
        pytest.skip("liver-p2p console script not installed in this interpreter's environment")
    out = subprocess.run([str(exe), "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "usage: liver-p2p" in out.stdout


# The rclpy adapter modules: the three nodes and the two managed ones, the bag player and the live-graph harness + demo.
# The modules that may import rclpy or ROS message packages (at module level or inside a function).
RCLPY_ADAPTERS = {
    "ros/register_node.py",
    "ros/preop_loader_node.py",
    "ros/register_lifecycle_node.py",
    "ros/preop_loader_lifecycle_node.py",
    "ros/managed.py",  # the managed nodes' base
    "ros/slicer_bridge_node.py",
    "ros/node_main.py",
    "ros/rclpy_types.py",  # the rclpy message classes the nodes share
    "ros/topics.py",  # only inside functions: the rclpy profile of a topic's QoS description
    "bags/player.py",
    "livegraph/graph.py",
    "livegraph/demo.py",
    "livegraph/cloud_delivery.py",  # the two-process probe of large clouds over Fast DDS (bench_dds_clouds.py)
}
ROS_PYTHON = r"(rclpy|lifecycle_msgs|rosgraph_msgs|sensor_msgs|geometry_msgs|diagnostic_msgs|std_msgs|std_srvs|rcl_interfaces|builtin_interfaces|tf2_ros)"


def test_no_rclpy_outside_ros_adapters() -> None:
    offenders = []
    for path in (ROOT / PACKAGE).rglob("*.py"):
        text = path.read_text()
        if re.search(rf"^\s*(import {ROS_PYTHON}|from {ROS_PYTHON}[. ])", text, re.M):
            if path.relative_to(ROOT / PACKAGE).as_posix() not in RCLPY_ADAPTERS:
                offenders.append(str(path.relative_to(ROOT)))
    assert offenders == []
