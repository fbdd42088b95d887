"""The flight recorder: real MCAP recordings of replays, the CLI and the live node, re-run pose for pose bit for bit."""

import io
import json
import re
import shutil
import signal
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from ros_support import BAG_A, BAGS, bag_frames_m

from liver_p2p_reg.bags.flight_replay import ReadState, is_recording, read_recording, rerun_recording
from liver_p2p_reg.bags.io import read_messages
from liver_p2p_reg.bags.recorded_points import message_points_mm, points_message
from liver_p2p_reg.bags.recorder import TOPIC_CONFIG, TOPIC_META, TOPIC_REGISTRATION, continuation, recorder_factory
from liver_p2p_reg.bags.replay import replay_bag
from liver_p2p_reg.bags.rerun_report import ROUNDOFF_TRANSLATION_MM, Rerun, deformed_within_roundoff, within_roundoff
from liver_p2p_reg.config import Config
from liver_p2p_reg.ros.messages import (
    feed_intraop_fiducials_msg,
    feed_intraop_msg,
    feed_preop_fiducials_msg,
    feed_preop_msg,
)
from liver_p2p_reg.ros.topics import TOPIC_INTRAOP, TOPIC_INTRAOP_FIDUCIALS, TOPIC_PREOP, TOPIC_PREOP_FIDUCIALS

CONFIG = Config(sensor_at_frame_origin=False)  # BAG_A's clouds are random crops, in no sensor's frame


def cli(*args, timeout=300):
    """`liver-p2p ARGS` as its own process: (exit status, stdout, stderr)."""
    proc = subprocess.run(
        [sys.executable, "-m", "liver_p2p_reg", *map(str, args)], capture_output=True, text=True, timeout=timeout
    )
    return proc.returncode, proc.stdout, proc.stderr


def reproduced(report):
    """Poses a re-run reproduced: bitwise, or within floating-point round-off (another process's summation order)."""
    return report.identical + report.roundoff


def recorded(path):
    """topic -> the messages of a recording (its JSON records as dicts)."""
    out = {}
    for item in read_recording(path):
        out.setdefault(item.topic, []).append(item.values if item.msgtype == "std_msgs/msg/String" else item.msg)
    return out


def diag_values(msg):
    """The key/values of a DiagnosticArray's first status."""
    return {kv.key: kv.value for kv in msg.status[0].values}


