"""The flight recorder: NodeCore's hook (stream/record_hooks.py) written to rosbag2-compatible MCAP, and read back.

One bare MCAP file per recording (profile `ros2`, CDR messages with their `ros2msg` schemas, as
rosbag2 writes them), unchunked and flushed after every registration: a writer killed at any
moment leaves every completed registration readable; `bags/flight_replay.py` reads the records one
by one, stops cleanly at a truncated tail (no footer, summary or index needed) and re-runs them.
Topics and the exactness of what they carry: msg_docs/flight_recorder.md.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from liver_p2p_reg.bags.io import (
    DIAGNOSTIC_ARRAY,
    MARKER,
    POINTCLOUD2,
    POSE_STAMPED,
    _qos,
    rosbags_marker_types,
    rosbags_output_types,
    typestore,
)
from liver_p2p_reg.bags.mcap_check import starts_as_mcap
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.weights_id import weights_sha256
from liver_p2p_reg.ros.messages import (
    diagnostic_array,
    pose_stamped,
    registered_structures_cloud,
    structure_labels_json,
    triangle_list_marker,
)
from liver_p2p_reg.ros.pointcloud2 import FLOAT64, M_PER_MM, MM_PER_M, cloud_to_points_mm, points_to_cloud
from liver_p2p_reg.ros.topics import (
    TOPIC_DEFORMED_PREOP,
    TOPIC_DIAGNOSTICS,
    TOPIC_INTRAOP,
    TOPIC_INTRAOP_FIDUCIALS,
    TOPIC_POSE,
    TOPIC_PREOP,
    TOPIC_PREOP_FIDUCIALS,
    TOPIC_PREOP_MESH,
    TOPIC_PREOP_STRUCTURES,
    TOPIC_STRUCTURE_LABELS,
    TOPIC_STRUCTURES,
    qos_of,
)
from liver_p2p_reg.stream.record_hooks import Recorder, RegistrationRecord

if TYPE_CHECKING:
    from liver_p2p_reg.stream.deformation import PreopMesh
    from liver_p2p_reg.structures_io import PlacedStructure, Structure

FORMAT = "liver_p2p_reg.flight_recorder/1"
STRING = "std_msgs/msg/String"
LIBRARY = "liver_p2p_reg flight recorder"  # the MCAP Header's `library` of every recording (how one is told)
TOPIC_PREFIX = "/flight_recorder/"
TOPIC_META = "/flight_recorder/meta"  # first message of every file: versions, weights, session, file index
TOPIC_CONFIG = "/flight_recorder/config"  # the full parameter set, at the head of a file and after every change
TOPIC_EVENT = "/flight_recorder/event"  # reset_survey; in a file's head: tracker (the prior), snapshot_end
TOPIC_REGISTRATION = "/flight_recorder/registration"  # one per registration, its last record (the commit)
MM_FIELDS = ("x_mm", "y_mm", "z_mm")  # exact float64 millimetres, beside x/y/z, when float32 metres lose bits
LABEL_LIST_MAX = 4096  # label ids from here up are named in the labels record's `names` only
EXISTING = ("refuse", "overwrite", "new")  # an existing file: InputError, replaced, or a new timestamped name


# ---------------------------------------------------------------- points, exactly
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
    points = np.concatenate([s.points_mm for s in structures]) if structures else np.zeros((0, 3))
    ids = np.concatenate([np.full(len(s.points_mm), s.label_id) for s in structures]) if structures else []
    return points_message(points, "ct", stamp_ns, {"label_id": np.asarray(ids, dtype=np.uint32)})


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
    from liver_p2p_reg.ros.messages import parse_structure_labels
    from liver_p2p_reg.ros.pointcloud2 import cloud_fields
    from liver_p2p_reg.stream.structures import fallback_label
    from liver_p2p_reg.structures_io import Structure

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


def _structures_key(structures: Sequence[Structure]) -> bytes:
    """What tells one set of structures from another: labels, ids and points' bits."""
    digest = hashlib.sha256()
    for s in structures:
        points = np.ascontiguousarray(s.points_mm, dtype="<f8")
        digest.update(f"{s.label}\0{s.label_id}\0{points.shape}\0".encode() + points.tobytes())
    return digest.digest()


