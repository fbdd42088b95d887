"""A Slicer stand-in for the tests: records every OpenIGTLink message, decoded independently of the product.

Headers, TRANSFORM and STRING bodies are decoded by pyigtl and every body's CRC is checked with
pyigtl's CRC-64 (crcmod); pyigtl cannot read POLYDATA (its reader is unfinished), so that body is
read here, straight from the protocol's layout.
"""

from __future__ import annotations

import os
import socket
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

try:
    import pyigtl  # noqa: F401 (re-exported: the tests use its message classes and client)
except ImportError:
    if os.environ.get("CI", "").lower() == "true":  # `make setup` installs the slicer extra: CI must run these
        raise
    pytest.skip("pyigtl not importable; install the slicer extra: pip install -e '.[slicer]'", allow_module_level=True)
from pyigtl.messages import CRC64, MessageBase  # noqa: E402


@dataclass
class Polydata:
    points: np.ndarray  # (N, 3) float64 from float32
    polygons: list[np.ndarray]
    vertices: int  # VERTICES cell count (0: Slicer cannot read vertex cells, see igtl/scene.py)


@dataclass
class Received:
    type_name: str
    device: str
    timestamp_s: float
    value: Any  # TRANSFORM: 4x4, STRING: str, POLYDATA: Polydata, else the raw body
    received_s: float


