"""Every bundled bag through the live graph (loader + register_node processes, bag played on real topics) equals replay."""

import numpy as np
import pytest
from conftest import require_rclpy

rclpy = require_rclpy()

from ros_support import BAGS  # noqa: E402
from same_pose import surface_shift_mm  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from liver_p2p_reg.bags.io import BagWriter, bag_custom_data, read_messages  # noqa: E402
from liver_p2p_reg.bags.replay import replay_bag  # noqa: E402
from liver_p2p_reg.config import Config  # noqa: E402
from liver_p2p_reg.livegraph.demo import format_graph_table, run_graph  # noqa: E402
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_m  # noqa: E402
from liver_p2p_reg.ros.topics import TOPIC_INTRAOP, TOPIC_INTRAOP_FIDUCIALS  # noqa: E402
from liver_p2p_reg.stream.intake import RATE_TOLERANCE  # noqa: E402

# Every frame a full registration: a pose then depends only on its model and cloud, so frames the
# live node drops under load (latest-only) cannot change the others, and each compares one to one.
# No sensor origin: replay takes none for random-crop bags (their clouds are in no sensor's frame), and the
# free-space score it adds can pick another candidate; the live node must run the same configuration.
PARAMS = {"track_previous_pose": False, "sensor_at_frame_origin": False}


def pose_matrix(position, orientation):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([orientation.x, orientation.y, orientation.z, orientation.w]).as_matrix()
    T[:3, 3] = [position.x, position.y, position.z]
    return T


def stamp_of(msg):
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def by_stamp(messages, topic):
    return {stamp_of(m.msg): m.msg for m in messages if m.topic == topic}


def same_arithmetic(values):
    """A registration diagnostic's values without the timings and the cache state (which differ by design)."""
    return {k: v for k, v in values.items() if not k.startswith("runtime_ms.") and k != "model_cache_computed"}


def registration_values(messages):
    """stamp -> key/values of the first registration diagnostic of each cloud."""
    out = {}
    for m in messages:
        if m.topic != "/diagnostics":
            continue
        for status in m.msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if status.name.endswith("registration") and "stamp_ns" in values and "received_clouds" not in values:
                out.setdefault(int(values["stamp_ns"]), values)
    return out


def faster_than_the_rate_limit(bag, config):
    """Whether the bag's clouds come closer together than max_rate_hz lets the node register them."""
    log_ns = [m.timestamp_ns for m in read_messages(bag, [TOPIC_INTRAOP])]
    return min(np.diff(log_ns), default=np.inf) * 1e-9 < (1.0 - RATE_TOLERANCE) / config.max_rate_hz


def frames_only(bag, stamps, path):
    """The bag with only the clouds stamped `stamps` (and their fiducials), moved 1 s apart in log time
    (stamps unchanged) so that replay registers every one of them: the frames the live graph registered
    and replay's rate limit skipped. A pose depends only on its model and cloud here (PARAMS)."""
    clouds = sorted((m.timestamp_ns, stamp_of(m.msg)) for m in read_messages(bag, [TOPIC_INTRAOP]))
    chosen = [(log_ns, stamp) for log_ns, stamp in clouds if stamp in stamps]
    shift = {stamp: clouds[0][0] + (i + 1) * 10**9 - log_ns for i, (log_ns, stamp) in enumerate(chosen)}
    with BagWriter(path, overwrite=True, custom_data=bag_custom_data(bag)) as writer:
        for m in read_messages(bag):
            if m.topic not in (TOPIC_INTRAOP, TOPIC_INTRAOP_FIDUCIALS):
                writer.write(m.topic, m.msgtype, m.timestamp_ns, m.msg)
            elif stamp_of(m.msg) in shift:  # fiducials keep their offset before their cloud
                writer.write(m.topic, m.msgtype, m.timestamp_ns + shift[stamp_of(m.msg)], m.msg)
    return path


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    out = tmp_path_factory.mktemp("graph")
    bags = sorted(p for p in BAGS.iterdir() if (p / "metadata.yaml").is_file())
    rows, startup_s = run_graph(bags, out, params=PARAMS, log=lambda *_: None)
    return bags, rows, out


