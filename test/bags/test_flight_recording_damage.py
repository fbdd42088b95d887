"""Damaged flight recordings, recordings of another shape and broken series: one error line and exit 2, never a
traceback, the CLI's internal error, a partial pass or a plain bag's replay; `bag play` plays the inputs only."""

import json
import re
import struct
from pathlib import Path

import pytest
from bags.test_flight_recorder import CONFIG, mcap_records
from ros_support import BAG_A

from liver_p2p_reg.bags.flight_replay import is_recording, rerun_recording
from liver_p2p_reg.bags.io import bag_topics
from liver_p2p_reg.bags.recorder import (
    FORMAT,
    TOPIC_CONFIG,
    TOPIC_EVENT,
    TOPIC_META,
    TOPIC_REGISTRATION,
    continuation,
)
from liver_p2p_reg.bags.replay import replay_bag
from liver_p2p_reg.cli import main
from liver_p2p_reg.errors import InputError

DATA_END, SCHEMA, CHANNEL = 0x0F, 0x03, 0x04


@pytest.fixture(scope="module")
def bag_recording(tmp_path_factory):
    """A flight recording of two registrations (a replay of BAG_A), each test damaging a copy of it."""
    path = tmp_path_factory.mktemp("rec") / "replay.mcap"
    assert replay_bag(BAG_A, CONFIG, record_path=path, max_frames=2).registered == 2
    return path


def liver_p2p(capsys, *args):
    """`liver-p2p ARGS` in this process: (exit status, its one stderr line); internal errors would exit 1."""
    capsys.readouterr()
    code = main([str(a) for a in args])
    err = capsys.readouterr().err
    assert err.count("\n") <= 1 and "Traceback" not in err and "internal error" not in err, err
    return code, err.strip()


def damaged(source, into, edit):
    """A copy of `source` with `edit(bytearray)` applied to its bytes."""
    data = bytearray(Path(source).read_bytes())
    edit(data)
    into.write_bytes(bytes(data))
    return into


def json_record(path, topic, nth=0):
    """(record offset, start, end) of the nth JSON record on `topic`: its text lies in data[start:end]."""
    offset = [r for r in mcap_records(path) if r[3] == topic][nth][1]
    # a Message record: 9 bytes of head, 22 of channel id, sequence and times, then CDR: 4 bytes of encapsulation
    # and the string's length (its NUL included)
    cdr = offset + 9 + 22
    (length,) = struct.unpack_from("<I", Path(path).read_bytes(), cdr + 4)
    return offset, cdr + 8, cdr + 8 + length - 1


def rewritten(source, into, topic, change, nth=0):
    """`source` with one JSON record replaced by `change(values)`, padded with spaces to its length (JSON allows
    them), so every record and the footer keep their offsets."""
    _, start, end = json_record(source, topic, nth)

    def edit(data):
        text = json.dumps(change(json.loads(bytes(data[start:end]))), separators=(",", ":")).encode()
        assert len(text) <= end - start, "the edit must not lengthen the record"
        data[start:end] = text.ljust(end - start)

    return damaged(source, into, edit)


def test_damaged_bytes_and_lengths_are_one_line_naming_the_record(bag_recording, tmp_path, capsys):
    records = mcap_records(bag_recording)
    header, schema = records[0], records[1]
    config_at, start, _ = json_record(bag_recording, TOPIC_CONFIG)

    def length(record, value):
        return lambda data: struct.pack_into("<Q", data, record[1] + 1, value)

    cases = {  # the file -> the error line (exit 2)
        "huge.mcap": (length(header, (header[2] - header[1] - 9) | 1 << 40), r"record at byte 8 claims \d+ bytes"),
        "short.mcap": (length(schema, schema[2] - schema[1] - 9 - 7), r"claims \d+ bytes, past the file's end"),
        "json.mcap": (
            lambda data: data.__setitem__(data.index(b":", start), ord(";")),  # {"config"; ...
            rf"cannot read flight recording .*json.mcap: the {TOPIC_CONFIG} record at byte {config_at} is not valid "
            "JSON",
        ),
    }
    for name, (edit, message) in cases.items():
        path = damaged(bag_recording, tmp_path / name, edit)
        code, err = liver_p2p(capsys, "replay", path)
        assert code == 2 and re.search(message, err) and name in err, (name, err)
    for action in ("info", "play"):  # rosbags would try to allocate a terabyte (MemoryError)
        code, err = liver_p2p(capsys, "bag", action, tmp_path / "huge.mcap")
        assert code == 2 and "the record at byte 8 claims" in err and "past the end of the file" in err, err


