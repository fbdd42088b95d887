"""The bridge read by the reference OpenIGTLink C++ library: reference_client.cxx, built here against it, is the peer.

The other tests decode the stream with pyigtl (which cannot read POLYDATA) and the protocol's
layout as written in igtl_support; here the library Slicer itself links (Debian's
libopenigtlink-dev) unpacks every TRANSFORM, POLYDATA and STRING with its CRC check. The client
prints what the library read (see its header comment), and this module compares that with what
the link was given: a bundled bag's registration, replayed through the link as `replay --slicer`
does, then a mesh, a UTF-8 verdict and live updates, the structures and the deformed model. The client's own checks (a bad CRC, a
missing message) are tested too, so that its "crc=ok" means something.
"""

from __future__ import annotations

import re
import shutil
import socket
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

SKIP_REASON = "install libopenigtlink-dev (Debian) to run the reference-client interop test"
HERE = Path(__file__).resolve().parent
SOURCE = HERE / "reference_client.cxx"
# Debian puts the headers in /usr/include/openigtlink and the library in /usr/lib; an upstream
# (CMake) install uses include/igtl and lib/igtl under its prefix.
INCLUDE_DIRS = ("/usr/include/openigtlink", "/usr/local/include/igtl", "/usr/include/igtl")
LIBRARY_DIRS = ("/usr/lib", "/usr/lib/x86_64-linux-gnu", "/usr/local/lib", "/usr/local/lib/igtl", "/usr/lib/igtl")
LINKABLE = ("libOpenIGTLink.so", "libOpenIGTLink.a")  # what -lOpenIGTLink needs (the runtime package has only .so.N)


def find_reference_library(
    include_dirs: tuple[str, ...] = INCLUDE_DIRS, library_dirs: tuple[str, ...] = LIBRARY_DIRS, compiler: str = "g++"
) -> tuple[str, str, str] | None:
    """(compiler, include dir, library dir) to build against the OpenIGTLink C++ library; None when one is missing."""
    cxx = shutil.which(compiler)
    include = next((d for d in include_dirs if (Path(d) / "igtlPolyDataMessage.h").is_file()), None)
    library = next((d for d in library_dirs if any((Path(d) / f).exists() for f in LINKABLE)), None)
    if cxx is None or include is None or library is None:
        return None
    return cxx, include, library


def library_absent(compiler_errors: str) -> bool:
    """Whether a build failed for want of the library (a header or libOpenIGTLink), not because of the source."""
    missing_header = re.search(r"igtl\w*\.h: No such file", compiler_errors) is not None
    return missing_header or "cannot find -lOpenIGTLink" in compiler_errors


LIBRARY = find_reference_library()
if LIBRARY is None:
    pytest.skip(SKIP_REASON, allow_module_level=True)

from igtl_support import (  # noqa: E402 (after the skip: pyigtl may skip too)
    STAGE_STAMP_NS,
    assert_wire_equal,
    deformed_stage,
    expected_transform,
)

from liver_p2p_reg.bags.replay import replay_bag  # noqa: E402
from liver_p2p_reg.config import Config  # noqa: E402
from liver_p2p_reg.igtl import wire  # noqa: E402
from liver_p2p_reg.igtl.bridge import SlicerBridge, open_endpoint  # noqa: E402
from liver_p2p_reg.igtl.link import SlicerLink  # noqa: E402
from liver_p2p_reg.ros.messages import mesh_marker_mm  # noqa: E402
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm, stamp_to_ns  # noqa: E402
from liver_p2p_reg.slicer_config import SlicerConfig  # noqa: E402
from liver_p2p_reg.stream.outputs import DIAG_NAME  # noqa: E402