def test_every_bundled_bag_through_the_live_graph_equals_replay(live, tmp_path, capsys):
    bags, rows, out = live
    with capsys.disabled():
        print("\n" + format_graph_table(rows))
    config = Config(**PARAMS)
    compared = 0
    for bag, row in zip(bags, rows, strict=True):
        assert row.registered >= 1, f"{bag.name}: no pose through the live graph"
        assert row.reregister.startswith("pose: registered"), (bag.name, row.reregister)
        replay_bag(bag, config, out_path=tmp_path / bag.name)
        replayed = list(read_messages(tmp_path / bag.name))
        replay_poses = by_stamp(replayed, "/registration/pose")
        replay_values = registration_values(replayed)
        recorded = list(read_messages(out / bag.name / "recorded"))
        live_poses = by_stamp(recorded, "/registration/pose")
        live_tf = by_stamp(recorded, "/registration/transform")
        live_clouds = by_stamp(recorded, "/registration/registered_preop")
        live_values = registration_values(recorded)
        inputs = list(read_messages(bag))
        preop_m = cloud_to_points_m(next(m.msg for m in inputs if m.topic == "/preop/points"))
        fid_ct = cloud_to_points_m(next(m.msg for m in inputs if m.topic == "/preop/fiducials")) * 1e3
        fid_cam = {s: cloud_to_points_m(msg) * 1e3 for s, msg in by_stamp(inputs, "/intraop/fiducials").items()}
        extra = set(row.poses) - set(replay_poses)
        if extra:
            # Clouds faster than max_rate_hz: which ones are registered depends on arrival and registration
            # times live, on log times in replay. Replay the frames only the live graph registered, alone.
            assert faster_than_the_rate_limit(bag, config), (bag.name, sorted(extra))  # else: strictly a subset
            only = frames_only(bag, extra, tmp_path / f"{bag.name}_live_frames")
            replay_bag(only, config, out_path=tmp_path / f"{bag.name}_live_frames_replay")
            replayed = list(read_messages(tmp_path / f"{bag.name}_live_frames_replay"))
            assert set(by_stamp(replayed, "/registration/pose")) == extra, bag.name
            replay_poses.update(by_stamp(replayed, "/registration/pose"))
            replay_values.update(registration_values(replayed))
        assert set(row.poses) <= set(replay_poses), bag.name
        for stamp in row.poses:
            live_pose, live_transform = live_poses[stamp], live_tf[stamp]
            T = pose_matrix(live_pose.pose.position, live_pose.pose.orientation)
            T_replay = pose_matrix(replay_poses[stamp].pose.position, replay_poses[stamp].pose.orientation)
            # Same arithmetic on the same float32 inputs, the same torch thread count (pinned per
            # registration): bitwise the same pose, whatever else ran in either process before.
            assert np.array_equal(T, T_replay), (bag.name, stamp, surface_shift_mm(T, T_replay, preop_m * 1e3))
            moved = preop_m @ T[:3, :3].T + T[:3, 3]
            t = live_transform.transform
            np.testing.assert_allclose(pose_matrix(t.translation, t.rotation), T, atol=1e-12)
            assert live_transform.child_frame_id == "ct" and live_transform.header.frame_id == "camera"
            np.testing.assert_allclose(cloud_to_points_m(live_clouds[stamp]), moved, atol=2e-6)
            # the reported RMS-TRE is the bag's own fiducials under the published pose, and replay's
            T_mm = T.copy()
            T_mm[:3, 3] *= 1e3
            tre = np.sqrt(np.mean(np.sum((fid_ct @ T_mm[:3, :3].T + T_mm[:3, 3] - fid_cam[stamp]) ** 2, axis=1)))
            assert abs(float(live_values[stamp]["rms_tre_mm"]) - tre) < 0.01, (bag.name, stamp)
            # and the same diagnostics, but for what depends on the clock or on what came before
            assert same_arithmetic(live_values[stamp]) == same_arithmetic(replay_values[stamp]), (bag.name, stamp)
            compared += 1
    assert compared >= len(bags)
