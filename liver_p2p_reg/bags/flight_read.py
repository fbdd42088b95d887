"""Read a flight recording record by record (no footer needed); tell it from a damaged recording or another file."""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any

from liver_p2p_reg.bags.flight_records import Damaged, RecordedMessage, checked_values
from liver_p2p_reg.bags.io import bag_error_reason, is_bag_error, typestore
from liver_p2p_reg.bags.mcap_check import MCAP_MAGIC, mcap_closed, mcap_record_heads, summary_start
from liver_p2p_reg.bags.recorder import FORMAT, LIBRARY, TOPIC_META, TOPIC_PREFIX, continuation, recording_series
from liver_p2p_reg.errors import InputError

# far above any record the recorder writes (a 640 x 480 cloud is 11 MB): a longer one is a damaged length, not a cut
MAX_RECORD_BYTES = 1 << 32


@dataclass
class ReadState:
    """What reading found besides the messages: the files read, whether the last one was cut short, and (of the
    last file) its writer's name and the topics its channels define."""

    files: list[Path]
    truncated: bool = False  # the last file ends without its footer, maybe inside a record (writer killed)
    library: str | None = None
    topics: set[str] = field(default_factory=set)


def read_file(path: Path, state: ReadState) -> Iterator[RecordedMessage]:
    """The messages of one MCAP file, record by record; a truncated tail ends it (state.truncated).

    Damaged bytes raise Damaged: one line naming the file and the record's byte offset.
    """
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Header, Message, Schema

    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}
    store = typestore()
    state.library, state.topics = None, set()
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        closed = mcap_closed(fh, size)  # every record of a closed file ends inside it: one running past is damaged
        fh.seek(0)
        if fh.read(8) != MCAP_MAGIC:
            raise Damaged(path, "it does not start with the MCAP magic")
        while True:
            offset = fh.tell()
            head = fh.read(9)
            if len(head) < 9:  # the end, without the footer a closed file has
                state.truncated = True
                return
            opcode, length = struct.unpack("<BQ", head)
            if length > size - offset - 9:
                if closed or length > MAX_RECORD_BYTES:
                    raise Damaged(
                        path, f"the record at byte {offset} claims {length} bytes, past the file's end ({size} bytes)"
                    )
                state.truncated = True  # the writer was killed inside this record
                return
            if opcode in (Opcode.DATA_END, Opcode.FOOTER):  # the summary follows: nothing to replay
                return
            if opcode not in (Opcode.HEADER, Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
                fh.seek(length, 1)  # chunks and indexes: a recording has none in its data, a bag's are not read here
                continue
            stream = ReadDataStream(BytesIO(fh.read(length)))
            try:
                if opcode == Opcode.HEADER:
                    state.library = Header.read(stream).library
                elif opcode == Opcode.SCHEMA:
                    schema = Schema.read(stream)
                    schemas[schema.id] = schema.name
                elif opcode == Opcode.CHANNEL:
                    channel = Channel.read(stream)
                    state.topics.add(channel.topic)
                    if channel.schema_id not in schemas:
                        raise Damaged(
                            path,
                            f"the channel at byte {offset} ({channel.topic}) refers to schema "
                            f"{channel.schema_id}, which the file never defines",
                        )
                    channels[channel.id] = (channel.topic, schemas[channel.schema_id])
                else:
                    message = Message.read(stream, length)
                    if message.channel_id not in channels:
                        raise Damaged(
                            path,
                            f"the message at byte {offset} refers to channel {message.channel_id}, "
                            "which the file never defines",
                        )
                    topic, msgtype = channels[message.channel_id]
                    if msgtype not in store.types:
                        raise Damaged(
                            path,
                            f"the message at byte {offset} ({topic}) has the type {msgtype!r}, "
                            "which this version does not know",
                        )
                    msg = store.deserialize_cdr(message.data, msgtype)
                    item = RecordedMessage(topic, msgtype, message.log_time, msg, path, offset)
            except Damaged:
                raise
            except Exception as exc:  # damaged bytes inside a record: one line naming the file, not a traceback
                if not is_bag_error(exc):
                    raise
                raise Damaged(path, f"the record at byte {offset}: {bag_error_reason(exc)}") from None
            if opcode == Opcode.MESSAGE:
                yield item


def first_meta(path: Path) -> dict[str, Any] | None:
    """The meta record of a flight recording's file ({} for one that ends before it: its writer killed as it opened
    the file), None for any other file.

    InputError (one line) for a file that bears a recording's marks (its writer's name, /flight_recorder/* topics
    in its channels or summary) but whose head cannot be read, and for a recording of another format.
    """
    path = Path(path)
    state = ReadState([])
    try:
        first = next(read_file(path, state), None)
        if first is None:
            ours = state.library in (None, LIBRARY) and all(t.startswith(TOPIC_PREFIX) for t in state.topics)
            if state.truncated and ours:  # cut before its first message: a recording, of no registration
                return {}
            problem = "it holds no message"
        elif first.topic != TOPIC_META:
            problem = f"its first message is on {first.topic}, not {TOPIC_META}"
        else:
            meta = checked_values(first)
            if meta["format"] != FORMAT:
                raise InputError(
                    f"{path} is a flight recording of format {meta['format']!r}; this version reads {FORMAT!r} only"
                )
            return meta
    except OSError:
        return None  # unreadable: what opens it next says why
    except Damaged as exc:
        problem = exc.detail
    if _flight_marks(path, state):
        raise InputError(f"{path} looks like a flight recording but its head cannot be read: {problem}")
    return None


def _flight_marks(path: Path, state: ReadState) -> bool:
    """Whether a file bears a flight recording's marks: its writer's name in its Header, or a /flight_recorder/*
    channel in its data or its summary, looked for past whatever damage stopped the reader."""
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Header

    if state.library == LIBRARY or any(t.startswith(TOPIC_PREFIX) for t in state.topics):
        return True
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        starts = [8]
        if mcap_closed(fh, size):  # the summary repeats every channel: found even where the data's are damaged
            starts.append(summary_start(fh, size))
        for start in filter(None, starts):
            for offset, opcode, length in mcap_record_heads(fh, start, size):
                if offset + 9 + length > size:
                    break  # a damaged length: what follows cannot be found from here
                if opcode not in (Opcode.HEADER, Opcode.CHANNEL):
                    continue
                fh.seek(offset + 9)
                stream = ReadDataStream(BytesIO(fh.read(length)))
                try:
                    mark = Header.read(stream).library if opcode == Opcode.HEADER else Channel.read(stream).topic
                except Exception as exc:  # a damaged record among others: look on
                    if not is_bag_error(exc):
                        raise
                    continue
                if mark == LIBRARY or mark.startswith(TOPIC_PREFIX):
                    return True
    return False


def is_recording(path: str | Path) -> bool:
    """Whether `path` is a flight recording: a bare .mcap whose first message is /flight_recorder/meta, or that its
    writer left before it. InputError (one line) for a damaged one or one of another format (first_meta)."""
    path = Path(path)
    return path.is_file() and path.suffix == ".mcap" and first_meta(path) is not None


def read_recording(path: str | Path, state: ReadState | None = None) -> Iterator[RecordedMessage]:
    """Every message of a recording from `path` on, through its rotated files (same session, next index).

    InputError (one line) where the series is not whole: a file missing before later ones, a file cut short with
    later ones after it, or a later file of another session; a re-run would then check part of it only.
    """
    path = Path(path)
    meta = first_meta(path)
    if meta is None:
        raise InputError(f"{path} is not a flight recording (no {TOPIC_META})")
    state = state if state is not None else ReadState([])
    if not meta:  # its writer was killed before its first message: nothing to read
        state.files.append(path)
        state.truncated = True
        return
    index = meta["file_index"]
    base = path
    if index:  # a later file of a series: its base name is the first file's
        base = path.with_name(path.stem.rsplit("_", 1)[0] + path.suffix)
    _check_series(path, base, index)
    while True:
        state.files.append(path)
        state.truncated = False
        yield from read_file(path, state)
        index += 1
        following = continuation(base, index)
        if not following.is_file():
            return
        if state.truncated:
            raise InputError(
                f"{path} ends without its footer, yet {following.name} follows it: the recording is "
                f"damaged; replay {following.name} on its own to check what follows"
            )
        nxt = first_meta(following)
        if nxt and (nxt["session"] != meta["session"] or nxt["file_index"] != index):
            raise InputError(
                f"{following}, named as the next file of {path.name}, is of another recording "
                f"(session or file index): move it away to check {path.name} alone"
            )
        if nxt is None:
            raise InputError(
                f"{following}, named as the next file of {path.name}, is no flight recording: move it "
                f"away to check {path.name} alone"
            )
        path = following


def _check_series(path: Path, base: Path, index: int) -> None:
    """InputError when a file of the series after `path` is missing while later ones exist (they would go unchecked)."""
    later = sorted(n for n in (int(p.stem.rsplit("_", 1)[1]) for p in recording_series(base)[1:]) if n > index)
    for expected, found in enumerate(later, start=index + 1):
        if found != expected:
            missing, unchecked = continuation(base, expected).name, continuation(base, found).name
            raise InputError(
                f"{missing} of the recording {path.name} is missing; {unchecked} and after would go "
                f"unchecked: put it back, or replay {unchecked} on its own"
            )