BAG = HERE.parents[1] / "bags" / "insilico_L9000001_D00_T007_random"
MODEL_POINTS, CLOUD_POINTS = 300, 200  # small decimation limits: every point is printed and compared
EVERY_POINT = 10_000  # the client's -p: print this many points and polygons per POLYDATA
SCENE = ("TRANSFORM:CTToSensor", "POLYDATA:PreopModel", "POLYDATA:IntraopCloud", "STRING:RegistrationStatus")


def compile_command(exe: Path) -> list[str]:
    """g++ -std=c++11 -I<headers> reference_client.cxx -o <exe> -L<lib> -Wl,-rpath,<lib> -lOpenIGTLink -lpthread"""
    cxx, include, library = LIBRARY
    linking = [f"-L{library}", f"-Wl,-rpath,{library}", "-lOpenIGTLink", "-lpthread"]
    return [cxx, "-std=c++11", f"-I{include}", str(SOURCE), "-o", str(exe), *linking]


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Path:
    exe = tmp_path_factory.mktemp("igtl_reference") / "reference_client"
    built = subprocess.run(compile_command(exe), capture_output=True, text=True, timeout=120)
    if built.returncode != 0:
        if library_absent(built.stderr):
            pytest.skip(SKIP_REASON)
        pytest.fail(f"reference_client.cxx does not compile:\n{built.stderr}", pytrace=False)
    return exe


# ---------------------------------------------------------------------------- the client's output
@dataclass
class Read:
    """What the client printed: its exit status and one dict of fields per line."""

    returncode: int
    lines: list[dict[str, str]]
    stdout: str

    def messages(self, type_name: str, device: str) -> list[dict[str, str]]:
        return [m for m in self.lines if m["kind"] == "MSG" and m["type"] == type_name and m["device"] == device]

    def one(self, type_name: str, device: str) -> dict[str, str]:
        got = self.messages(type_name, device)
        assert len(got) == 1, f"{len(got)} {type_name} {device} message(s) read:\n{self.stdout}"
        return got[0]


def parse_line(line: str) -> dict[str, str]:
    head, has_text, text = line.partition("\ttext=")  # the text comes last and may hold anything but a newline
    kind, *fields = head.split("\t")
    parsed = {"kind": kind}
    for field in fields:
        key, _, value = field.partition("=")
        parsed[key] = value
    if has_text:
        parsed["text"] = text
    return parsed


def start_client(exe: Path, port: int, *expected: str, timeout_s: float = 10.0) -> subprocess.Popen:
    command = [str(exe), "-p", str(EVERY_POINT), "127.0.0.1", str(port), str(timeout_s), *expected]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def finish_client(process: subprocess.Popen, timeout_s: float = 15.0) -> Read:
    try:
        out, err = process.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
    stdout = out.decode("utf-8")
    read = Read(process.returncode, [parse_line(line) for line in stdout.splitlines() if line], stdout)
    assert read.returncode is not None
    read.stdout += err.decode("utf-8", errors="replace")
    return read


def floats(text: str) -> np.ndarray:
    """'x,y,z;x,y,z' -> (N, 3) (or one row of any length)."""
    rows = [[float(v) for v in row.split(",")] for row in text.split(";") if row]
    return np.array(rows, dtype=np.float64)


def float32s(text: str) -> np.ndarray:
    """Points the client printed with 9 significant digits: exactly the library's float32 values."""
    return floats(text).astype(np.float32)


def cells(text: str) -> list[list[int]]:
    return [[int(v) for v in cell.split(",")] for cell in text.split(";") if cell]


def wire_stamp(stamp_ns: int) -> tuple[int, int]:
    """The protocol's timestamp, written out: whole seconds and the fraction in units of 2^-32 s."""
    return stamp_ns // 10**9, round((stamp_ns % 10**9) * 2**32 / 10**9)


def assert_stamp(message: dict[str, str], stamp_ns: int) -> None:
    sec, frac = (int(v) for v in message["stamp"].split(","))
    want_sec, want_frac = wire_stamp(stamp_ns)
    assert sec == want_sec and abs(frac - want_frac) <= 1, (message["stamp"], stamp_ns)