def mcap_records(path):
    """(opcode, start offset, end offset, topic of a message or "") of every record of an MCAP file."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Channel, Message

    data, out, topics, pos = Path(path).read_bytes(), [], {}, 8
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        body = data[pos + 9 : pos + 9 + length]
        topic = ""
        if opcode == 0x04:
            channel = Channel.read(ReadDataStream(io.BytesIO(body)))
            topics[channel.id] = channel.topic
        elif opcode == 0x05:
            topic = topics[Message.read(ReadDataStream(io.BytesIO(body)), length).channel_id]
        out.append((opcode, pos, pos + 9 + length, topic))
        pos += 9 + length
    return out


@pytest.fixture(scope="module")
def bag_recording(tmp_path_factory):
    """A replay of BAG_A, flight-recorded (5 registrations, the last frames tracked)."""
    path = tmp_path_factory.mktemp("rec") / "replay.mcap"
    row = replay_bag(BAG_A, CONFIG, record_path=path)
    assert row.registered == row.frames == 5
    return path


def test_points_are_stored_exactly():
    rng = np.random.default_rng(0)
    from_float32 = rng.normal(0, 0.1, (500, 3)).astype(np.float32).astype(np.float64) * 1e3  # a ROS cloud, decoded
    arbitrary = rng.normal(0, 80.0, (500, 3))  # millimetres from a file: float32 metres would lose bits
    arbitrary[3] = np.nan
    for points in (from_float32, arbitrary):
        back = message_points_mm(points_message(points, "camera", 7))
        assert back.shape == points.shape and back.tobytes() == points.tobytes()
    assert len(points_message(from_float32, "camera", 7).fields) == 3  # float32 metres, as the bags
    assert len(points_message(arbitrary, "camera", 7).fields) == 6  # + exact float64 x_mm, y_mm, z_mm


def test_a_recorded_replay_is_re_run_bit_for_bit_by_the_cli(bag_recording):
    topics = recorded(bag_recording)
    meta = topics[TOPIC_META][0]
    assert meta["package_version"] and len(meta["weights_sha256"]) == 64 and meta["file_index"] == 0
    assert topics[TOPIC_CONFIG][0]["config"]["sensor_at_frame_origin"] is False
    assert len(topics[TOPIC_PREOP]) == len(topics[TOPIC_PREOP_FIDUCIALS]) == 1
    regs = topics[TOPIC_REGISTRATION]
    assert [r["reason"] for r in regs] == ["continuous"] * 5 and all(r["pose"] for r in regs)
    assert all(r["fiducials"] for r in regs) and len(topics[TOPIC_INTRAOP_FIDUCIALS]) == 5  # the pair each used
    assert "track" in [r["method"] for r in regs]
    assert len(topics[TOPIC_INTRAOP]) == 5 and len(topics["/registration/pose"]) == len(topics["/diagnostics"]) == 5
    # the input clouds as the node registered them: the bag's frames, decoded
    _, frames_m = bag_frames_m(BAG_A)
    assert message_points_mm(topics[TOPIC_INTRAOP][0]).tobytes() == (frames_m[0] * 1e3).tobytes()
    # a complete recording is rosbag2 MCAP that rosbags reads like any bag
    assert sum(1 for m in read_messages(bag_recording) if m.topic == TOPIC_INTRAOP) == 5
    code, out, err = cli("replay", bag_recording)
    assert code == 0, err
    assert "5 registrations re-run from 1 file(s): " in out and "differ" not in out, out
    bitwise, poses = map(int, re.search(r"(\d+) of (\d+) poses bitwise identical", out).groups())
    more = re.search(r"(\d+) more within floating-point round-off", out)
    assert poses == 5 and bitwise + (int(more.group(1)) if more else 0) == 5, out


def test_round_off_is_told_apart_from_a_real_difference():
    T = np.eye(4)
    T[:3, 3] = (12.5, -40.0, 110.0)
    near, rotated, moved = T.copy(), T.copy(), T.copy()
    near[:3, 3] += 1.83e-6  # the one CI re-run that was not bitwise: the same pose
    near[0, 1] += 5e-7
    rotated[0, 1] += 1e-5  # 2 um at 200 mm: a real difference
    moved[2, 3] += 1e-3
    assert within_roundoff(T, T) and within_roundoff(near, T)
    assert not within_roundoff(rotated, T) and not within_roundoff(moved, T)
    surface = np.random.default_rng(0).normal(size=(50, 3)) * 80.0
    assert deformed_within_roundoff(surface + 5e-4, surface) and not deformed_within_roundoff(surface + 2e-3, surface)
    assert not deformed_within_roundoff(surface[:-1], surface)  # another vertex count is never round-off
    report = Rerun(["a.mcap"], registrations=3, poses=3, identical=2, roundoff=1)
    assert report.ok and "2 of 3 poses bitwise identical" in report.summary()
    assert f"1 more within floating-point round-off ({ROUNDOFF_TRANSLATION_MM:g} mm" in report.summary()


def test_record_refuses_an_existing_file_unless_forced(bag_recording, tmp_path):
    code, _, err = cli("replay", BAG_A, "--record", bag_recording)
    assert code == 2 and err.strip().endswith("exists; pass --force to overwrite it"), err
    code, _, err = cli("replay", bag_recording, "--method", "fpfh-p2p")
    assert code == 2 and "re-run under its recorded parameters" in err, err


def cut(path, at, into):
    into.write_bytes(Path(path).read_bytes()[:at])
    return into


def test_a_truncated_recording_is_read_up_to_its_last_complete_registration(bag_recording, tmp_path):
    records = mcap_records(bag_recording)
    data_end = next(start for op, start, _, _ in records if op == 0x0F)  # the summary follows
    clouds = [(s, e) for op, s, e, t in records if t == TOPIC_INTRAOP]
    commits = [(s, e) for op, s, e, t in records if t == TOPIC_REGISTRATION]
    cases = {
        "inside the last cloud": ((clouds[-1][0] + clouds[-1][1]) // 2, 4),
        "inside the last commit": (commits[-1][0] + 12, 4),
        "just after the last commit (no footer)": (commits[-1][1], 5),
        "inside a record header": (data_end + 3, 5),
    }
    for name, (at, expected) in cases.items():
        path = cut(bag_recording, at, tmp_path / "cut.mcap")
        report = rerun_recording(path)
        assert report.truncated, name
        assert (report.registrations, reproduced(report), report.poses) == (expected,) * 3, (name, report)
        assert report.ok and "without its footer" in report.summary()
    state = ReadState([])
    assert sum(1 for _ in read_recording(bag_recording, state)) > 0 and not state.truncated


def drive(core, bag, change_after=None, changes=None, frames=None, reset_after=None, after=None):
    """Feed a bag's messages to a core as replay does, registering every cloud (1 s apart, at most `frames`);
    reconfigure after `change_after` registrations, reset the survey after `reset_after`, call `after(n)` after
    the n-th. Returns the poses."""
    poses, t = [], 0.0
    for item in read_messages(bag):
        if item.topic == TOPIC_PREOP:
            feed_preop_msg(core, item.msg)
        elif item.topic == TOPIC_PREOP_FIDUCIALS:
            feed_preop_fiducials_msg(core, item.msg)
        elif item.topic == TOPIC_INTRAOP_FIDUCIALS:
            feed_intraop_fiducials_msg(core, item.msg)
        elif item.topic == TOPIC_INTRAOP:
            t += 1.0
            feed_intraop_msg(core, item.msg, t)
            output = core.process_pending(t) or core.flush()
            poses.append(output.pose.T_sensor_ct_mm)
            if len(poses) == change_after:
                core.reconfigure(changes)
            if len(poses) == reset_after:
                core.reset_survey()
            if after is not None:
                after(len(poses))
            if len(poses) == frames:
                break
    core.close_recording()
    return poses


def test_a_parameter_change_mid_stream_is_recorded_and_re_applied(bag_recording, tmp_path):
    from liver_p2p_reg.stream.core import NodeCore

    path = tmp_path / "changed.mcap"
    core = NodeCore(CONFIG.replace(record_path=str(path)), recorder_factory=recorder_factory("refuse"))
    changes = {"icp_max_points": 300, "track_previous_pose": False, "max_input_points": 10_000}
    poses = drive(core, BAG_A, change_after=2, changes=changes)
    topics = recorded(path)
    configs = topics[TOPIC_CONFIG]
    assert [c["snapshot"] for c in configs] == [True, False]
    assert configs[1]["config"]["icp_max_points"] == 300 and configs[1]["config"]["track_previous_pose"] is False
    # the clouds are recorded as decoded, before the node voxelizes those of max_input_points or more
    clouds = [message_points_mm(m) for m in topics[TOPIC_INTRAOP]]
    assert all(len(c) == 18508 for c in clouds)
    valid = [int(diag_values(d)["valid_points"]) for d in topics["/diagnostics"]]
    assert valid[:2] == [18508] * 2 and all(v < 10_000 for v in valid[2:]), valid
    # the change matters: the later poses differ from those of the unchanged replay ...
    unchanged = [np.asarray(r["pose"]["T_sensor_ct_mm"]) for r in recorded(bag_recording)[TOPIC_REGISTRATION]]
    assert all(a.tobytes() == b.tobytes() for a, b in zip(poses[:2], unchanged[:2], strict=True))
    assert all(a.tobytes() != b.tobytes() for a, b in zip(poses[2:], unchanged[2:], strict=True))
    # ... and the re-run applies it where it came
    report = rerun_recording(path)
    assert (report.registrations, reproduced(report)) == (5, 5) and report.ok, report


def test_survey_mode_and_its_resets_re_run_bit_for_bit(tmp_path):
    from liver_p2p_reg.stream.core import NodeCore

    path = tmp_path / "survey.mcap"
    core = NodeCore(Config(mode="survey", record_path=str(path)), recorder_factory=recorder_factory("refuse"))
    drive(core, BAGS / "sweep_insilico_9000002", frames=10, reset_after=6)
    topics = recorded(path)
    assert [r["reason"] for r in topics[TOPIC_REGISTRATION]] == ["survey"] * 10
    assert [e["event"] for e in topics["/flight_recorder/event"]] == ["snapshot_end", "reset_survey"]
    report = rerun_recording(path)
    assert (report.registrations, reproduced(report)) == (10, 10) and report.ok, report


def test_rotation_starts_numbered_files_that_re_run_as_one_and_alone(tmp_path):
    path = tmp_path / "rot.mcap"
    structures = structures_of(bag_frames_m(BAG_A)[0] * 1e3, 10)
    replay_bag(BAG_A, CONFIG.replace(record_max_mb=0.6), record_path=path, structures=structures)
    files = [continuation(path, i) for i in range(3)]
    assert files[1].is_file(), sorted(tmp_path.iterdir())
    report = rerun_recording(path)
    assert len(report.files) >= 2 and (report.registrations, reproduced(report)) == (5, 5) and report.ok, report
    assert report.structures == 5, report
    # a later file alone: its head repeats the model, the parameters and the tracking prior; its first
    # registration, the structures
    alone = rerun_recording(files[1])
    assert alone.ok and alone.registrations == reproduced(alone) == alone.structures >= 1, alone
    head = recorded(files[1])
    assert head[TOPIC_META][0]["file_index"] == 1 and head[TOPIC_CONFIG][0]["snapshot"] and head[TOPIC_PREOP]
    assert is_recording(files[1]) and not is_recording(BAG_A / f"{BAG_A.name}.mcap")


def structures_of(preop_mm, *shares):
    """Subsurface structures for a test: preop points pulled halfway to the centroid, a slice of them each."""
    from liver_p2p_reg.structures_io import Structure

    inner = preop_mm.mean(axis=0) + 0.5 * (preop_mm - preop_mm.mean(axis=0)) + 0.123  # not float32 metres
    return [Structure(f"s{i}", inner[i * 40 : i * 40 + n], i) for i, n in enumerate(shares)]


def test_structures_are_recorded_with_each_registration_and_re_placed_bit_for_bit(tmp_path):
    """The set each registration moved is kept (when it changed) and given back before it; its placement
    (positions and bounds) is compared with the recorded one. A set that changes mid-stream, and one cleared."""
    import dataclasses

    from liver_p2p_reg.bags.recorded_points import message_structures
    from liver_p2p_reg.bags.rerun_report import structures_within_roundoff
    from liver_p2p_reg.ros.topics import TOPIC_PREOP_STRUCTURES, TOPIC_STRUCTURE_LABELS, TOPIC_STRUCTURES
    from liver_p2p_reg.stream.core import NodeCore

    preop_mm = bag_frames_m(BAG_A)[0] * 1e3
    first = structures_of(preop_mm, 12, 7)
    second = [dataclasses.replace(structures_of(preop_mm + 2.0, 5)[0], label_id=2**31 - 2)]  # any id a loader sends
    path = tmp_path / "structures.mcap"
    core = NodeCore(CONFIG.replace(record_path=str(path)), recorder_factory=recorder_factory("refuse"))
    core.structures.set_structures(first)
    sets, placed = {2: second, 4: []}, []  # a new set after two registrations, none after four

    def after(n):
        placed.append(core.last_output.structures)
        if n in sets:
            core.structures.set_structures(sets[n])

    assert len(drive(core, BAG_A, after=after)) == 5
    topics = recorded(path)
    pairs = zip(topics[TOPIC_PREOP_STRUCTURES], topics[TOPIC_STRUCTURE_LABELS], strict=True)
    kept = [message_structures(cloud, json.dumps(labels)) for cloud, labels in pairs]  # names: JSON
    assert [[(s.label, s.label_id, len(s.points_mm)) for s in k] for k in kept] == [
        [("s0", 0, 12), ("s1", 1, 7)],
        [("s0", 2**31 - 2, 5)],
        [],
    ]
    assert kept[0][1].points_mm.tobytes() == first[1].points_mm.tobytes()  # exact millimetres
    regs = topics[TOPIC_REGISTRATION]
    assert [r["structures_sha256"] is not None for r in regs] == [True] * 4 + [False]
    assert len(topics[TOPIC_STRUCTURES]) == 4
    report = rerun_recording(path)
    assert report.ok and (report.structures, report.structures_identical + report.structures_roundoff) == (4, 4), report
    assert "placements of structures bitwise identical" in report.summary()
    # round-off is told from a difference against the published cloud (float32 metres)
    cloud = topics[TOPIC_STRUCTURES][0]
    assert structures_within_roundoff(placed[0], cloud)
    moved = [dataclasses.replace(s, position_mm=s.position_mm + 0.01) for s in placed[0]]
    assert not structures_within_roundoff(moved, cloud)
    assert not structures_within_roundoff(placed[0][:1], cloud)


def test_register_cli_record_keeps_its_structures_and_re_places_them(tmp_path):
    preop_m, frames_m = bag_frames_m(BAG_A)
    np.save(tmp_path / "source.npy", preop_m * 1e3)
    np.save(tmp_path / "view.npy", frames_m[0] * 1e3)
    np.save(tmp_path / "tumour.npy", structures_of(preop_m * 1e3, 9)[0].points_mm)
    rec = tmp_path / "register.mcap"
    code, out, err = cli("register", tmp_path / "source.npy", tmp_path / "view.npy", "--structures",
                         f"{tmp_path / 'tumour.npy'}:tumour", "--record", rec, "--sensor-origin", "0,0,0")  # fmt: skip
    assert code == 0, err
    placed = json.loads(out)["structures"][0]
    regs = recorded(rec)[TOPIC_REGISTRATION]
    assert regs[0]["structures_sha256"] and placed["label"] == "tumour"
    report = rerun_recording(rec)
    assert report.ok and report.structures == 1 and report.registrations == reproduced(report) == 1, report


def test_register_cli_record_is_re_run_bit_for_bit(tmp_path):
    preop_m, frames_m = bag_frames_m(BAG_A)
    np.save(tmp_path / "source.npy", preop_m * 1e3)
    for i in (0, 3):
        np.save(tmp_path / f"view{i}.npy", frames_m[i] * 1e3 + 0.123)  # not float32 metres: stored exactly
    rec = tmp_path / "register.mcap"
    code, _, err = cli("register", tmp_path / "source.npy", tmp_path / "view0.npy", tmp_path / "view3.npy",
                       "--record", rec, "--sensor-origin", "0,0,0", "-q")  # fmt: skip
    assert code == 0, err
    regs = recorded(rec)[TOPIC_REGISTRATION]
    assert [r["reason"] for r in regs] == ["register"] * 2 and regs[0]["extras"]["sensor_origin_mm"] == [0, 0, 0]
    report = rerun_recording(rec)
    assert (report.registrations, reproduced(report)) == (2, 2) and report.ok, report


def test_the_live_node_killed_mid_stream_leaves_a_recording_that_re_runs_bit_for_bit(tmp_path):
    from conftest import require_rclpy

    require_rclpy()
    from ros_support import start_graph, stop_graph

    path = tmp_path / "node.mcap"
    params = {"record_path": str(path), "sensor_at_frame_origin": False, "max_rate_hz": 20.0}
    graph = start_graph(tmp_path / "logs", params)
    try:
        graph.send_model(BAG_A)
        since = graph.mark()
        for i in range(3):
            graph.send_frame(BAG_A, i)
            assert graph.wait_attempts(since, i + 1), graph.node.stderr()
        assert graph.probe.reregister().success  # the ~/reregister service: reason `reregister`
        graph.set(icp_max_points=300)  # a parameter change mid-stream, recorded
        for i in (3, 4, 0, 1):  # then frames in a row; the node is killed while it works on them
            graph.send_frame(BAG_A, i)
        graph.probe.wait_for(lambda: len(graph.attempts(since)) >= 5, 60)
        graph.send_frame(BAG_A, 2)
        seen = len(graph.attempts(since))
        graph.node.stop(signal.SIGKILL)
    finally:
        stop_graph(graph)
    shutil.copy(path, tmp_path / "copy.mcap")  # read what the killed writer left, as found
    report = rerun_recording(tmp_path / "copy.mcap")
    assert report.truncated and report.ok, report
    assert report.registrations >= seen >= 5 and reproduced(report) == report.poses == report.registrations, report
    topics = recorded(tmp_path / "copy.mcap")
    assert [r["reason"] for r in topics[TOPIC_REGISTRATION]][:4] == ["continuous"] * 3 + ["reregister"]
    configs = topics[TOPIC_CONFIG]
    assert configs[0]["config"]["record_path"] == str(path) and configs[-1]["config"]["icp_max_points"] == 300


def test_the_node_switches_recordings_at_runtime_and_closes_them_on_shutdown(tmp_path):
    from conftest import require_rclpy

    require_rclpy()
    from ros_support import start_graph, stop_graph

    first, second = tmp_path / "first.mcap", tmp_path / "second.mcap"
    first.write_bytes(b"an older recording")  # never overwritten: the node takes a timestamped name
    graph = start_graph(tmp_path / "logs", {"record_path": str(first), "sensor_at_frame_origin": False})
    try:
        graph.send_model(BAG_A)
        since = graph.mark()
        graph.send_frame(BAG_A, 0)
        assert graph.wait_attempts(since, 1), graph.node.stderr()
        graph.set(record_path=str(second))  # closes the first recording, opens the second with the model in its head
        graph.probe.wait_for(second.is_file, 30)
        graph.send_frame(BAG_A, 1)
        assert graph.wait_attempts(since, 2), graph.node.stderr()
        # a recording that cannot be opened is refused by the parameter set itself, with the reason
        (refused,) = graph.probe.set_parameters({"record_path": str(tmp_path / "no" / "such.mcap")})
        assert not refused.successful and "does not exist" in refused.reason, refused.reason
        code, _ = graph.node.stop(signal.SIGINT)
        assert code == 0, graph.node.stderr()
    finally:
        stop_graph(graph)
    assert first.read_bytes() == b"an older recording"
    (renamed,) = [p for p in tmp_path.glob("first-*.mcap")]
    for path in (renamed, second):
        state = ReadState([])
        list(read_recording(path, state))
        assert not state.truncated, path  # closed with its footer
        report = rerun_recording(path)
        assert (report.registrations, reproduced(report)) == (1, 1) and report.ok, (path, report)
    assert recorded(second)[TOPIC_PREOP] and recorded(second)[TOPIC_CONFIG][0]["snapshot"]


def test_a_recording_with_damaged_bytes_is_one_line_not_a_traceback(bag_recording, tmp_path):
    records = mcap_records(bag_recording)
    start, end = next((s, e) for op, s, e, t in records if t == TOPIC_REGISTRATION)
    data = bytearray(Path(bag_recording).read_bytes())
    middle = (start + end) // 2
    data[middle : middle + 64] = bytes(b ^ 0xFF for b in data[middle : middle + 64])  # inside a String record's JSON
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    code, _, err = cli("replay", damaged)
    assert (
        code == 2 and err.strip().startswith("liver-p2p: error: cannot read flight recording") and "damaged.mcap" in err
    ), err
    assert "Traceback" not in err


def test_a_recording_cut_before_its_first_registration_verifies_nothing_and_says_so(bag_recording, tmp_path):
    records = mcap_records(bag_recording)
    first_commit = next(s for op, s, e, t in records if t == TOPIC_REGISTRATION)
    path = cut(bag_recording, first_commit + 12, tmp_path / "early.mcap")
    code, _, err = cli("replay", path)
    assert code == 2 and "holds no complete registration to re-run" in err, err
