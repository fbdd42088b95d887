"""A flight recording's JSON records as this version writes them: their keys and types, one line for another shape."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from liver_p2p_reg.bags.io import MARKER, POINTCLOUD2
from liver_p2p_reg.bags.recorder import STRING, TOPIC_CONFIG, TOPIC_EVENT, TOPIC_META, TOPIC_REGISTRATION
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.ros.topics import (
    INPUT_TOPICS,
    TOPIC_DEFORMED_PREOP,
    TOPIC_PREOP_MESH,
    TOPIC_PREOP_STRUCTURES,
    TOPIC_STRUCTURE_LABELS,
    TOPIC_STRUCTURES,
)

# the JSON records' keys this version reads, and their JSON types (bool is refused where an int is wanted)
_NONE = type(None)
_RECORD_KEYS: dict[str, dict[str, tuple[type, ...]]] = {
    TOPIC_META: {"format": (str,), "session": (str,), "file_index": (int,)},
    TOPIC_CONFIG: {"config": (dict,)},
    TOPIC_EVENT: {"event": (str,)},
    TOPIC_REGISTRATION: {
        "seq": (int,),
        "reason": (str,),
        "frame_id": (str,),
        "stamp_ns": (int,),
        "decoded": (bool,),
        "n_raw": (int,),
        "decode_error": (str, _NONE),
        "fiducials": (bool,),
        "pose": (dict, _NONE),
        "extras": (dict,),
    },
}
_TRACKER_KEYS = {"reference_residual_mm": (int, float), "frame_id": (str,), "frames": (int,)}
# the message type each topic the re-run decodes must have
_MESSAGE_TYPES = {
    **dict.fromkeys(INPUT_TOPICS, POINTCLOUD2),
    TOPIC_DEFORMED_PREOP: POINTCLOUD2,
    TOPIC_PREOP_MESH: MARKER,
    TOPIC_PREOP_STRUCTURES: POINTCLOUD2,
    TOPIC_STRUCTURE_LABELS: STRING,
    TOPIC_STRUCTURES: POINTCLOUD2,
    **dict.fromkeys(_RECORD_KEYS, STRING),
}


class Damaged(InputError):
    """A record of a recording that cannot be read: the file, and where and why (`detail`)."""

    def __init__(self, path: Path, detail: str) -> None:
        super().__init__(f"cannot read flight recording {path}: {detail}")
        self.detail = detail


def other_version(path: Path, detail: str) -> InputError:
    """The one line for JSON records of another shape than this version writes (another format version)."""
    return InputError(f"{path}: not a flight recording this version reads ({detail})")


@dataclass
class RecordedMessage:
    """One message of a recording, deserialized, with the file it came from and its record's byte offset there."""

    topic: str
    msgtype: str
    log_ns: int
    msg: Any
    file: Path
    offset: int = 0

    @property
    def where(self) -> str:
        return f"the {self.topic} record at byte {self.offset}"

    @property
    def values(self) -> dict[str, Any]:
        """The JSON object of a std_msgs/String record; InputError (one line) for damaged JSON or another shape."""
        try:
            values = json.loads(self.msg.data)
        except (ValueError, RecursionError) as exc:
            raise Damaged(self.file, f"{self.where} is not valid JSON ({exc})") from None
        if not isinstance(values, dict):
            raise other_version(self.file, f"{self.where} is a JSON {type(values).__name__}, not an object")
        return values


def checked_values(item: RecordedMessage) -> dict[str, Any] | None:
    """The JSON of a /flight_recorder/* record with every key this version reads, of its type (None for other
    topics); InputError (one line) for another message type, a key missing or of another type."""
    if item.topic in _MESSAGE_TYPES and item.msgtype != _MESSAGE_TYPES[item.topic]:
        raise other_version(item.file, f"{item.where} is a {item.msgtype}, not a {_MESSAGE_TYPES[item.topic]}")
    if item.topic not in _RECORD_KEYS:
        return None
    values = item.values
    what = {
        TOPIC_META: "its meta record",
        TOPIC_CONFIG: f"the config record at byte {item.offset}",
        TOPIC_EVENT: f"the event record at byte {item.offset}",
    }.get(item.topic)
    if what is None:  # a registration: by its seq, as the re-run's report names it
        seq = values.get("seq")
        what = f"registration {seq}" if _of_type(seq, (int,)) else f"the registration record at byte {item.offset}"
    _check_keys(item.file, values, _RECORD_KEYS[item.topic], what)
    if item.topic == TOPIC_REGISTRATION:
        if values["pose"] is not None and not _matrix(values["pose"].get("T_sensor_ct_mm")):
            raise other_version(item.file, f"{what}'s pose lacks a 4x4 'T_sensor_ct_mm' of numbers")
        extras = values["extras"]
        initial, origin = extras.get("initial_T_mm"), extras.get("sensor_origin_mm")
        if values["reason"] == "register" and not (
            (initial is None or _matrix(initial)) and (origin is None or _vector(origin))
        ):
            raise other_version(item.file, f"{what}'s extras are not a 4x4 initial_T_mm and a 3-vector origin")
    if item.topic == TOPIC_EVENT and values["event"] == "tracker":
        _check_keys(item.file, values, _TRACKER_KEYS, f"the tracker event at byte {item.offset}")
        if not _matrix(values.get("T_mm")):
            raise other_version(item.file, f"the tracker event at byte {item.offset} lacks a 4x4 'T_mm' of numbers")
    return values


def _of_type(value: Any, kinds: tuple[type, ...]) -> bool:
    return isinstance(value, kinds) and (bool in kinds or not isinstance(value, bool))


def _check_keys(path: Path, values: dict[str, Any], keys: dict[str, tuple[type, ...]], what: str) -> None:
    for key, kinds in keys.items():
        if key not in values:
            raise other_version(path, f"{what} lacks {key!r}")
        if not _of_type(values[key], kinds):
            wanted = " or ".join("null" if k is _NONE else k.__name__ for k in kinds)
            raise other_version(path, f"{what} has {key!r} as {type(values[key]).__name__}, not {wanted}")


def _vector(value: Any, n: int = 3) -> bool:
    return isinstance(value, list) and len(value) == n and all(_of_type(v, (int, float)) for v in value)


def _matrix(value: Any) -> bool:
    return isinstance(value, list) and len(value) == 4 and all(_vector(row, 4) for row in value)