def assert_splatted_cloud(message: dict[str, str], cloud_mm: np.ndarray, leg_mm: float) -> None:
    """A cloud sent as triangles: 3N points, the first N the cloud (float32), polygon i = (i, i+N, i+2N)."""
    n = len(cloud_mm)
    assert message["version"] == "1" and message["crc"] == "ok"
    assert int(message["points"]) == 3 * n and int(message["polygons"]) == n
    assert int(message["vertices"]) == int(message["lines"]) == int(message["strips"]) == 0
    assert int(message["attributes"]) == 0 and int(message["polygon_words"]) == 4 * n
    points = float32s(message["first_points"])
    assert points.shape == (3 * n, 3)
    np.testing.assert_array_equal(points[:n], cloud_mm.astype(np.float32))
    np.testing.assert_allclose(floats(message["point_sum"])[0], points.sum(axis=0, dtype=np.float64), rtol=1e-12)
    index = np.arange(n)
    assert cells(message["first_polygons"]) == np.column_stack([index, index + n, index + 2 * n]).tolist()
    for corner in (points[n : 2 * n], points[2 * n :]):  # each leg along one axis, point_size_mm long
        np.testing.assert_allclose(np.linalg.norm(corner - points[:n], axis=1), leg_mm, atol=1e-4)


def evenly(points: np.ndarray, count: int) -> np.ndarray:
    """The documented decimation: `count` points evenly spread over the array (all of them if fewer)."""
    if len(points) <= count:
        return points
    return points[np.linspace(0, len(points) - 1, count).round().astype(np.int64)]


# ---------------------------------------------------------------------------- tests
class Tee:
    """The replay's observer: hands every message to the link and keeps it, for the expected values."""

    def __init__(self, link: SlicerLink) -> None:
        self.link = link
        self.inputs: dict[str, list] = {}
        self.outputs: list = []

    def on_input(self, topic: str, msg: object) -> None:
        self.inputs.setdefault(topic, []).append(msg)
        self.link.on_input(topic, msg)

    def on_output(self, output: object) -> None:
        self.outputs.append(output)
        self.link.on_output(output)


def test_a_replayed_registration_as_the_reference_library_reads_it(client: Path) -> None:
    config = SlicerConfig(host="127.0.0.1", port=0, max_model_points=MODEL_POINTS, max_cloud_points=CLOUD_POINTS)
    endpoint = open_endpoint(config)
    try:
        link = SlicerLink(SlicerBridge(config, endpoint))
        process = start_client(client, endpoint.port, *SCENE)
        assert endpoint.wait_for_peers(1, 10.0), "the reference client did not connect"
        tee = Tee(link)  # connected first: everything below goes out live, as to a Slicer already listening
        replay_bag(BAG, Config(method="icp"), max_frames=1, observer=tee)
        read = finish_client(process)
    finally:
        endpoint.close()
    assert read.returncode == 0, read.stdout
    assert all(m["crc"] == "ok" and m["version"] == "1" for m in read.lines if m["kind"] == "MSG"), read.stdout

    (output,) = [o for o in tee.outputs if o.pose is not None]
    pose = output.pose
    transform = read.one("TRANSFORM", "CTToSensor")
    assert_wire_equal(floats(transform["matrix"]).reshape(4, 4), expected_transform(pose.T_sensor_ct_mm, "LPS"))
    assert_stamp(transform, pose.stamp_ns)

    (verdict,) = [d for d in output.diagnostics if d.name == DIAG_NAME]
    status = read.one("STRING", "RegistrationStatus")
    assert status["text"] == f"{verdict.level_name}: {verdict.message}" and status["encoding"] == "3"
    assert_stamp(status, pose.stamp_ns)

    (cloud_msg,) = [m for m in tee.inputs["/intraop/points"] if stamp_to_ns(m.header.stamp) == pose.stamp_ns]
    cloud_mm = cloud_to_points_mm(cloud_msg)
    assert len(cloud_mm) == cloud_msg.width * cloud_msg.height > CLOUD_POINTS  # all finite: plain decimation
    cloud = read.one("POLYDATA", "IntraopCloud")
    assert_splatted_cloud(cloud, evenly(cloud_mm, CLOUD_POINTS), config.point_size_mm)
    assert_stamp(cloud, pose.stamp_ns)

    # the bag's /preop/mesh (same stamp as its points, logged first) is the model Slicer gets: a mesh, not points
    (preop_msg,), (mesh_msg,) = tee.inputs["/preop/points"], tee.inputs["/preop/mesh"]
    vertices_mm, triangles = mesh_marker_mm(mesh_msg)
    ras = vertices_mm * [-1.0, -1.0, 1.0]  # LPS ct frame -> Slicer's RAS
    model = read.one("POLYDATA", "PreopModel")
    assert int(model["points"]) == len(vertices_mm) and int(model["polygons"]) == len(triangles)
    np.testing.assert_array_equal(float32s(model["first_points"]), ras.astype(np.float32))
    assert cells(model["first_polygons"])[:5] == triangles[:5].tolist()
    assert_stamp(model, stamp_to_ns(preop_msg.header.stamp))


