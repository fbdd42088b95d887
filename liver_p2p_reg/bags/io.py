"""Read rosbag2 directories / bare MCAP files and write MCAP rosbag2 directories with `rosbags` (no ROS needed)."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from liver_p2p_reg.bags.mcap_check import check_bare_mcap, looks_like_recording
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.ros.pointcloud2 import MessageTypes
from liver_p2p_reg.ros.topics import INPUT_TOPICS, LOADER_INPUT_TOPICS, qos_of

if TYPE_CHECKING:
    from liver_p2p_reg.ros.messages import MarkerTypes, OutputTypes

# rosbag2 metadata version 9 is what Jazzy's rosbag2 (0.26) writes: QoS profiles as a YAML list.
BAG_VERSION = 9
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
MARKER = "visualization_msgs/msg/Marker"


@lru_cache(maxsize=1)
def typestore() -> Any:
    """The Jazzy message typestore of rosbags (message classes for reading and writing)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def rosbags_types() -> MessageTypes:
    """PointCloud2 building blocks as rosbags message classes."""
    types = typestore().types
    return MessageTypes(
        PointCloud2=types[POINTCLOUD2],
        PointField=types["sensor_msgs/msg/PointField"],
        Header=types["std_msgs/msg/Header"],
        Time=types["builtin_interfaces/msg/Time"],
        wrap_bytes=lambda raw: np.frombuffer(raw, dtype=np.uint8).copy(),
    )


def rosbags_output_types() -> OutputTypes:
    """Output message classes (pose, transform, diagnostics) from the rosbags Jazzy typestore."""
    # imported here: ros.messages brings the stream core (scipy), which reading a bag does not need
    from liver_p2p_reg.ros.messages import OutputTypes

    t = typestore().types
    return OutputTypes(
        cloud=rosbags_types(),
        PoseStamped=t[POSE_STAMPED],
        Pose=t["geometry_msgs/msg/Pose"],
        Point=t["geometry_msgs/msg/Point"],
        Quaternion=t["geometry_msgs/msg/Quaternion"],
        TransformStamped=t[TRANSFORM_STAMPED],
        Transform=t["geometry_msgs/msg/Transform"],
        Vector3=t["geometry_msgs/msg/Vector3"],
        DiagnosticArray=t[DIAGNOSTIC_ARRAY],
        DiagnosticStatus=t["diagnostic_msgs/msg/DiagnosticStatus"],
        KeyValue=t["diagnostic_msgs/msg/KeyValue"],
        level=int,
    )


def rosbags_marker_types() -> MarkerTypes:
    """visualization_msgs/Marker and its parts from the rosbags Jazzy typestore (/preop/mesh)."""
    from liver_p2p_reg.ros.messages import MarkerTypes

    t = typestore().types
    return MarkerTypes(
        cloud=rosbags_types(),
        Marker=t[MARKER],
        Point=t["geometry_msgs/msg/Point"],
        Pose=t["geometry_msgs/msg/Pose"],
        Quaternion=t["geometry_msgs/msg/Quaternion"],
        Vector3=t["geometry_msgs/msg/Vector3"],
        ColorRGBA=t["std_msgs/msg/ColorRGBA"],
        Duration=t["builtin_interfaces/msg/Duration"],
        CompressedImage=t["sensor_msgs/msg/CompressedImage"],
        MeshFile=t["visualization_msgs/msg/MeshFile"],
    )


def msg_class(msgtype: str) -> type:
    """A rosbags message class by ROS type name (e.g. 'geometry_msgs/msg/PoseStamped')."""
    return typestore().types[msgtype]


def is_bag_path(path: Path) -> bool:
    """True for a rosbag2 directory (with metadata.yaml or .mcap files) or a bare .mcap file."""
    path = Path(path)
    if path.is_file():
        return path.suffix == ".mcap"
    return path.is_dir() and ((path / "metadata.yaml").is_file() or any(path.glob("*.mcap")))


def check_replaceable_bag(path: Path) -> None:
    """InputError unless `path` is a bag --force may replace: a .mcap file that is no flight recording, an empty
    folder, or a rosbag2 folder (metadata.yaml and its .mcap files, nothing else).

    Anything else (a folder of other files or of several bare .mcap files, the current folder, a pipe, another
    file) is refused with one line: --force replaces a bag, it never deletes what merely stands at the bag's path.
    """
    path = Path(path)
    refuse = f"{path} exists and is not a bag this command wrote; not replacing it: choose another path"
    if path.is_symlink() or path.is_file():
        if path.suffix != ".mcap":
            raise InputError(refuse)
        if looks_like_recording(path):  # evidence of a session: never replaced by a bag
            raise InputError(f"{path} is a flight recording; not replacing it with a bag: choose another path")
        return
    if not path.is_dir():
        raise InputError(refuse)
    if Path.cwd().resolve().is_relative_to(path.resolve()):
        raise InputError(f"{path} holds the current folder; not replacing it: choose another path")
    entries = sorted(path.iterdir())
    foreign = [e.name for e in entries if not (e.is_file() and (e.name == "metadata.yaml" or e.suffix == ".mcap"))]
    if foreign:
        raise InputError(
            f"{path} holds {foreign[0]!r}, which is not a bag's file; not replacing it: choose another path"
        )
    if entries and not (path / "metadata.yaml").is_file():
        raise InputError(
            f"{path} holds .mcap files but no metadata.yaml (recordings or bare bags, not one bag); "
            "not replacing it: choose another path"
        )