def test_a_writer_killed_as_it_opened_the_file_left_no_registration(bag_recording, tmp_path, capsys):
    magic_only = damaged(bag_recording, tmp_path / "magic.mcap", lambda data: data.__delitem__(slice(8, None)))
    assert is_recording(magic_only)
    report = rerun_recording(magic_only)
    assert report.truncated and report.registrations == 0
    code, err = liver_p2p(capsys, "replay", magic_only)
    assert code == 2 and err.endswith("magic.mcap holds no complete registration to re-run"), err


def test_bag_info_and_play_say_a_killed_recording_ends_without_its_footer(bag_recording, tmp_path, capsys):
    data_end = next(start for op, start, _, _ in mcap_records(bag_recording) if op == DATA_END)
    killed = damaged(bag_recording, tmp_path / "killed.mcap", lambda data: data.__delitem__(slice(data_end, None)))
    assert rerun_recording(killed).registrations == 2  # replay reads it
    for action in ("info", "play"):
        code, err = liver_p2p(capsys, "bag", action, killed)
        assert code == 2 and "killed.mcap: it ends without its footer" in err and "liver-p2p replay" in err, err


def test_records_a_message_or_a_schema_never_defined_are_named(bag_recording, tmp_path, capsys):
    records = mcap_records(bag_recording)
    channel = [r for r in records if r[0] == CHANNEL][3]
    schema = [r for r in records if r[0] == SCHEMA][2]
    for name, (_, begin, end, _), message in (
        ("no_channel.mcap", channel, r"the message at byte \d+ refers to channel \d+, which the file never defines"),
        ("no_schema.mcap", schema, r"the channel at byte \d+ \(/\S+\) refers to schema \d+, which the file never"),
    ):
        path = damaged(bag_recording, tmp_path / name, lambda data, b=begin, e=end: data.__delitem__(slice(b, e)))
        code, err = liver_p2p(capsys, "replay", path)
        assert code == 2 and re.search(message, err) and err.startswith("liver-p2p: error: cannot read flight"), err