def test_a_mesh_a_utf8_verdict_and_live_updates(client: Path, rng: np.random.Generator) -> None:
    config = SlicerConfig(host="127.0.0.1", port=0, ct_convention="RAS")
    endpoint = open_endpoint(config)
    try:
        bridge = SlicerBridge(config, endpoint)
        vertices = rng.uniform(-80, 80, (30, 3))
        triangles = rng.integers(0, 30, (40, 3))
        first_pose = np.eye(4)
        first_pose[:3, 3] = [10.0, -20.0, 30.5]
        second_pose = np.array([[0.0, -1.0, 0.0, 101.25], [1.0, 0.0, 0.0, -7.5], [0.0, 0.0, 1.0, 250.0], [0, 0, 0, 1]])
        bridge.send_model(vertices, triangles, stamp_ns=1_700_000_000_000_000_001)
        bridge.send_pose(first_pose, stamp_ns=1_700_000_001_250_000_000)
        first_text = bridge.send_status("OK", "résidu 1.2 mm ≤ 4 mm", stamp_ns=1_700_000_001_250_000_000)
        process = start_client(
            client, endpoint.port, "POLYDATA:PreopModel", "TRANSFORM:CTToSensor:2", "STRING:RegistrationStatus:2"
        )
        assert endpoint.wait_for_peers(1, 10.0) and endpoint.flush(10.0)  # the state first, then live updates
        bridge.send_pose(second_pose, stamp_ns=1_700_000_002_999_999_999)
        second_text = bridge.send_status("WARN", "registered: residual 5.10 mm", stamp_ns=1_700_000_002_999_999_999)
        read = finish_client(process)
    finally:
        endpoint.close()
    assert read.returncode == 0, read.stdout

    model = read.one("POLYDATA", "PreopModel")
    assert int(model["points"]) == 30 and int(model["polygons"]) == 40 and int(model["polygon_words"]) == 160
    assert int(model["vertices"]) == int(model["lines"]) == int(model["strips"]) == 0
    np.testing.assert_array_equal(float32s(model["first_points"]), vertices.astype(np.float32))
    assert cells(model["first_polygons"]) == triangles.tolist()
    assert_stamp(model, 1_700_000_000_000_000_001)

    transforms = read.messages("TRANSFORM", "CTToSensor")
    assert len(transforms) == 2
    for message, pose in zip(transforms, (first_pose, second_pose), strict=True):
        assert_wire_equal(floats(message["matrix"]).reshape(4, 4), expected_transform(pose, "RAS"))
    assert_stamp(transforms[1], 1_700_000_002_999_999_999)

    statuses = read.messages("STRING", "RegistrationStatus")
    assert [(m["encoding"], m["text"]) for m in statuses] == [("106", first_text), ("3", second_text)]