def remove_bag(path: Path) -> None:
    """Delete an existing bag that is to be overwritten (check_replaceable_bag first)."""
    check_replaceable_bag(path)
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)  # an empty folder too: nothing in it is lost
    else:
        path.unlink()


@dataclass
class BagMessage:
    """One deserialized message in log-time order."""

    topic: str
    msgtype: str
    timestamp_ns: int
    msg: Any


# Packages whose exceptions, raised while a bag is opened or read, mean "this is no readable bag":
# rosbags (per storage backend), the MCAP and YAML parsers, the chunk decompressors, struct unpacking.
_BAG_ERROR_PACKAGES = ("rosbags", "mcap", "yaml", "zstandard", "backports", "lz4", "struct")


def read_messages(path: str | Path, topics: list[str] | None = None) -> Iterator[BagMessage]:
    """Yield the messages of a rosbag2 directory or bare .mcap file in timestamp order.

    Raises InputError (one line naming the bag) for a missing or unreadable bag.
    """
    from rosbags.highlevel import AnyReader

    source = bag_source(Path(path))
    try:
        with AnyReader([source], default_typestore=typestore()) as reader:
            conns = [c for c in reader.connections if topics is None or c.topic in topics]
            for conn, timestamp, raw in reader.messages(connections=conns):
                yield BagMessage(conn.topic, conn.msgtype, int(timestamp), reader.deserialize(raw, conn.msgtype))
    except Exception as exc:
        if not is_bag_error(exc):
            raise
        raise unreadable(path, exc) from None


def bag_source(path: Path) -> Path:
    """What rosbags opens for a bag: a rosbag2 folder, the one .mcap of a folder without metadata.yaml, a .mcap file.

    InputError for anything else, and for a folder whose metadata.yaml is malformed (rosbags would
    report PyYAML's multi-line excerpt).
    """
    if not path.exists():
        raise InputError(f"bag not found: {path}")
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            _bag_information(path)
            return path
        mcaps = sorted(path.glob("*.mcap"))
        if len(mcaps) != 1:  # a folder of one MCAP without metadata.yaml: read the file itself
            raise InputError(f"{path} is not a rosbag2 directory (no metadata.yaml)")
        return bag_source(mcaps[0])  # read as the bare file it is: the same framing checks
    if not path.is_file() or path.suffix != ".mcap":  # a pipe would block; another file is no bag
        raise InputError(f"not a rosbag2 directory or .mcap file: {path}")
    check_bare_mcap(path)
    return path


def is_bag_error(exc: BaseException) -> bool:
    """Whether an exception raised by the bag readers says the bag's bytes are unreadable (not a bug of ours)."""
    if isinstance(exc, (ValueError, KeyError, IndexError, OSError, EOFError)):
        return True
    if type(exc).__module__.split(".")[0] in _BAG_ERROR_PACKAGES:
        return True
    # a built-in error raised inside a reader over damaged bytes: ord(b"") on a file that holds only the magic
    # (TypeError), an absurd record length (MemoryError, OverflowError)
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return tb is not None and tb.tb_frame.f_globals.get("__name__", "").split(".")[0] in _BAG_ERROR_PACKAGES


def unreadable(path: str | Path, exc: BaseException) -> InputError:
    """The one-line InputError for a bag rosbags cannot read: its path and what is wrong, in words."""
    return InputError(f"cannot read bag {path}: {bag_error_reason(exc)}")


def bag_error_reason(exc: BaseException) -> str:
    """What a bag reader's exception (is_bag_error) says is wrong with the bytes, in one line of words."""
    if isinstance(exc, KeyError):  # its text alone would be the key ("4", "''")
        reason = f"a record refers to {exc.args[0]!r}, which the file does not define (damaged or incomplete)"
    elif isinstance(exc, (MemoryError, OverflowError)):
        reason = f"a record's length runs past the end of the file (damaged; {type(exc).__name__})"
    else:
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return reason


