"""`liver-p2p register --slicer HOST:PORT` and `liver-p2p replay BAG --slicer PORT` over loopback (no ROS)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from igtl_support import Recorder, SlicerServerStandIn, assert_wire_equal, expected_transform, free_port

from liver_p2p_reg.bags.io import read_messages
from liver_p2p_reg.cli import main
from liver_p2p_reg.cloud_io import load_mesh, load_points, sample_mesh_surface, save_points
from liver_p2p_reg.igtl import scene
from liver_p2p_reg.igtl.link import level_of, pose_to_T_mm
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.ros.messages import mesh_marker_mm
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm
from liver_p2p_reg.slicer_config import SlicerConfig
from liver_p2p_reg.stream.outputs import DIAG_NAME, LEVEL_NAMES

BAG = Path(__file__).resolve().parents[2] / "bags" / "insilico_L9000001_D00_T007_random"  # visibility 0.9, OK


@pytest.fixture(scope="module")
def mesh_files(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """An ellipsoid liver stand-in as STL and a moved part of its surface as XYZ (mm)."""
    from liver_p2p_reg.o3d import o3d_module

    o3d = o3d_module()
    tmp = tmp_path_factory.mktemp("slicer_cli")
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=20)
    vertices = np.asarray(mesh.vertices) * [90.0, 60.0, 45.0]
    mesh.vertices = o3d.utility.Vector3dVector(vertices)
    mesh.compute_triangle_normals()
    stl = tmp / "liver.stl"
    assert o3d.io.write_triangle_mesh(str(stl), mesh)
    T = np.eye(4)
    T[:3, 3] = [4.0, -3.0, 250.0]
    surface = sample_mesh_surface(vertices, np.asarray(mesh.triangles), seed=3)
    target = transform_points(T, surface[surface[:, 0] > 20])
    xyz = tmp / "view.xyz"
    save_points(xyz, target)
    return {"stl": str(stl), "xyz": str(xyz), "target": target}


def test_register_sends_mesh_cloud_transform_and_verdict(mesh_files: dict, tmp_path: Path, capsys) -> None:
    slicer = SlicerServerStandIn()
    try:
        argv = [
            "register",
            mesh_files["stl"],
            mesh_files["xyz"],
            "--method",
            "icp",
            "--output",
            str(tmp_path / "r.json"),
        ]
        assert main([*argv, "--slicer", f"127.0.0.1:{slicer.port}"]) == 0
        T = np.array(json.loads((tmp_path / "r.json").read_text())["transform"])
        received = slicer.wait_connected()
        assert_wire_equal(received.wait_for("CTToSensor")[0].value, expected_transform(T))
        model = received.wait_for("PreopModel")[0].value
        vertices, triangles = load_mesh(mesh_files["stl"])
        assert len(model.polygons) == len(triangles) and len(model.points) == len(vertices)  # the file's mesh
        np.testing.assert_allclose(model.points, (vertices * [-1, -1, 1]).astype(np.float32), atol=0)
        cloud = received.wait_for("IntraopCloud")[0].value
        n = len(cloud.polygons)
        target = load_points(mesh_files["xyz"])  # what the command read (text keeps fewer digits)
        assert n == min(len(target), SlicerConfig().max_cloud_points)
        np.testing.assert_allclose(cloud.points[:n], scene.decimate(target, n).astype(np.float32), rtol=0, atol=0)
        status = received.wait_for("RegistrationStatus")[0].value
        assert re.match(r"(OK|WARN): registered: residual \d+\.\d\d mm", status), status
    finally:
        slicer.close()


def test_register_without_slicer_is_one_line_and_exit_2(mesh_files: dict, capsys) -> None:
    port = free_port()
    start = time.monotonic()
    assert (
        main(["register", mesh_files["stl"], mesh_files["xyz"], "--method", "icp", "--slicer", f"127.0.0.1:{port}"])
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"liver-p2p: error: cannot connect to 3D Slicer at 127.0.0.1:{port} (Connection refused): "
        "is an OpenIGTLinkIF connector of type Server active on that port?"
    ]
    assert time.monotonic() - start < 5.0  # refused at once, not after a timeout
    assert main(["register", mesh_files["stl"], mesh_files["xyz"], "--slicer", "localhost:http"]) == 2
    assert "expected HOST:PORT" in capsys.readouterr().err
    # ':PORT' is this machine, as a bare PORT is (it was refused as if the port were wrong)
    assert main(["register", mesh_files["stl"], mesh_files["xyz"], "--method", "icp", "--slicer", f":{port}"]) == 2
    assert f"cannot connect to 3D Slicer at localhost:{port}" in capsys.readouterr().err


def bag_outputs(bag: Path) -> tuple[list[np.ndarray], list[str], np.ndarray]:
    """Poses (mm) and registration statuses ('LEVEL: message') of a replay's output bag, and its preop model."""
    poses, statuses, preop = [], [], None
    for item in read_messages(bag):
        if item.topic == "/registration/pose":
            poses.append(pose_to_T_mm(item.msg.pose))
        elif item.topic == "/diagnostics":
            for s in item.msg.status:
                if s.name == DIAG_NAME:
                    statuses.append(f"{LEVEL_NAMES[level_of(s.level)]}: {s.message}")
        elif item.topic == "/preop/points":
            preop = cloud_to_points_mm(item.msg)
    return poses, statuses, preop


def test_replay_serves_a_bag_to_slicer(tmp_path: Path) -> None:
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "liver_p2p_reg", "replay", str(BAG), "--max-frames", "2", "--out", str(out)]
    cmd += ["--slicer", "0", "--slicer-wait", "60"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        port = None
        for line in proc.stderr:
            if match := re.search(r"OpenIGTLink server on port (\d+)", line):
                port = int(match.group(1))
                break
        assert port, "the replay did not say its port"
        received = Recorder.connect(port)
        stdout, stderr = proc.communicate(timeout=300)
        assert proc.returncode == 0, stderr[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
    poses, statuses, preop = bag_outputs(out / BAG.name)
    assert len(poses) == 2 and len(statuses) == 2
    transforms = received.wait_for("CTToSensor", 2)
    for got, T in zip(transforms, poses, strict=True):
        assert_wire_equal(got.value, expected_transform(T))
    assert [m.value for m in received.wait_for("RegistrationStatus", 2)] == statuses
    models = received.wait_for("PreopModel")
    assert len(models) == 1  # the bag's mesh (logged before its points, same stamp): the points are not sent too
    mesh = next(mesh_marker_mm(m.msg) for m in read_messages(BAG, ["/preop/mesh"]))
    assert len(models[0].value.polygons) == len(mesh[1]) != min(len(preop), SlicerConfig().max_model_points)
    clouds = received.wait_for("IntraopCloud")
    assert all(len(c.value.polygons) == SlicerConfig().max_cloud_points for c in clouds)  # 18508 decimated
    received.close()