def test_each_structure_as_the_reference_library_reads_it(client: Path) -> None:
    """`replay --structures` as Slicer gets it: one POLYDATA per structure, named by its label, sensor frame."""
    from liver_p2p_reg.structures_io import Structure

    (preop_msg,) = [m for topic, m in _bag_messages("/preop/points")]
    inside = cloud_to_points_mm(preop_msg).mean(axis=0)
    tumour = Structure("tumour", inside + np.random.default_rng(2).normal(size=(20, 3)) * 3.0, 0)
    vessel = Structure("portal vein", inside + np.linspace(-30, 30, 12)[:, None] * [1.0, 0.2, 0.0], 1)
    config = SlicerConfig(host="127.0.0.1", port=0)
    endpoint = open_endpoint(config)
    try:
        link = SlicerLink(SlicerBridge(config, endpoint))
        process = start_client(client, endpoint.port, "POLYDATA:tumour", "POLYDATA:portal vein")
        assert endpoint.wait_for_peers(1, 10.0), "the reference client did not connect"
        tee = Tee(link)
        replay_bag(BAG, Config(method="procrustes"), max_frames=1, observer=tee, structures=[tumour, vessel])
        read = finish_client(process)
    finally:
        endpoint.close()
    assert read.returncode == 0, read.stdout
    (output,) = [o for o in tee.outputs if o.pose is not None]
    for placed in output.structures:
        message = read.one("POLYDATA", placed.label)
        assert_splatted_cloud(message, placed.position_mm, config.point_size_mm)
        assert_stamp(message, output.pose.stamp_ns)


def test_the_deformed_model_as_the_reference_library_reads_it(client: Path) -> None:
    """The non-rigid stage's surface as the replay's observer sends it: the mesh's triangles on the deformed welded
    vertices, sensor frame, under its own device, beside the preop model (ct frame, RAS) of the same mesh."""
    from liver_p2p_reg.ros.topics import TOPIC_PREOP_MESH

    stage = deformed_stage()
    n_vertices, n_triangles = len(stage.vertices_mm), len(stage.triangles)
    config = SlicerConfig(host="127.0.0.1", port=0)
    endpoint = open_endpoint(config)
    try:
        link = SlicerLink(SlicerBridge(config, endpoint))
        process = start_client(client, endpoint.port, "POLYDATA:PreopModel", "POLYDATA:DeformedModel")
        assert endpoint.wait_for_peers(1, 10.0), "the reference client did not connect"
        link.on_input(TOPIC_PREOP_MESH, stage.marker)
        link.on_output(stage.output)
        read = finish_client(process)
    finally:
        endpoint.close()
    assert read.returncode == 0, read.stdout
    deformed = read.one("POLYDATA", "DeformedModel")
    assert deformed["version"] == "1" and deformed["crc"] == "ok"
    assert int(deformed["points"]) == n_vertices and int(deformed["polygons"]) == n_triangles
    assert int(deformed["polygon_words"]) == 4 * n_triangles
    assert int(deformed["vertices"]) == int(deformed["lines"]) == int(deformed["strips"]) == 0
    np.testing.assert_array_equal(float32s(deformed["first_points"]), stage.output.deformed_preop_mm.astype(np.float32))
    assert cells(deformed["first_polygons"]) == stage.triangles.tolist()
    assert_stamp(deformed, STAGE_STAMP_NS)
    model = read.one("POLYDATA", "PreopModel")  # the same triangles, undeformed, in the CT's RAS coordinates
    assert int(model["points"]) == n_vertices and cells(model["first_polygons"]) == stage.triangles.tolist()
    np.testing.assert_array_equal(float32s(model["first_points"]), (stage.vertices_mm * [-1, -1, 1]).astype(np.float32))


