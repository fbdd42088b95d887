"""PointCloud2 <-> numpy round trips for every supported layout, on rosbags message objects."""

import struct

import numpy as np
import pytest

from liver_p2p_reg.bags.io import rosbags_types, typestore
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.ros.pointcloud2 import FLOAT32, FLOAT64, cloud_to_points_m, cloud_to_points_mm, points_to_cloud

TYPES = rosbags_types()


@pytest.fixture
def points_m():
    return np.random.default_rng(3).uniform(-0.15, 0.15, size=(60, 3))


@pytest.mark.parametrize(
    "layout",
    [
        {},
        {"dtype": np.float64},
        {"big_endian": True},
        {"big_endian": True, "dtype": np.float64},
        {"field_order": ("z", "x", "y")},
        {"extra_fields": {"intensity": np.arange(60, dtype=np.float32), "ring": np.arange(60, dtype=np.uint16)}},
        {"pad_bytes": 4},
        {"height": 6},
        {"height": 4, "field_order": ("y", "z", "x"), "pad_bytes": 3, "big_endian": True},
    ],
)
def test_round_trip_layouts(points_m, layout):
    msg = points_to_cloud(points_m, TYPES, frame_id="cam", stamp_ns=1_500_000_007, **layout)
    # the bytes survive CDR serialization as written in bags
    msg = typestore().deserialize_cdr(typestore().serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)
    out = cloud_to_points_m(msg)
    tol = 1e-12 if layout.get("dtype") is np.float64 else 1e-7
    np.testing.assert_allclose(out, points_m, atol=tol)
    assert msg.header.frame_id == "cam" and msg.header.stamp.sec == 1 and msg.header.stamp.nanosec == 500_000_007
    assert msg.height == layout.get("height", 1)


def test_hand_packed_big_endian_with_row_padding():
    """An organized 2x2 cloud packed with struct (independent of our writer): fields y,x,z float64 BE + rgb."""
    pts = [(1.0, 2.0, 3.0), (4.0, 5.0, 6.0), (7.0, 8.0, 9.0), (np.nan, 1.0, 1.0)]
    point_step = 8 * 3 + 4 + 4  # y,x,z doubles, rgb uint32, 4 pad bytes
    row_step = 2 * point_step + 8  # 8 bytes of row padding
    data = b""
    for row in range(2):
        for x, y, z in pts[2 * row : 2 * row + 2]:
            data += struct.pack(">dddI4x", y, x, z, 0xFF00FF)
        data += b"\xee" * 8
    PF = TYPES.PointField
    msg = TYPES.PointCloud2(
        header=TYPES.Header(stamp=TYPES.Time(sec=0, nanosec=0), frame_id="cam"),
        height=2,
        width=2,
        fields=[
            PF(name="y", offset=0, datatype=FLOAT64, count=1),
            PF(name="x", offset=8, datatype=FLOAT64, count=1),
            PF(name="z", offset=16, datatype=FLOAT64, count=1),
            PF(name="rgb", offset=24, datatype=6, count=1),
        ],
        is_bigendian=True,
        point_step=point_step,
        row_step=row_step,
        data=np.frombuffer(data, dtype=np.uint8),
        is_dense=False,
    )
    out = cloud_to_points_m(msg)
    np.testing.assert_array_equal(out, np.array(pts[:3]))  # the NaN point is dropped
    np.testing.assert_array_equal(cloud_to_points_mm(msg), np.array(pts[:3]) * 1000)


def test_nan_points_removed(points_m):
    pts = points_m.copy()
    pts[::3, 1] = np.nan
    pts[1, 2] = np.inf
    out = cloud_to_points_m(points_to_cloud(pts, TYPES, frame_id="cam"))
    assert len(out) == 60 - 20 - 1
    assert np.isfinite(out).all()


def test_values_that_overflow_in_mm_are_dropped_silently(points_m, recwarn):
    pts = points_m.copy()
    pts[4] = 1e307  # finite in metres, infinite once multiplied by 1000
    out = cloud_to_points_mm(points_to_cloud(pts, TYPES, frame_id="cam", dtype=np.float64))
    assert len(out) == 59 and np.isfinite(out).all()
    assert len(recwarn) == 0  # no numpy RuntimeWarning in the node's log


def test_missing_xyz_field_is_input_error(points_m):
    msg = points_to_cloud(points_m, TYPES, frame_id="cam", extra_fields={"intensity": np.ones(60, np.float32)})
    msg.fields = [f for f in msg.fields if f.name != "z"]
    with pytest.raises(InputError, match="lacks field"):
        cloud_to_points_m(msg)


def test_truncated_data_is_input_error(points_m):
    msg = points_to_cloud(points_m, TYPES, frame_id="cam")
    msg.data = msg.data[:-5]
    with pytest.raises(InputError, match="truncated"):
        cloud_to_points_m(msg)


def test_empty_cloud_gives_no_points():
    msg = points_to_cloud(np.zeros((0, 3)), TYPES, frame_id="cam")
    assert cloud_to_points_m(msg).shape == (0, 3)
    assert msg.fields[0].datatype == FLOAT32