def model_and_clouds(path: str | Path, *, metres: bool = False) -> tuple[np.ndarray | None, list[np.ndarray]]:
    """A bag's (last) preop points and its intraop clouds, (N, 3) mm, or metres as the messages hold them."""
    from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_m, cloud_to_points_mm
    from liver_p2p_reg.ros.topics import TOPIC_INTRAOP, TOPIC_PREOP

    convert = cloud_to_points_m if metres else cloud_to_points_mm
    preop, clouds = None, []
    for item in read_messages(path, [TOPIC_PREOP, TOPIC_INTRAOP]):
        if item.topic == TOPIC_PREOP:
            preop = convert(item.msg)
        else:
            clouds.append(convert(item.msg))
    return preop, clouds


def bag_topics(path: str | Path) -> dict[str, tuple[str, int]]:
    """topic -> (msgtype, message count) of a bag; InputError (one line) for a missing or unreadable bag."""
    from rosbags.highlevel import AnyReader

    source = bag_source(Path(path))
    try:
        with AnyReader([source], default_typestore=typestore()) as reader:
            return {name: (info.msgtype, info.msgcount) for name, info in reader.topics.items()}
    except Exception as exc:
        if not is_bag_error(exc):
            raise
        raise unreadable(path, exc) from None


def _qos(*, latched: bool, best_effort: bool = False, depth: int = 1) -> Any:
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(0, 0)  # 0 = the RMW default (infinite) deadline/lifespan/lease
    return Qos(
        history=QosHistory.KEEP_LAST,
        depth=depth,
        reliability=QosReliability.BEST_EFFORT if best_effort else QosReliability.RELIABLE,
        durability=QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
        deadline=zero,
        lifespan=zero,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=zero,
        avoid_ros_namespace_conventions=False,
    )


# Offered QoS recorded per topic so `ros2 bag play` republishes latched topics as latched
# (the inputs' documented profiles, ros.topics; every other recorded QoS: reliable, volatile, depth 1).
LATCHED_TOPICS = tuple(topic for topic in INPUT_TOPICS + LOADER_INPUT_TOPICS if qos_of(topic).latched)


class BagWriter:
    """Write a rosbag2 directory (metadata.yaml + MCAP) that `ros2 bag play` on Jazzy accepts."""

    def __init__(self, path: str | Path, *, overwrite: bool = False, custom_data: dict[str, str] | None = None) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path = Path(path)
        if self.path.exists():
            if not overwrite:
                raise InputError(f"output bag {self.path} exists (use --force to overwrite)")
            remove_bag(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._writer = Writer(self.path, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
        for key, value in (custom_data or {}).items():  # shown by `ros2 bag info`, read back by replay
            self._writer.set_custom_data(key, value)
        self._writer.open()
        self._connections: dict[str, Any] = {}

    def write(self, topic: str, msgtype: str, timestamp_ns: int, msg: Any) -> None:
        """Serialize a rosbags message object and append it."""
        self.write_raw(topic, msgtype, timestamp_ns, typestore().serialize_cdr(msg, msgtype))

    def write_raw(self, topic: str, msgtype: str, timestamp_ns: int, raw: bytes) -> None:
        """Append an already serialized (CDR) message, e.g. one recorded from a live topic."""
        conn = self._connections.get(topic)
        if conn is None:
            qos = _qos(latched=topic in LATCHED_TOPICS)
            conn = self._writer.add_connection(topic, msgtype, typestore=typestore(), offered_qos_profiles=[qos])
            self._connections[topic] = conn
        self._writer.write(conn, int(timestamp_ns), raw)

    def close(self) -> None:
        self._writer.close()
        # rosbags records itself as the distro; say jazzy, the distribution these bags target
        meta = self.path / "metadata.yaml"
        meta.write_text(meta.read_text().replace("ros_distro: rosbags", "ros_distro: jazzy", 1))

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def bag_custom_data(path: str | Path) -> dict[str, str]:
    """The custom_data mapping of a rosbag2 directory's metadata.yaml ({} for bare MCAP files).

    Raises InputError (one line) for a malformed metadata.yaml.
    """
    custom = _bag_information(Path(path)).get("custom_data") or {}
    if not isinstance(custom, dict):
        raise InputError(f"bag metadata {Path(path) / 'metadata.yaml'}: custom_data is not a mapping")
    return {str(k): str(v) for k, v in custom.items()}


def _bag_information(path: Path) -> dict[str, Any]:
    """The rosbag2_bagfile_information mapping of a bag folder's metadata.yaml ({} without one)."""
    from liver_p2p_reg.config_io import load_yaml_text

    meta = path / "metadata.yaml"
    if not meta.is_file():
        return {}
    data = load_yaml_text(meta, "bag metadata")
    info = data.get("rosbag2_bagfile_information") if isinstance(data, dict) else None
    if not isinstance(info, dict):
        raise InputError(f"bag metadata {meta} holds no rosbag2_bagfile_information mapping")
    return info


def bag_size_bytes(path: str | Path) -> int:
    """Total size of a bag directory or file in bytes."""
    path = Path(path)
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