def _bag_messages(topic: str) -> list:
    from liver_p2p_reg.bags.io import read_messages

    return [(item.topic, item.msg) for item in read_messages(BAG, [topic])]


def test_the_client_fails_on_a_bad_crc(client: Path) -> None:
    good = wire.pack_message("STRING", "RegistrationStatus", wire.string_body("OK: fine"), 5)
    bad = bytearray(wire.pack_message("STRING", "Other", wire.string_body("ERROR: flipped"), 6))
    bad[-1] ^= 0x01  # the last body byte: the header's CRC no longer matches
    with socket.create_server(("127.0.0.1", 0)) as listener:
        process = start_client(client, listener.getsockname()[1], "STRING:RegistrationStatus", "STRING:Other")
        try:
            listener.settimeout(10.0)
            peer, _ = listener.accept()
            with peer:
                peer.sendall(good + bytes(bad))
                read = finish_client(process)
        finally:
            process.kill()  # no-op once it has exited
            process.wait()
    assert read.returncode == 2, read.stdout
    assert read.one("STRING", "RegistrationStatus")["text"] == "OK: fine"
    assert [m["kind"] for m in read.lines] == ["MSG", "CRC_FAIL"] and read.lines[1]["device"] == "Other"


def test_the_client_fails_on_a_missing_message(client: Path) -> None:
    device = "CTToSensorTwentyByte"  # the longest name: 20 bytes, no NUL left in the header's field
    config = SlicerConfig(host="127.0.0.1", port=0, transform_device=device)
    endpoint = open_endpoint(config)
    try:
        SlicerBridge(config, endpoint).send_pose(np.eye(4), stamp_ns=1)
        read = finish_client(start_client(client, endpoint.port, f"TRANSFORM:{device}", SCENE[1], timeout_s=1.0))
    finally:
        endpoint.close()
    assert read.returncode == 3, read.stdout
    assert len(device) == 20 and read.one("TRANSFORM", device)["crc"] == "ok"
    missing = [m for m in read.lines if m["kind"] == "MISSING"]
    assert [(m["expected"], m["seen"], m["why"]) for m in missing] == [("POLYDATA:PreopModel", "0", "timeout")]


def test_the_library_is_looked_for_where_debian_and_upstream_install_it(tmp_path: Path) -> None:
    assert LIBRARY is not None and Path(LIBRARY[1], "igtlClientSocket.h").is_file()
    nowhere = (str(tmp_path / "nowhere"),)
    assert find_reference_library(include_dirs=nowhere) is None  # no headers: the module skips with SKIP_REASON
    assert find_reference_library(library_dirs=nowhere) is None
    assert find_reference_library(compiler="no-such-compiler-g++") is None
    (tmp_path / "include").mkdir()
    (tmp_path / "include" / "igtlPolyDataMessage.h").touch()
    (tmp_path / "lib").mkdir()
    (tmp_path / "lib" / "libOpenIGTLink.so.1.11").touch()  # the runtime library alone cannot be linked
    assert find_reference_library((str(tmp_path / "include"),), (str(tmp_path / "lib"),)) is None
    (tmp_path / "lib" / "libOpenIGTLink.so").symlink_to("libOpenIGTLink.so.1.11")
    found = find_reference_library((str(tmp_path / "include"),), (str(tmp_path / "lib"),))
    assert found is not None and found[1:] == (str(tmp_path / "include"), str(tmp_path / "lib"))
    assert "libopenigtlink-dev" in SKIP_REASON
    assert library_absent("reference_client.cxx:26:10: fatal error: igtlClientSocket.h: No such file or directory")
    assert library_absent("/usr/bin/ld: cannot find -lOpenIGTLink: No such file or directory")
    assert not library_absent("reference_client.cxx:80:3: error: 'Foo' was not declared in this scope")
