"""`liver-p2p bag play`: a bag's messages on live topics with recorded timing, original stamps and documented QoS."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import require_rclpy

rclpy = require_rclpy()

from ros_support import BAG_B  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from visualization_msgs.msg import Marker  # noqa: E402

from liver_p2p_reg.bags.io import read_messages  # noqa: E402
from liver_p2p_reg.livegraph.graph import GraphProbe, set_isolated_environment, stamp_ns  # noqa: E402
from liver_p2p_reg.ros.topics import (  # noqa: E402
    TOPIC_INTRAOP,
    TOPIC_INTRAOP_FIDUCIALS,
    TOPIC_PREOP,
    TOPIC_PREOP_FIDUCIALS,
    TOPIC_PREOP_MESH,
    rclpy_qos,
)


@pytest.fixture
def listener():
    set_isolated_environment()
    probe = GraphProbe("bag_play_listener")
    got = {
        TOPIC_PREOP: [],
        TOPIC_PREOP_FIDUCIALS: [],
        TOPIC_PREOP_MESH: [],
        TOPIC_INTRAOP: [],
        TOPIC_INTRAOP_FIDUCIALS: [],
    }
    for topic, items in got.items():
        probe.node.create_subscription(
            Marker if topic == TOPIC_PREOP_MESH else PointCloud2,
            topic,
            lambda m, items=items: items.append((stamp_ns(m), time.monotonic())),
            rclpy_qos(topic),
        )
    yield probe, got
    probe.close()


def play(*args):
    return subprocess.Popen(
        [sys.executable, "-m", "liver_p2p_reg", "bag", "play", str(BAG_B), "--wait-s", "30", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(os.environ),
    )


def test_play_keeps_stamps_and_timing_at_rate(listener):
    """Waits for the listener (--wait-s), then every message, original stamps, at twice the recorded pace."""
    probe, got = listener
    expected = [(m.topic, m.msg.header.stamp.sec * 10**9 + m.msg.header.stamp.nanosec) for m in read_messages(BAG_B)]
    proc = play("--rate", "2")
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert len(expected) == 13 and f"published {len(expected)} messages" in out  # the preop mesh too
    probe.wait_for(lambda: len(got[TOPIC_INTRAOP]) == 5, 5)
    assert [s for s, _ in got[TOPIC_INTRAOP]] == [s for t, s in expected if t == TOPIC_INTRAOP]
    assert [s for s, _ in got[TOPIC_INTRAOP_FIDUCIALS]] == [s for t, s in expected if t == TOPIC_INTRAOP_FIDUCIALS]
    assert [s for s, _ in got[TOPIC_PREOP]] == [s for t, s in expected if t == TOPIC_PREOP]
    # the mesh on its latched QoS, with its model's stamp (register_node pairs them by it)
    assert probe.wait_for(lambda: [s for s, _ in got[TOPIC_PREOP_MESH]] == [s for s, _ in got[TOPIC_PREOP]], 5)
    gaps = np.diff([t for _, t in got[TOPIC_INTRAOP]])
    # recorded 0.5 s apart, played at rate 2 (arrival times also carry this machine's scheduling jitter)
    assert abs(np.median(gaps) - 0.25) < 0.05 and abs(gaps.sum() - 1.0) < 0.3, gaps


def test_latched_preop_reaches_a_late_subscriber_and_loop_stops_on_sigint(listener):
    probe, got = listener
    proc = play("--loop", "--rate", "4")
    try:
        assert probe.wait_for(lambda: len(got[TOPIC_INTRAOP]) >= 7, 60), "no second pass of --loop"
        late = []
        probe.node.create_subscription(
            PointCloud2, TOPIC_PREOP, lambda m: late.append(stamp_ns(m)), rclpy_qos(TOPIC_PREOP)
        )
        assert probe.wait_for(lambda: late, 10), "the latched /preop/points did not reach a late subscriber"
        start = time.monotonic()
        proc.send_signal(signal.SIGINT)
        proc.wait(10)
        assert proc.returncode == 0 and time.monotonic() - start < 2.0, proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()


def test_play_without_the_bag_is_one_line(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "liver_p2p_reg", "bag", "play", str(tmp_path / "nope")], capture_output=True, text=True
    )
    assert proc.returncode == 2 and proc.stderr.strip().count("\n") == 0 and "bag not found" in proc.stderr
