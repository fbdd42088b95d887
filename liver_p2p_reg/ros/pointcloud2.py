"""sensor_msgs/PointCloud2 <-> numpy, written once for rclpy and rosbags message objects (metres)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from liver_p2p_reg.errors import InputError

# sensor_msgs/PointField datatype constants (identical in every ROS 2 distribution).
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
MAX_POINT_STEP = 1 << 16  # bytes per point: x, y, z and every extra field of a real sensor fit in far less
_NUMPY_OF = {
    INT8: "i1",
    UINT8: "u1",
    INT16: "i2",
    UINT16: "u2",
    INT32: "i4",
    UINT32: "u4",
    FLOAT32: "f4",
    FLOAT64: "f8",
}
_DATATYPE_OF = {np.dtype(v).newbyteorder("<").str[1:]: k for k, v in _NUMPY_OF.items()}
M_PER_MM = 1e-3
MM_PER_M = 1e3


@dataclass(frozen=True)
class MessageTypes:
    """The message classes of one ROS binding (rclpy or rosbags) and how it stores uint8[] data."""

    PointCloud2: type
    PointField: type
    Header: type
    Time: type
    wrap_bytes: Callable[[bytes], Any]  # rosbags wants np.uint8 arrays, rclpy array.array('B')


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def make_header(types: MessageTypes, frame_id: str, stamp_ns: int) -> Any:
    """A std_msgs/Header for either binding."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return types.Header(stamp=types.Time(sec=sec, nanosec=nanosec), frame_id=frame_id)


def field_names(msg: Any) -> list[str]:
    """Names of the fields of a PointCloud2 (for messages)."""
    return [f.name for f in msg.fields]


def cloud_to_points_m(msg: Any) -> np.ndarray:
    """Decode x/y/z of any PointCloud2 layout into finite (N, 3) float64 metres.

    Handles any field order, float32/float64 (and integer) coordinates, padding and extra
    fields, big-endian data, organized clouds (height > 1, row padding); drops NaN/inf points.
    Raises InputError for missing x/y/z fields or a truncated buffer.
    """
    rec = _records(msg, "xyz")
    points = np.empty((len(rec), 3), dtype=np.float64)
    with np.errstate(invalid="ignore"):  # garbage bytes may decode to NaN: dropped just below
        points[:, 0], points[:, 1], points[:, 2] = rec["x"], rec["y"], rec["z"]
    return points[np.isfinite(points).all(axis=1)]


def cloud_fields(msg: Any, names: Sequence[str]) -> dict[str, np.ndarray]:
    """The named fields of every point of a PointCloud2 (any layout, as `cloud_to_points_m`), each (N,) in its
    own dtype, native byte order; nothing dropped, so the fields stay aligned. InputError for a missing field."""
    rec = _records(msg, names)
    return {name: rec[name].astype(rec.dtype[name].newbyteorder("=")) for name in names}


def _records(msg: Any, names: Sequence[str]) -> np.ndarray:
    """The cloud's points as a numpy record array of the named fields (a view of its data where it can be)."""
    by_name = {f.name: f for f in msg.fields}
    twice = sorted({f.name for f in msg.fields if f.name in names and sum(g.name == f.name for g in msg.fields) > 1})
    if twice:  # which one is meant cannot be known: the last one was taken, and the geometry was wrong
        raise InputError(f"PointCloud2 has field(s) {', '.join(twice)} twice")
    missing = [name for name in names if name not in by_name]
    if missing:
        have = ", ".join(by_name) or "none"
        raise InputError(f"PointCloud2 lacks field(s) {', '.join(missing)} (fields: {have})")
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    n = height * width
    if point_step > MAX_POINT_STEP:  # numpy's record type takes a C int: 2**31 raised a ValueError past the checks
        raise InputError(f"PointCloud2 point_step {point_step} is implausible (more than {MAX_POINT_STEP} bytes)")
    if n == 0:  # an empty cloud is empty whatever its fields say
        return np.zeros(0, dtype=[(name, "f8") for name in names])
    order = ">" if msg.is_bigendian else "<"
    formats, offsets = [], []
    for name in names:
        f = by_name[name]
        if int(f.datatype) not in _NUMPY_OF:
            raise InputError(f"PointCloud2 field {name} has unknown datatype {f.datatype}")
        formats.append(order + _NUMPY_OF[int(f.datatype)])
        offsets.append(int(f.offset))
        if int(f.offset) + np.dtype(formats[-1]).itemsize > point_step:
            raise InputError(f"PointCloud2 field {name} lies outside point_step {point_step}")
    dtype = np.dtype({"names": list(names), "formats": formats, "offsets": offsets, "itemsize": point_step})
    row_step = max(row_step, width * point_step)  # some writers leave row_step at 0
    raw = np.frombuffer(memoryview(msg.data).cast("B"), dtype=np.uint8)
    needed = (height - 1) * row_step + width * point_step
    if raw.size < needed:
        raise InputError(
            f"PointCloud2 data is truncated: {raw.size} bytes for {height}x{width} points ({needed} needed)"
        )
    if row_step != width * point_step:  # organized cloud with row padding: cut each row
        rows = np.lib.stride_tricks.as_strided(raw, shape=(height, width * point_step), strides=(row_step, 1))
        raw = np.ascontiguousarray(rows).reshape(-1)
    else:
        raw = raw[: n * point_step]
    return np.frombuffer(raw, dtype=dtype, count=n)


