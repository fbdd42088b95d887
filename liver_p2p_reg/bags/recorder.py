"""The flight recorder: NodeCore's hook (stream/record_hooks.py) written to rosbag2-compatible MCAP, and read back.

One bare MCAP file per recording (profile `ros2`, CDR messages with their `ros2msg` schemas, as
rosbag2 writes them), unchunked and flushed after every registration: a writer killed at any
moment leaves every completed registration readable; `bags/flight_replay.py` reads the records one
by one, stops cleanly at a truncated tail (no footer, summary or index needed) and re-runs them.
Topics and the exactness of what they carry: msg_docs/flight_recorder.md.
"""

from __future__ import annotations

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
from liver_p2p_reg.bags.recorded_points import (
    exact_metres,
    placed_sha256,
    points_message,
    points_sha256,
    structure_labels,
    structures_key,
    structures_message,
)
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.weights_id import weights_sha256
from liver_p2p_reg.ros.messages import (
    diagnostic_array,
    pose_stamped,
    registered_structures_cloud,
    triangle_list_marker,
)
from liver_p2p_reg.ros.pointcloud2 import M_PER_MM, points_to_cloud
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
    from liver_p2p_reg.structures_io import Structure

FORMAT = "liver_p2p_reg.flight_recorder/1"
STRING = "std_msgs/msg/String"
LIBRARY = "liver_p2p_reg flight recorder"  # the MCAP Header's `library` of every recording (how one is told)
TOPIC_PREFIX = "/flight_recorder/"
TOPIC_META = "/flight_recorder/meta"  # first message of every file: versions, weights, session, file index
TOPIC_CONFIG = "/flight_recorder/config"  # the full parameter set, at the head of a file and after every change
TOPIC_EVENT = "/flight_recorder/event"  # reset_survey; in a file's head: tracker (the prior), snapshot_end
TOPIC_REGISTRATION = "/flight_recorder/registration"  # one per registration, its last record (the commit)
EXISTING = ("refuse", "overwrite", "new")  # an existing file: InputError, replaced, or a new timestamped name


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
        self._structures_key = structures_key(structures)

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
        if record.structures is not None and structures_key(record.structures) != self._structures_key:
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
