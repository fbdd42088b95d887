"""What a flight recording stores exactly: point clouds that decode to the recorded millimetres bit for bit,
the subsurface structures a registration moved, and the digests re-runs are compared by (bags/recorder.py writes
them, bags/flight_replay.py reads them back)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from typing import Any

import numpy as np

from liver_p2p_reg.bags.io import rosbags_output_types
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.ros.messages import parse_structure_labels, structure_labels_json
from liver_p2p_reg.ros.pointcloud2 import FLOAT64, M_PER_MM, MM_PER_M, cloud_fields, cloud_to_points_mm, points_to_cloud
from liver_p2p_reg.stream.structures import fallback_label
from liver_p2p_reg.structures_io import PlacedStructure, Structure, stacked_points

MM_FIELDS = ("x_mm", "y_mm", "z_mm")  # exact float64 millimetres, beside x/y/z, when float32 metres lose bits
LABEL_LIST_MAX = 4096  # label ids from here up are named in the labels record's `names` only


def points_message(
    points_mm: np.ndarray, frame_id: str, stamp_ns: int, extra_fields: dict[str, np.ndarray] | None = None
) -> Any:
    """A PointCloud2 in metres (float32, as the bags) that decodes back to exactly these millimetres; when
    float32 metres cannot (points not from a float32 cloud), float64 x_mm/y_mm/z_mm fields carry them exactly.
    `extra_fields`: more per-point fields (a structures cloud's label_id)."""
    points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    types = rosbags_output_types().cloud
    metres = (points * M_PER_MM).astype(np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        exact = bool(np.isfinite(points).all()) and np.array_equal(metres.astype(np.float64) * 1e3, points)
    extra = dict(extra_fields or {})
    if not exact:
        extra.update({name: points[:, i].copy() for i, name in enumerate(MM_FIELDS)})
    return points_to_cloud(metres, types, frame_id=frame_id, stamp_ns=stamp_ns, extra_fields=extra or None)


def structures_message(structures: Sequence[Structure], stamp_ns: int) -> Any:
    """/preop/structures as the recording keeps it: every structure's points (ct frame), exactly, with its label_id."""
    points, ids = stacked_points(structures)
    return points_message(points, "ct", stamp_ns, {"label_id": ids.astype(np.uint32)})


def structure_labels(structures: Sequence[Structure], stamp_ns: int) -> str:
    """/preop/structure_labels as the recording keeps it: the loader's list of names by label id (`bag play`
    publishes it) where the ids are small, and always `names`, {label id: name}, which any id fits (a publisher
    of label ids near 2**31 would otherwise make a list of 2**31 names)."""
    values = {"labels": [], "stamp_ns": int(stamp_ns)}
    if max((s.label_id for s in structures), default=-1) < LABEL_LIST_MAX:
        values = json.loads(structure_labels_json(structures, stamp_ns))
    values["names"] = {str(s.label_id): s.label for s in structures}
    return json.dumps(values)


def message_structures(msg: Any, labels_text: str) -> list[Structure]:
    """The structures `structures_message` and /preop/structure_labels stored, bit for bit, named as recorded."""
    points, ids = message_points_mm(msg), cloud_fields(msg, ["label_id"])["label_id"].astype(np.int64)
    names, _ = parse_structure_labels(labels_text)
    label = dict(enumerate(names))
    sparse = json.loads(labels_text).get("names")  # by label id: what `structure_labels` wrote for any id
    if isinstance(sparse, dict):
        label = {int(k): str(v) for k, v in sparse.items() if str(k).isascii() and str(k).isdigit()}
    _, first = np.unique(ids, return_index=True)  # in the order they were written
    return [Structure(label.get(int(i), fallback_label(i)), points[ids == i], int(i)) for i in ids[np.sort(first)]]


def placed_sha256(placed: Sequence[PlacedStructure]) -> str | None:
    """The digest a recording keeps of a registration's placed structures (label ids, positions and bounds as
    published, float64 mm), to compare re-runs bit for bit; None when it placed none."""
    if not placed:
        return None
    digest = hashlib.sha256()
    for s in placed:
        digest.update(np.int64(s.label_id).tobytes())
        digest.update(np.ascontiguousarray(s.current_position_mm, dtype="<f8").tobytes())
        digest.update(np.ascontiguousarray(s.current_error_bound_mm, dtype="<f8").tobytes())
    return digest.hexdigest()


def message_points_mm(msg: Any) -> np.ndarray:
    """The millimetres `points_message` stored, bit for bit (NaN rows included when it stored them)."""
    fields = {f.name: f for f in msg.fields}
    if not all(name in fields for name in MM_FIELDS):
        return cloud_to_points_mm(msg)  # float32 metres decode exactly as the node decodes them
    if any(int(fields[name].datatype) != FLOAT64 for name in MM_FIELDS) or msg.is_bigendian:
        raise InputError("flight recording: x_mm/y_mm/z_mm must be little-endian float64")
    n, step = int(msg.width) * int(msg.height), int(msg.point_step)
    raw = np.frombuffer(memoryview(msg.data).cast("B"), dtype=np.uint8)
    rec = np.frombuffer(raw, dtype=np.dtype({"names": list(MM_FIELDS), "formats": ["<f8"] * 3,
                        "offsets": [int(fields[k].offset) for k in MM_FIELDS], "itemsize": step}), count=n)  # fmt: skip
    return np.stack([rec[k] for k in MM_FIELDS], axis=1).astype(np.float64)


def exact_metres(points_mm: np.ndarray) -> np.ndarray:
    """Float64 metres that decode (x 1000, as /preop/mesh is read) to exactly these millimetres wherever a value
    within 3 ulps of mm / 1000 does: always for millimetres that came as metres (a mesh received as a Marker)."""
    mm = np.asarray(points_mm, dtype=np.float64)
    flat_mm, metres = mm.reshape(-1), (mm * M_PER_MM).reshape(-1)
    for step in (1, -1, 2, -2, 3, -3):
        wrong = np.flatnonzero(metres * MM_PER_M != flat_mm)
        if not len(wrong):
            break
        candidate = flat_mm[wrong] * M_PER_MM
        for _ in range(abs(step)):
            candidate = np.nextafter(candidate, np.inf if step > 0 else -np.inf)
        hit = candidate * MM_PER_M == flat_mm[wrong]
        metres[wrong[hit]] = candidate[hit]
    return metres.reshape(mm.shape)


def points_sha256(points_mm: np.ndarray | None) -> str | None:
    """The digest a recording keeps of a float64 cloud (the deformed preop surface), to compare re-runs bit for bit."""
    if points_mm is None:
        return None
    return hashlib.sha256(np.ascontiguousarray(points_mm, dtype="<f8").tobytes()).hexdigest()


def structures_key(structures: Sequence[Structure]) -> bytes:
    """What tells one set of structures from another: labels, ids and points' bits."""
    digest = hashlib.sha256()
    for s in structures:
        points = np.ascontiguousarray(s.points_mm, dtype="<f8")
        digest.update(f"{s.label}\0{s.label_id}\0{points.shape}\0".encode() + points.tobytes())
    return digest.digest()