def cloud_to_points_mm(msg: Any) -> np.ndarray:
    """`cloud_to_points_m` converted to millimetres (the core's unit), still all finite."""
    with np.errstate(over="ignore"):  # a value near float64's limit overflows to inf: dropped
        points = cloud_to_points_m(msg) * MM_PER_M
    return points[np.isfinite(points).all(axis=1)]


def points_to_cloud(
    points_m: np.ndarray,
    types: MessageTypes,
    *,
    frame_id: str,
    stamp_ns: int = 0,
    dtype: str | np.dtype = np.float32,
    big_endian: bool = False,
    field_order: Sequence[str] = ("x", "y", "z"),
    extra_fields: dict[str, np.ndarray] | None = None,
    pad_bytes: int = 0,
    height: int = 1,
) -> Any:
    """Build a PointCloud2 (metres) from (N, 3) points; the layout options exist for interop tests.

    extra_fields: name -> (N,) array packed after the named coordinates in `field_order`
    position order; pad_bytes: unused bytes at the end of each point; height > 1 gives an
    organized cloud (N must be divisible by height).
    """
    points_m = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    n = len(points_m)
    if height < 1 or n % height:
        raise InputError(f"cannot arrange {n} points into {height} rows")
    columns: dict[str, np.ndarray] = {"x": points_m[:, 0], "y": points_m[:, 1], "z": points_m[:, 2]}
    for name, values in (extra_fields or {}).items():
        columns[name] = np.asarray(values).reshape(-1)
    order = list(field_order) + [name for name in columns if name not in field_order]
    endian = ">" if big_endian else "<"
    names, formats, offsets, fields = [], [], [], []
    offset = 0
    for name in order:
        base = np.dtype(dtype) if name in "xyz" else columns[name].dtype
        code = np.dtype(base).newbyteorder("<").str[1:]
        if code not in _DATATYPE_OF:
            raise InputError(f"cannot store field {name} of dtype {base} in a PointCloud2")
        names.append(name)
        formats.append(endian + code)
        offsets.append(offset)
        fields.append(types.PointField(name=name, offset=offset, datatype=_DATATYPE_OF[code], count=1))
        offset += np.dtype(code).itemsize
    point_step = offset + pad_bytes
    rec = np.zeros(n, dtype=np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}))
    for name in names:
        rec[name] = columns[name]
    width = n // height
    return types.PointCloud2(
        header=make_header(types, frame_id, stamp_ns),
        height=height,
        width=width,
        fields=fields,
        is_bigendian=big_endian,
        point_step=point_step,
        row_step=point_step * width,
        data=types.wrap_bytes(rec.tobytes()),
        is_dense=bool(np.isfinite(points_m).all()),
    )


def structures_to_cloud(
    points_m: np.ndarray,
    label_ids: np.ndarray,
    types: MessageTypes,
    *,
    frame_id: str,
    stamp_ns: int = 0,
    error_bound_m: np.ndarray | None = None,
) -> Any:
    """A structures PointCloud2: x, y, z float32 (m), label_id uint32 and, when given, error_bound float32 (m)."""
    extra = {"label_id": np.asarray(label_ids, dtype=np.uint32).reshape(-1)}
    if error_bound_m is not None:
        extra["error_bound"] = np.asarray(error_bound_m, dtype=np.float32).reshape(-1)
    return points_to_cloud(points_m, types, frame_id=frame_id, stamp_ns=stamp_ns, extra_fields=extra)


def cloud_to_structures(msg: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(points (N, 3) float64 m, label ids (N,) int64, error bounds (N,) float64 m or None) of a structures
    PointCloud2; points with a non-finite coordinate are dropped with their fields. InputError when the
    cloud lacks x/y/z or label_id, or a label id is not a non-negative whole number."""
    names = ["x", "y", "z", "label_id"] + (["error_bound"] if "error_bound" in field_names(msg) else [])
    fields = cloud_fields(msg, names)
    points = np.column_stack([fields[c].astype(np.float64) for c in "xyz"]).reshape(-1, 3)
    ids = fields["label_id"].astype(np.float64)
    keep = np.isfinite(points).all(axis=1)
    points, ids = points[keep], ids[keep]
    # below 2**31: a float64 id of 1e300 is whole too, and cast to an integer it became garbage
    if not (np.isfinite(ids).all() and (ids >= 0).all() and (ids < 2**31).all() and (ids == np.round(ids)).all()):
        raise InputError("PointCloud2 label_id must hold non-negative whole numbers below 2**31")
    bounds = fields["error_bound"].astype(np.float64)[keep] if "error_bound" in fields else None
    return points, ids.astype(np.int64), bounds