def parse_polydata(body: bytes) -> Polydata:
    """The POLYDATA body per the protocol: 10 uint32 counts, float32 points, uint32 cell arrays (big-endian)."""
    counts = struct.unpack(">10I", body[:40])
    n_points, n_vertices, vertex_bytes, _, line_bytes, n_polygons, polygon_bytes = counts[:7]
    points = np.frombuffer(body, dtype=">f4", count=3 * n_points, offset=40).reshape(-1, 3).astype(np.float64)
    offset = 40 + 12 * n_points + vertex_bytes + line_bytes
    words = np.frombuffer(body, dtype=">u4", count=polygon_bytes // 4, offset=offset)
    polygons, i = [], 0
    for _ in range(n_polygons):
        polygons.append(words[i + 1 : i + 1 + words[i]].astype(np.int64))
        i += 1 + int(words[i])
    assert i == len(words), "POLYGONS size does not match its cells"
    return Polydata(points, polygons, n_vertices)


def recv_exact(sock: socket.socket, size: int) -> bytes | None:
    chunks, got = [], 0
    while got < size:
        chunk = sock.recv(size - got)
        if not chunk:
            return None
        chunks.append(chunk)
        got += len(chunk)
    return b"".join(chunks)


class Recorder:
    """Reads a connected socket on a thread and keeps every message in order."""

    def __init__(self, sock: socket.socket) -> None:
        sock.settimeout(None)  # a quiet stream is no error: wait as long as it takes
        self.sock = sock
        self.messages: list[Received] = []
        self.closed_by_peer = False
        self.error: Exception | None = None
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    @classmethod
    def connect(cls, port: int, host: str = "127.0.0.1", timeout_s: float = 10.0) -> Recorder:
        end = time.monotonic() + timeout_s
        while True:
            try:
                return cls(socket.create_connection((host, port), timeout=timeout_s))
            except ConnectionRefusedError:
                if time.monotonic() > end:
                    raise
                time.sleep(0.05)

    def _read(self) -> None:
        try:
            while True:
                header = recv_exact(self.sock, MessageBase.IGTL_HEADER_SIZE)
                if header is None:
                    self.closed_by_peer = True
                    return
                fields = MessageBase.parse_header(header)
                body = recv_exact(self.sock, fields["body_size"])
                if body is None:
                    self.closed_by_peer = True
                    return
                assert struct.unpack(">Q", header[50:58])[0] == CRC64(body), "CRC mismatch"
                self._keep(fields, body)
        except OSError:  # closed by close()
            return
        except Exception as exc:  # a decoding failure fails the test that waits on it
            self.error = exc

    def _keep(self, fields: dict, body: bytes) -> None:
        kind = fields["message_type"]
        if kind == "POLYDATA":
            value: Any = parse_polydata(body)
        elif kind in ("TRANSFORM", "STRING"):
            message = MessageBase.create_message(kind)
            message.unpack(fields, body)
            value = np.asarray(message.matrix, dtype=np.float64) if kind == "TRANSFORM" else message.string
        else:
            value = body
        with self._lock:
            self.messages.append(Received(kind, fields["device_name"], fields["timestamp"], value, time.monotonic()))

    def of(self, device: str) -> list[Received]:
        with self._lock:
            return [m for m in self.messages if m.device == device]

    def wait_for(self, device: str, count: int = 1, timeout_s: float = 20.0) -> list[Received]:
        end = time.monotonic() + timeout_s
        while len(self.of(device)) < count and time.monotonic() < end and self.error is None:
            time.sleep(0.01)
        if self.error is not None:
            raise self.error
        got = self.of(device)
        assert len(got) >= count, f"{len(got)} {device} message(s) after {timeout_s} s, {count} expected"
        return got

    def close(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()
        self._thread.join(2.0)


class SlicerServerStandIn:
    """Slicer's connector of type Server: accepts one connection and records it."""

    def __init__(self, port: int = 0) -> None:
        self.listener = socket.create_server(("127.0.0.1", port))
        self.port = self.listener.getsockname()[1]
        self.recorder: Recorder | None = None
        self._thread = threading.Thread(target=self._accept, daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        try:
            sock, _ = self.listener.accept()
        except OSError:
            return
        self.recorder = Recorder(sock)

    def wait_connected(self, timeout_s: float = 10.0) -> Recorder:
        self._thread.join(timeout_s)
        assert self.recorder is not None, "nobody connected"
        return self.recorder

    def close(self) -> None:
        self.listener.close()
        if self.recorder is not None:
            self.recorder.close()


def hung_up(sock: socket.socket, timeout_s: float = 10.0) -> bool:
    """Whether the other side closed the connection (EOF or reset) within the timeout."""
    sock.settimeout(timeout_s)
    try:
        while sock.recv(1 << 20):
            pass
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False
    return True


def free_port() -> int:
    """A port nothing listens on right now (the OS's next ephemeral one)."""
    with socket.create_server(("127.0.0.1", 0)) as probe:
        return probe.getsockname()[1]


def expected_transform(T_sensor_ct_mm: np.ndarray, ct_convention: str = "LPS") -> np.ndarray:
    """The documented conversion, written out independently: T @ diag(-1, -1, 1, 1) for an LPS ct frame."""
    flip = np.diag([-1.0, -1.0, 1.0, 1.0]) if ct_convention == "LPS" else np.eye(4)
    return np.asarray(T_sensor_ct_mm, dtype=np.float64) @ flip


def assert_wire_equal(received: np.ndarray, expected: np.ndarray) -> None:
    """TRANSFORM carries float32 (the protocol): equal to the float32 of the expected matrix within 1e-6."""
    np.testing.assert_allclose(received, expected.astype(np.float32).astype(np.float64), rtol=0, atol=1e-6)


def mesh_marker_msg(vertices_mm: np.ndarray, triangles: np.ndarray, stamp_ns: int, frame_id: str = "ct") -> Any:
    """A /preop/mesh Marker TRIANGLE_LIST (rosbags classes, metres), built as the loader and the bags build it."""
    from liver_p2p_reg.bags.mesh import preop_mesh_marker

    return preop_mesh_marker(vertices_mm, triangles, frame_id, stamp_ns)


@dataclass
class DeformedStage:
    """One registration of a procedural liver with the non-rigid stage applied on its /preop/mesh."""

    marker: Any  # the /preop/mesh message the core (and a Slicer link) got
    vertices_mm: np.ndarray  # its welded vertices (ct frame), the order of output.deformed_preop_mm
    triangles: np.ndarray
    points_mm: np.ndarray  # the model's /preop/points (sampled from the mesh)
    output: Any  # the CoreOutput: rigid pose, deformed surface


STAGE_STAMP_NS = 1_700_000_000_500_000_000  # the intraop view's (and so the pose's) stamp


def deformed_stage() -> DeformedStage:
    """A small procedural liver (an elastic model built in about a second) registered by NodeCore as register_node
    runs it, /preop/mesh marker in, exact rigid pose from the fiducials, then the non-rigid stage on the mesh."""
    from liver_p2p_reg.cloud_io import sample_mesh_surface
    from liver_p2p_reg.config import Config
    from liver_p2p_reg.phantom.anatomy import make_liver
    from liver_p2p_reg.phantom.dataset import make_case
    from liver_p2p_reg.phantom.simulate import simulate_liver
    from liver_p2p_reg.ros.messages import feed_preop_mesh_msg, mesh_marker_mm
    from liver_p2p_reg.stream.core import NodeCore
    from liver_p2p_reg.stream.outputs import OK

    sim = simulate_liver(7, 1, target_tets=1500, liver=make_liver(7, spacing_mm=5.0))
    case = make_case(sim, 0, 0.35, seed=1)
    marker = mesh_marker_msg(case["src_pcd"], case["src_triangles"], stamp_ns=5)
    vertices, triangles = mesh_marker_mm(marker)
    points = sample_mesh_surface(case["src_pcd"], case["src_triangles"], seed=0)
    config = Config(method="procrustes", mode="on_demand", deform=True, deform_modes=12, deform_target_tets=1500)
    core = NodeCore(config)
    assert feed_preop_mesh_msg(core, marker).level == OK
    assert core.set_preop(points, "ct", 5).level == OK  # the mesh's stamp: the stage runs on the mesh
    core.set_preop_fiducials(case["src_marker"], 5)
    core.set_intraop_fiducials(case["tgt_marker"], STAGE_STAMP_NS)
    core.on_intraop_points(case["tgt_pcd"], "camera", STAGE_STAMP_NS)
    output = core.reregister()
    values = output.diagnostics[0].values
    assert values.get("deform_applied") == "true" and values["deform_surface"] == "mesh", values
    return DeformedStage(marker, vertices, triangles, points, output)
