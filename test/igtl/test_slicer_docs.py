"""The Slicer link's documentation: every bridge parameter with its default, the /preop/mesh page, README, launch file."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

from liver_p2p_reg.slicer_config import SlicerConfig

ROOT = Path(__file__).resolve().parents[2]


def test_every_bridge_parameter_documented_with_its_default() -> None:
    text = (ROOT / "msg_docs" / "parameters_slicer_bridge.md").read_text()
    defaults = SlicerConfig()
    for f in dataclasses.fields(SlicerConfig):
        row = next((line for line in text.splitlines() if line.startswith(f"| `{f.name}` |")), None)
        assert row is not None, f"{f.name} missing from msg_docs/parameters_slicer_bridge.md"
        assert f"`{getattr(defaults, f.name)!r}`" in row, f"{f.name}: documented default differs from SlicerConfig"
    for device in defaults.devices():
        assert f"| `{device}` |" in text


def test_preop_mesh_topic_page_and_index() -> None:
    index = (ROOT / "msg_docs" / "README.md").read_text()
    assert "`/preop/mesh`" in index and "parameters_slicer_bridge.md" in index
    page = (ROOT / "msg_docs" / "preop_mesh.md").read_text()
    assert page.startswith("# `/preop/mesh`")
    for word in ("type", "direction", "QoS", "frame", "units", "Example", "TRIANGLE_LIST"):
        assert word in page


def test_readme_section_and_its_picture() -> None:
    readme = (ROOT / "README.md").read_text()
    start = readme.index("## See it in 3D Slicer")
    section = readme[start : readme.index("\n## ", start + 1)]
    for needed in ("slicer:=true", "--slicer localhost:18944", "replay bags/", "CTToSensor", "LPS", "Client"):
        assert needed in section, needed
    assert "docs/slicer/what_arrives.png" in section and (ROOT / "docs" / "slicer" / "what_arrives.png").is_file()


def test_launch_file_starts_the_bridge_on_slicer_true() -> None:
    tree = ast.parse((ROOT / "launch" / "registration.launch.py").read_text())
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)]
    declared = {c.args[0].value for c in calls if getattr(c.func, "id", None) == "DeclareLaunchArgument"}
    assert {"slicer", "slicer_port", "ct_convention"} <= declared
    bridge = [
        c
        for c in calls
        if getattr(c.func, "id", None) == "Node"
        and any(k.arg == "executable" and getattr(k.value, "value", None) == "slicer_bridge_node" for k in c.keywords)
    ]
    assert len(bridge) == 1
    condition = next(k.value for k in bridge[0].keywords if k.arg == "condition")
    assert "slicer" in ast.unparse(condition)
    params = next(k.value for k in bridge[0].keywords if k.arg == "parameters")
    keys = {k.value for d in params.elts for k in d.keys}
    assert keys <= {f.name for f in dataclasses.fields(SlicerConfig)}
    assert '"slicer_bridge_node = liver_p2p_reg.ros.slicer_bridge_node:main"' in (ROOT / "setup.py").read_text()
