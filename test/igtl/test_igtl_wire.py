"""OpenIGTLink encoding and Slicer's conventions, checked against pyigtl and the protocol's layout (no ROS)."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from igtl_support import CRC64, MessageBase, assert_wire_equal, expected_transform, parse_polydata, pyigtl
from scipy.spatial.transform import Rotation

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.igtl import scene, wire
from liver_p2p_reg.slicer_config import SlicerConfig


def unpack(data: bytes) -> tuple[dict, bytes]:
    fields = MessageBase.parse_header(data[: wire.HEADER_SIZE])
    body = data[wire.HEADER_SIZE :]
    assert fields["body_size"] == len(body)
    assert struct.unpack(">Q", data[50:58])[0] == CRC64(body)  # pyigtl's own CRC-64 (crcmod)
    return fields, body


def random_pose(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.uniform(-300, 300, 3)
    return T


def test_transform_as_pyigtl_reads_it(rng: np.random.Generator) -> None:
    T = random_pose(rng)
    data = wire.pack_message("TRANSFORM", "CTToSensor", wire.transform_body(T), 1_700_000_000_250_000_000)
    fields, body = unpack(data)
    assert fields["message_type"] == "TRANSFORM" and fields["device_name"] == "CTToSensor"
    assert fields["header_version"] == 1
    assert fields["timestamp"] == pytest.approx(1_700_000_000.25, abs=1e-6)
    message = pyigtl.TransformMessage()
    message.unpack(fields, body)
    assert_wire_equal(message.matrix, T)


def test_string_ascii_and_utf8_as_pyigtl_reads_them() -> None:
    for text in ("WARN: registered: residual 5.10 mm", "OK: résidu 1.0 mm ≤ 4"):
        fields, body = unpack(wire.pack_message("STRING", "RegistrationStatus", wire.string_body(text), 1))
        message = pyigtl.StringMessage()
        message.unpack(fields, body)
        assert message.string == text
    long_text = "é" * 40000  # 80000 UTF-8 bytes: cut to the format's limit on a character boundary
    body = wire.string_body(long_text)
    assert wire.decode_string(body) == "é" * (wire.MAX_STRING_BYTES // 2)


def test_polydata_mesh_and_splatted_points_per_the_protocol(rng: np.random.Generator) -> None:
    vertices = rng.uniform(-50, 50, (30, 3))
    triangles = rng.integers(0, 30, (40, 3))
    poly = parse_polydata(wire.polydata_body(vertices, triangles))
    np.testing.assert_allclose(poly.points, vertices.astype(np.float32), atol=0)
    assert [p.tolist() for p in poly.polygons] == triangles.tolist()
    points = rng.uniform(-50, 50, (7, 3))
    splatted = parse_polydata(wire.polydata_body(*scene.splat(points, 1.5)))
    assert len(splatted.points) == 21 and len(splatted.polygons) == 7 and splatted.vertices == 0
    np.testing.assert_allclose(splatted.points[:7], points.astype(np.float32), atol=0)  # the first N are the cloud
    for i, cell in enumerate(splatted.polygons):
        corners = splatted.points[cell]
        assert cell[0] == i and np.allclose(np.linalg.norm(corners[1:] - corners[0], axis=1), 1.5, atol=1e-4)
    with pytest.raises(InputError, match="does not exist"):
        wire.polydata_body(vertices, [[0, 1, 30]])


def test_slicer_transform_maps_slicer_ras_of_the_ct_to_the_sensor(rng: np.random.Generator) -> None:
    T = random_pose(rng)
    points_ct = rng.uniform(-100, 100, (50, 3))
    in_sensor = points_ct @ T[:3, :3].T + T[:3, 3]
    for convention in ("LPS", "RAS"):
        M = scene.slicer_transform(T, convention)
        np.testing.assert_allclose(M, expected_transform(T, convention), atol=1e-12)
        ras = scene.ct_to_slicer(points_ct, convention)
        np.testing.assert_allclose(ras @ M[:3, :3].T + M[:3, 3], in_sensor, atol=1e-9)
        assert np.linalg.det(M[:3, :3]) == pytest.approx(1.0)  # a rotation: triangles keep their winding
    np.testing.assert_allclose(scene.ct_to_slicer(points_ct, "LPS")[:, :2], -points_ct[:, :2])
    with pytest.raises(InputError):
        scene.slicer_transform(np.full((4, 4), np.nan), "LPS")


def test_decimate_is_bounded_and_even() -> None:
    points = np.arange(3000, dtype=float).reshape(-1, 3)
    assert np.array_equal(scene.decimate(points, 5000), points)
    kept = scene.decimate(points, 10)
    assert len(kept) == 10 and kept[0, 0] == 0 and kept[-1, 0] == points[-1, 0]


def test_stream_reader_splits_checks_and_refuses_garbage() -> None:
    first = wire.pack_message("STRING", "a", wire.string_body("one"), 5)
    second = pyigtl.TransformMessage(np.eye(4), device_name="FromSlicer").pack()  # what Slicer may send us
    reader = wire.StreamReader()
    got = [m for byte in first + second for m in reader.feed(bytes([byte]))]
    assert [(m.type_name, m.device) for m in got] == [("STRING", "a"), ("TRANSFORM", "FromSlicer")]
    assert wire.decode_string(got[0].body) == "one" and got[0].stamp_ns == 5
    bad_crc = bytearray(first)
    bad_crc[-1] ^= 1
    garbage = {
        "header version": b"\x00\x07" + first[2:],
        "type": first[:2] + b"TRANS\x01FORM\0\0\0" + first[14:],
        "padding": first[:2] + b"STRING\0X\0\0\0\0" + first[14:],
        "body size": first[:42] + struct.pack(">Q", 1 << 40) + first[50:],
        "CRC": bytes(bad_crc),
    }
    for what, data in garbage.items():
        with pytest.raises(wire.ProtocolError):
            wire.StreamReader().feed(data)
        assert what


def test_slicer_config_refuses_bad_settings() -> None:
    assert SlicerConfig().validate().port == 18944
    for bad in (
        {"role": "peer"},
        {"ct_convention": "RAI"},
        {"port": 70000},
        {"role": "client", "port": 0},
        {"transform_device": "X" * 21},
        {"model_device": "CTToSensor"},
        {"deformed_model_device": "PreopModel"},  # the deformed model must not replace the model in Slicer
        {"deformed_model_device": ""},
        {"max_cloud_points": 0},
        {"cloud_rate_hz": float("nan")},
        {"cloud_rate_hz": -1.0},
        {"colour": "red"},
    ):
        with pytest.raises(InputError):
            SlicerConfig().replace(**bad)
    assert SlicerConfig.from_dict({"port": "18945", "cloud_rate_hz": 2}).port == 18945
