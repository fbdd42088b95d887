"""Packaging for colcon (ament_python) and pip alike; see README "Installation"."""

import os
from glob import glob

from setuptools import find_packages, setup
from setuptools.command.develop import develop
from setuptools.command.install_scripts import install_scripts

PACKAGE = "liver_p2p_reg"
VERSION = "0.1.0"  # keep equal to package.xml (a test checks)
NODE_EXECUTABLES = (
    "register_node",
    "preop_loader_node",
    "slicer_bridge_node",
    "register_lifecycle_node",
    "preop_loader_lifecycle_node",
)


class ros_aware_install_scripts(install_scripts):
    """Put ROS node executables where `ros2 run` looks (<prefix>/lib/<pkg>/), keep the CLI on PATH.

    ament_python packages usually set `install_scripts=$base/lib/<pkg>` in setup.cfg, which
    would also hide `liver-p2p` from PATH. Instead the node executables are routed here and
    `liver-p2p` goes to <prefix>/bin (and, for `ros2 run liver_p2p_reg liver-p2p`, also to
    <prefix>/lib/<pkg>/). Wheel installs (pip) do not run this command: pip writes every
    entry point to the environment's bin/ as usual.
    """

    def write_script(self, script_name, contents, mode="t", *ignored):
        ros_dir = os.path.join(os.path.dirname(os.path.normpath(self.install_dir)), "lib", PACKAGE)
        base_dir = self.install_dir
        if script_name in NODE_EXECUTABLES or script_name == "liver-p2p":
            self.install_dir = ros_dir
            try:
                super().write_script(script_name, contents, mode, *ignored)
            finally:
                self.install_dir = base_dir
        if script_name not in NODE_EXECUTABLES:
            super().write_script(script_name, contents, mode, *ignored)


class ros_aware_develop(develop):
    """`colcon build --symlink-install` (`setup.py develop`): setup.cfg sends every script to
    <prefix>/lib/<pkg>/ for `ros2 run`; `liver-p2p` also goes to <prefix>/bin, as in a plain install."""

    def write_script(self, script_name, contents, mode="t", *ignored):
        super().write_script(script_name, contents, mode, *ignored)
        if script_name == "liver-p2p":
            base_dir = self.script_dir
            self.script_dir = os.path.join(os.path.dirname(os.path.dirname(os.path.normpath(base_dir))), "bin")
            os.makedirs(self.script_dir, exist_ok=True)
            try:
                super().write_script(script_name, contents, mode, *ignored)
            finally:
                self.script_dir = base_dir


def tree(directory, patterns=("*",)):
    """data_files entries mirroring `directory` under share/<pkg>/ (for bags/)."""
    entries = {}
    for pattern in patterns:
        for path in glob(os.path.join(directory, "**", pattern), recursive=True):
            if os.path.isfile(path):
                entries.setdefault(os.path.join("share", PACKAGE, os.path.dirname(path)), []).append(path)
    return sorted(entries.items())


setup(
    name=PACKAGE,
    version=VERSION,
    description="Automatic complete-to-partial rigid registration of liver surfaces (patches-to-partial, P2P)",
    long_description=open("README.md", encoding="utf-8").read() if os.path.exists("README.md") else "",
    long_description_content_type="text/markdown",
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={PACKAGE: ["weights/*.safetensors", "weights/*.json", "weights/*.md", "data/*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.rviz") + glob("config/*.xml")),
        *tree("bags"),
    ],
    install_requires=[
        "numpy>=1.24",
        "scipy>=1.10",
        "pykdtree>=1.3",  # the ICP loops' closest-point search (registration/nearest.py)
        "threadpoolctl>=3.1",  # Open3D's registration calls on a set number of OpenMP threads (registration/baselines.py)
        "torch>=2.2",
        "rosbags>=0.10",
        "mcap>=1.1",
        "safetensors>=0.4",
        "tqdm>=4.60",
        "matplotlib>=3.6",
        "pyyaml>=6.0",
        "scikit-fem>=10.0",
        "scikit-image>=0.21",
    ],
    # Open3D comes in two builds that provide the same module; pick one extra
    # (cpu: headless, no libusb; full: needs the system's libusb-1.0-0).
    extras_require={
        # the OpenIGTLink link to 3D Slicer: fastcrc computes the protocol's CRC-64 (the bridge needs it);
        # pyigtl, an independent OpenIGTLink implementation, is the tests' and scripts' Slicer stand-in
        "slicer": ["fastcrc>=0.3", "pyigtl>=0.3.4"],
        "cpu": ["open3d-cpu>=0.18,<0.20"],  # 0.20.0's CPU wheel links libusb again
        "full": ["open3d>=0.18"],
        # setuptools: the colcon-layout test; colcon: the colcon build test
        "dev": ["pytest>=7", "ruff>=0.5", "setuptools>=61", "colcon-common-extensions>=0.3"],
        # ROS 2 Jazzy's rclpy and messages as PyPI wheels (no tf2_ros, launch or rosbag2 wheels exist)
        "ros": [
            "ros-jazzy-rclpy[fastrtps]>=7.1",
            "ros-jazzy-common-interfaces>=5.3",
            "ros-jazzy-std-srvs>=5.3",
            "ros-jazzy-rcl-lifecycle",  # the managed nodes (rclpy.lifecycle)
            "ros-jazzy-lifecycle-msgs",
        ],
    },
    zip_safe=False,
    cmdclass={"install_scripts": ros_aware_install_scripts, "develop": ros_aware_develop},
    entry_points={
        "console_scripts": [
            "liver-p2p = liver_p2p_reg.cli:main",
            "register_node = liver_p2p_reg.ros.register_node:main",
            "preop_loader_node = liver_p2p_reg.ros.preop_loader_node:main",
            "register_lifecycle_node = liver_p2p_reg.ros.register_lifecycle_node:main",
            "preop_loader_lifecycle_node = liver_p2p_reg.ros.preop_loader_lifecycle_node:main",
            "slicer_bridge_node = liver_p2p_reg.ros.slicer_bridge_node:main",
        ],
    },
)