def test_records_of_another_shape_are_refused_with_what_lacks(bag_recording, tmp_path, capsys):
    _, config_start, _ = json_record(bag_recording, TOPIC_CONFIG)
    snapshot_end = [r for r in mcap_records(bag_recording) if r[3] == TOPIC_EVENT][-1]
    assert b'"snapshot_end"' in Path(bag_recording).read_bytes()[snapshot_end[1] : snapshot_end[2]]

    def without(key):
        return lambda values: {k: v for k, v in values.items() if k != key}

    cases = [  # (topic, nth record, change, the line's end)
        (TOPIC_REGISTRATION, 0, without("pose"), "(registration 0 lacks 'pose')"),
        (TOPIC_REGISTRATION, 1, without("reason"), "(registration 1 lacks 'reason')"),
        (TOPIC_REGISTRATION, 0, lambda v: {**v, "stamp_ns": str(v["stamp_ns"])}, "has 'stamp_ns' as str, not int)"),
        (
            TOPIC_REGISTRATION,
            0,
            lambda v: {**v, "pose": {**v["pose"], "T_sensor_ct_mm": [[1, 0], [0, 1]]}},
            "(registration 0's pose lacks a 4x4 'T_sensor_ct_mm' of numbers)",
        ),  # fmt: skip
        (TOPIC_META, 0, without("file_index"), "(its meta record lacks 'file_index')"),
        (
            TOPIC_META,
            0,
            lambda v: list(v.values()),
            f"(the {TOPIC_META} record at byte 0 is a JSON list, not an object)",
        ),
        (TOPIC_CONFIG, 0, without("config"), "lacks 'config')"),
        (TOPIC_EVENT, 0, without("event"), "lacks 'event')"),
    ]
    for n, (topic, nth, change, end) in enumerate(cases):
        path = rewritten(bag_recording, tmp_path / f"v{n}.mcap", topic, change, nth)
        code, err = liver_p2p(capsys, "replay", path)
        assert code == 2 and "not a flight recording this version reads (" in err, (end, err)
        assert err.endswith(end.replace("record at byte 0", f"record at byte {json_record(path, topic)[0]}")), err
    other = rewritten(bag_recording, tmp_path / "v2.mcap", TOPIC_META, lambda v: {**v, "format": FORMAT[:-1] + "2"})
    code, err = liver_p2p(capsys, "replay", other)
    assert code == 2 and f"v2.mcap is a flight recording of format '{FORMAT[:-1]}2'; this version reads" in err, err


def test_a_damaged_head_is_refused_not_replayed_as_a_plain_bag(bag_recording, tmp_path, capsys):
    data = Path(bag_recording).read_bytes()
    first_channel = next(start for op, start, _, _ in mcap_records(bag_recording) if op == CHANNEL)
    schema_name = data.index(b"std_msgs/msg/String")
    flips = {
        "schema.mcap": lambda d: d.__setitem__(schema_name + 18, d[schema_name + 18] ^ 0x01),  # 'String' -> 'Strinf'
        "opcode.mcap": lambda d: d.__setitem__(first_channel, 0x55),  # the meta's channel: an unknown record
    }
    for name, flip in flips.items():
        path = damaged(bag_recording, tmp_path / name, flip)
        code, err = liver_p2p(capsys, "replay", path)
        assert code == 2 and f"{name} looks like a flight recording but its head cannot be read: " in err, err
    assert not is_recording(BAG_A / f"{BAG_A.name}.mcap")  # a plain bag's .mcap is no recording


def test_a_series_with_a_file_missing_is_refused_naming_it(tmp_path, capsys):
    path = tmp_path / "rot.mcap"
    replay_bag(BAG_A, CONFIG.replace(record_max_mb=0.05), record_path=path, max_frames=4)  # a file a registration
    files = [continuation(path, i) for i in range(4)]
    assert all(f.is_file() for f in files), sorted(tmp_path.iterdir())
    files[2].rename(tmp_path / "aside.mcap")
    with pytest.raises(InputError, match=r"rot_002.mcap of the recording rot.mcap is missing; rot_003.mcap and after"):
        rerun_recording(path)
    code, err = liver_p2p(capsys, "replay", path)
    assert code == 2 and "rot_002.mcap of the recording rot.mcap is missing" in err, err
    assert rerun_recording(files[3]).registrations >= 1  # the file after the gap, on its own, as the line says


def test_bag_play_plays_the_inputs_only_unless_all_topics(bag_recording):
    pytest.importorskip("rclpy")
    from liver_p2p_reg.bags.player import split_topics

    topics = bag_topics(bag_recording)
    played, skipped = split_topics(topics)
    inputs = ["/intraop/fiducials", "/intraop/points", "/preop/fiducials", "/preop/mesh", "/preop/points"]
    assert played == [*inputs, "/preop/structure_labels", "/preop/structures"]  # the set each registration moved
    assert "/registration/pose" in skipped and "/diagnostics" in skipped and TOPIC_REGISTRATION in skipped
    assert split_topics(topics, all_topics=True) == (sorted(topics), [])
