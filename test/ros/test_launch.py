"""launch/registration.launch.py against the Jazzy launch_ros API: statically everywhere, for real where launch_ros is."""

from __future__ import annotations

import ast
import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import pytest

from liver_p2p_reg.config import Config

ROOT = Path(__file__).resolve().parents[2]
LAUNCH = ROOT / "launch" / "registration.launch.py"
# launch_ros.actions.Node.__init__ on Jazzy (keyword-only), plus what it forwards to ExecuteProcess.
JAZZY_NODE_KWARGS = {"executable", "package", "name", "namespace", "exec_name", "parameters", "remappings"}
JAZZY_NODE_KWARGS |= {"ros_arguments", "arguments", "output", "condition", "emulate_tty", "respawn", "respawn_delay"}
JAZZY_NODE_KWARGS |= {"sigterm_timeout", "sigkill_timeout", "additional_env", "cwd", "on_exit", "prefix", "log_cmd"}
LOADER_PARAMETERS = {"model_path", "fiducials_path", "mesh_path", "frame_id", "units", "structures_paths"}
MANAGED = {"register_lifecycle_node": "register_node", "preop_loader_lifecycle_node": "preop_loader_node"}


def calls(tree: ast.AST, name: str) -> list[ast.Call]:
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", None) == name]


def keyword(call: ast.Call, name: str):
    return next((k.value for k in call.keywords if k.arg == name), None)


def test_launch_file_uses_the_jazzy_node_api_and_real_names():
    tree = ast.parse(LAUNCH.read_text())
    declared = {c.args[0].value for c in calls(tree, "DeclareLaunchArgument")}
    used = {c.args[0].value for c in calls(tree, "LaunchConfiguration") if isinstance(c.args[0], ast.Constant)}
    assert used <= declared, used - declared
    nodes = [c for c in calls(tree, "Node") if isinstance(keyword(c, "package"), ast.Constant)]
    managed = calls(tree, "LifecycleNode")  # launch_ros.actions.LifecycleNode: name and namespace required
    ours = {
        keyword(c, "executable").value: c for c in nodes + managed if keyword(c, "package").value == "liver_p2p_reg"
    }
    assert set(ours) == {"register_node", "preop_loader_node", "slicer_bridge_node"} | MANAGED.keys()
    for call in managed:
        assert keyword(call, "namespace") is not None
        assert keyword(call, "name").value == MANAGED[keyword(call, "executable").value]  # the plain node's name
    for call in nodes + managed:
        assert not call.args, "launch_ros Node takes keyword arguments only"
        assert {k.arg for k in call.keywords} <= JAZZY_NODE_KWARGS, {k.arg for k in call.keywords} - JAZZY_NODE_KWARGS
    setup = (ROOT / "setup.py").read_text()
    for exe in ours:
        assert f'"{exe} = liver_p2p_reg.ros.{exe}:main"' in setup
    fields = {f.name for f in dataclasses.fields(Config)}
    lists = {
        t.id: v
        for n in ast.walk(tree)
        if isinstance(n, ast.Assign)
        for t, v in [(n.targets[0], n.value)]
        if isinstance(t, ast.Name)
    }
    for exe, allowed in (("register_node", fields), ("preop_loader_node", LOADER_PARAMETERS)):
        for name in (exe, {"register_node": "register_lifecycle_node"}.get(exe, "preop_loader_lifecycle_node")):
            params = keyword(ours[name], "parameters")
            params = lists.get(getattr(params, "id", None), params)  # a list named once, used by both variants
            for item in params.elts:
                if isinstance(item, ast.Dict):
                    keys = {k.value for k in item.keys}
                    assert keys <= allowed, (name, keys - allowed)


def test_launch_description_builds_with_launch_ros(tmp_path):
    pytest.importorskip("launch_ros", reason="launch_ros has no PyPI wheel; this runs where ROS 2 Jazzy is sourced")
    prefix = tmp_path / "install"
    proc = subprocess.run(
        [sys.executable, "setup.py", "egg_info", "--egg-base", str(tmp_path), "install", "--prefix", str(prefix),
         "--single-version-externally-managed", "--record", str(tmp_path / "record.txt")],
        cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    os.environ["AMENT_PREFIX_PATH"] = f"{prefix}{os.pathsep}{os.environ.get('AMENT_PREFIX_PATH', '')}"
    from launch.launch_description_sources import PythonLaunchDescriptionSource

    from launch import LaunchDescription

    description = PythonLaunchDescriptionSource(str(LAUNCH)).get_launch_description(None)
    assert isinstance(description, LaunchDescription)
    names = {getattr(e, "name", None) for e in description.entities}
    assert {"model_path", "bag", "rviz", "method", "managed"} <= names