def _exact(array: np.ndarray | None) -> list | None:
    """A small float array as JSON lists (Python floats round-trip through JSON bit for bit)."""
    return None if array is None else np.asarray(array, dtype=np.float64).tolist()


# ---------------------------------------------------------------- metadata
def run_environment() -> dict[str, Any]:
    """What makes a pose reproducible besides its inputs: versions, weights, threads."""
    from importlib import metadata

    from liver_p2p_reg import __version__
    from liver_p2p_reg.bench.sysinfo import code_version

    def _version(dist: str) -> str:
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return "not installed"

    return {
        "package_version": __version__,
        "code_version": code_version(),
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "torch": _version("torch"),
        "open3d": _version("open3d-cpu") if _version("open3d") == "not installed" else _version("open3d"),
        "usable_cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS", ""),
    }


# ---------------------------------------------------------------- file names
def continuation(path: Path, index: int) -> Path:
    """The file `index` of a rotated recording: PATH itself, then PATH_001.mcap, PATH_002.mcap, ..."""
    return path if index == 0 else path.with_name(f"{path.stem}_{index:03d}{path.suffix}")


def recording_series(path: Path) -> list[Path]:
    """PATH and the continuations of its rotated recording that exist (PATH_001.mcap, ...): one recording's files."""
    return [path, *sorted(path.parent.glob(f"{path.stem}_[0-9][0-9][0-9]{path.suffix}"))]


def recording_path(record_path: str, existing: str) -> Path:
    """Where a recording asked for as `record_path` goes (a folder: flight_<time>.mcap in it)."""
    try:  # ~nosuchuser (RuntimeError) and a name over 255 bytes (OSError) crashed the node from a parameter
        path = Path(record_path).expanduser()
        stamp = time.strftime("%Y%m%d-%H%M%S")
        if record_path.endswith(os.sep) or path.is_dir():
            path = path / f"flight_{stamp}.mcap"
        if path.suffix != ".mcap":
            raise InputError(f"record_path {record_path}: a flight recording is an .mcap file (or a folder for one)")
        if not path.parent.is_dir():
            raise InputError(f"record_path {record_path}: folder {path.parent} does not exist")
        taken = [p for p in recording_series(path) if p.exists() or p.is_symlink()]  # a dangling link is taken too
    except (RuntimeError, OSError) as exc:
        raise InputError(f"record_path {record_path[:200]}: not usable ({exc})") from None
    if taken and existing == "refuse":
        raise InputError(f"{taken[0]} exists; pass --force to overwrite it")
    if taken and existing == "overwrite":
        # PATH's old continuations go with it (left behind, they would be read as the new recording's), but only
        # what is one: an MCAP file; a folder or another file under such a name is the user's and stops the run
        for old in taken[1:] if taken[0] == path else taken:
            if old.is_symlink() or not old.is_file() or not starts_as_mcap(old):
                raise InputError(f"{old} stands where {path}'s continuation would be, and is no recording; move it")
        for old in taken:
            old.unlink() if old.is_file() or old.is_symlink() else shutil.rmtree(old)  # a link, never its target
    elif taken:  # "new": a recording is evidence, never overwritten
        base, n = path.with_name(f"{path.stem}-{stamp}{path.suffix}"), 1
        path = base
        while any(p.exists() for p in recording_series(path)):
            n += 1
            path = base.with_name(f"{base.stem}-{n}{base.suffix}")
    return path


# ---------------------------------------------------------------- the writer
class McapRecorder(Recorder):
    """Writes one recording (the Recorder protocol of stream/record_hooks.py); rotates beyond record_max_mb."""

    def __init__(self, record_path: str, config: Config, *, existing: str = "new") -> None:
        self.base = recording_path(record_path, existing)
        self.command_mesh: PreopMesh | None = None  # `liver-p2p register --deform`'s SOURCE mesh, as read back
        self.session = uuid.uuid4().hex
        self.max_bytes = int(config.record_max_mb * 1e6)
        self.index, self.registrations, self._last_ns = -1, 0, 0
        self._config = config
        self._environment = run_environment()
        self._open(0)

    def _open(self, index: int) -> None:
        from mcap.writer import CompressionType, Writer

        self.index, self.path = index, str(continuation(self.base, index))
        self._file = open(self.path, "xb")  # noqa: SIM115 (closed in close / rotate)
        self._writer = Writer(self._file, use_chunking=False, compression=CompressionType.NONE)
        self._writer.start(profile="ros2", library=LIBRARY)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._model_stamp_ns, self._fiducials_key = 0, b""  # the last model and preop fiducials in this file
        self._structures_key: bytes | None = None  # the last structures written in this file (None: none yet)
        previous = continuation(self.base, index - 1).name if index else ""
        meta = {"format": FORMAT, "session": self.session, "file_index": index, "previous_file": previous}
        meta.update(started_unix_ns=time.time_ns(), **self._environment, weights_sha256=weights_sha256(self._config))
        self._json(TOPIC_META, meta)
        self._writer.flush()

    def _channel(self, topic: str, msgtype: str) -> int:
        if topic not in self._channels:
            import yaml
            from rosbags.rosbag2.metadata import dump_qos_v9

            store = typestore()
            if msgtype not in self._schemas:
                msgdef, _ = store.generate_msgdef(msgtype, ros_version=2)
                self._schemas[msgtype] = self._writer.register_schema(msgtype, "ros2msg", msgdef.encode())
            qos = yaml.safe_dump(dump_qos_v9([_qos(latched=qos_of(topic).latched)]), sort_keys=False).strip()
            metadata = {"offered_qos_profiles": qos, "topic_type_hash": store.hash_rihs01(msgtype)}
            self._channels[topic] = self._writer.register_channel(topic, "cdr", self._schemas[msgtype], metadata)
        return self._channels[topic]

    def _write(self, topic: str, msgtype: str, msg: Any) -> None:
        self._last_ns = max(time.time_ns(), self._last_ns)  # log times never go back (unindexed files)
        raw = typestore().serialize_cdr(msg, msgtype)
        self._writer.add_message(self._channel(topic, msgtype), self._last_ns, bytes(raw), self._last_ns)

    def _json(self, topic: str, values: dict[str, Any]) -> None:
        self._write(topic, STRING, typestore().types[STRING](data=json.dumps(values)))

    # ---------------------------------------------------------------- the Recorder protocol
    def config(self, config: Config, snapshot: bool = False) -> None:
        self._config = config
        self._json(TOPIC_CONFIG, {"config": config.to_dict(), "snapshot": snapshot, "weights_sha256": weights_sha256(config)})  # fmt: skip
        self._writer.flush()

    def preop(self, points_mm: np.ndarray, frame_id: str, stamp_ns: int, snapshot: bool = False) -> None:
        self._model_stamp_ns = int(stamp_ns)
        self._write(TOPIC_PREOP, POINTCLOUD2, points_message(points_mm, frame_id, stamp_ns))
        self._writer.flush()

    def preop_fiducials(self, points_mm: np.ndarray | None, stamp_ns: int, snapshot: bool = False) -> None:
        points = np.zeros((0, 3)) if points_mm is None else np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        self._fiducials_key = points.tobytes()  # none (0 points): the model's markers removed
        self._write(TOPIC_PREOP_FIDUCIALS, POINTCLOUD2, points_message(points, "ct", stamp_ns))

    def preop_mesh(self, mesh: PreopMesh, snapshot: bool = False) -> None:
        """The non-rigid stage's surface as the node got it (/preop/mesh), in metres that decode to its exact mm."""
        metres = exact_metres(mesh.vertices_mm)
        marker = triangle_list_marker(metres, mesh.triangles, rosbags_marker_types(), mesh.frame_id, mesh.stamp_ns)
        self._write(TOPIC_PREOP_MESH, MARKER, marker)
        self._writer.flush()

    def preop_structures(self, structures: Sequence[Structure], stamp_ns: int) -> None:
        """The structures a registration moved (/preop/structures exactly, /preop/structure_labels their names)."""
        self._write(TOPIC_PREOP_STRUCTURES, POINTCLOUD2, structures_message(structures, stamp_ns))
        labels = typestore().types[STRING](data=structure_labels(structures, stamp_ns))
        self._write(TOPIC_STRUCTURE_LABELS, STRING, labels)
        self._structures_key = _structures_key(structures)

    def event(self, name: str, values: dict[str, Any] | None = None) -> None:
        self._json(TOPIC_EVENT, {"event": name, **(values or {})})
        self._writer.flush()

    def registration(self, record: RegistrationRecord) -> None:
        """The input cloud, the pose and the diagnostics on the node's topics, then the JSON record; flushed."""
        out, types = record.output, rosbags_output_types()
        if record.points_mm is not None:
            self._write(TOPIC_INTRAOP, POINTCLOUD2, points_message(record.points_mm, record.frame_id, record.stamp_ns))
        if record.fiducials_mm is not None:  # the pair it used: the model's markers (when not the last written)
            fid_s, fid_t = (np.asarray(f, dtype=np.float64).reshape(-1, 3) for f in record.fiducials_mm)
            if fid_s.tobytes() != self._fiducials_key or not len(fid_s):
                self.preop_fiducials(fid_s, self._model_stamp_ns)
            self._write(TOPIC_INTRAOP_FIDUCIALS, POINTCLOUD2, points_message(fid_t, record.frame_id, record.stamp_ns))
        if record.structures is not None and _structures_key(record.structures) != self._structures_key:
            self.preop_structures(record.structures, self._model_stamp_ns)  # the set it moved, when not the last
        if out.pose is not None:
            self._write(TOPIC_POSE, POSE_STAMPED, pose_stamped(out.pose, types))
        placed = out.structures if out.pose is not None else []
        if placed:  # as published: sensor frame, float32 metres, with their bounds; the exact digest in the record
            cloud = registered_structures_cloud(placed, types.cloud, out.pose.frame_id, out.pose.stamp_ns)
            self._write(TOPIC_STRUCTURES, POINTCLOUD2, cloud)
        deformed = out.deformed_preop_mm if out.pose is not None else None
        if deformed is not None:  # as published (float32 metres); its exact digest goes in the record
            metres = np.asarray(deformed, dtype=np.float64) * M_PER_MM
            cloud = points_to_cloud(metres, types.cloud, frame_id=out.pose.frame_id, stamp_ns=out.pose.stamp_ns)
            self._write(TOPIC_DEFORMED_PREOP, POINTCLOUD2, cloud)
        self._write(TOPIC_DIAGNOSTICS, DIAGNOSTIC_ARRAY, diagnostic_array(out.diagnostics, record.stamp_ns, types))
        pose = out.pose
        values = {
            "seq": self.registrations,
            "reason": record.reason,
            "frame_id": record.frame_id,
            "stamp_ns": record.stamp_ns,
            "decoded": record.points_mm is not None,
            "n_raw": record.n_raw,
            "decode_error": record.decode_error,
            "fiducials": record.fiducials_mm is not None,
            "pose": None
            if pose is None
            else {
                "T_sensor_ct_mm": _exact(pose.T_sensor_ct_mm),
                "frame_id": pose.frame_id,
                "child_frame_id": pose.child_frame_id,
                "stamp_ns": pose.stamp_ns,
            },  # fmt: skip
            "level": out.level,
            "message": out.summary,
            "method": None if out.result is None else out.result.method,
            "extras": record.extras,
            # the non-rigid stage (deform on): its diagnostic values and the digest of the deformed surface
            "deformation": {k: v for k, v in out.diagnostics[0].values.items() if k.startswith("deform")}
            if out.diagnostics
            else {},
            "deformed_preop_sha256": points_sha256(deformed),
            "structures_sha256": placed_sha256(placed),
        }
        self._json(TOPIC_REGISTRATION, values)
        self.registrations += 1
        self._writer.flush()  # the commit: everything up to here survives a killed writer

    def rotate_due(self) -> bool:
        return self.max_bytes > 0 and self._file.tell() >= self.max_bytes

    def rotate(self) -> None:
        self._finish()
        self._open(self.index + 1)

    def _finish(self) -> None:
        self._writer.finish()
        self._file.close()

    def close(self) -> None:
        if not self._file.closed:
            self._finish()


def recorder_factory(existing: str = "new") -> Callable[[str, Config], Recorder]:
    """NodeCore's recorder_factory: (record_path, config) -> an open McapRecorder (see EXISTING)."""
    if existing not in EXISTING:
        raise ValueError(f"existing must be one of {EXISTING}")
    return lambda record_path, config: McapRecorder(record_path, config, existing=existing)
