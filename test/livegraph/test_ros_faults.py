"""Faults a robot's graph brings, over real processes: looped bags with a jumping clock, restarts, QoS, parameter floods."""

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from conftest import require_rclpy

rclpy = require_rclpy()

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from ros_support import BAG_A, BAG_B, Graph, bag_raw, clean_stderr, start_graph, stop_graph  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402

from liver_p2p_reg.bags.io import read_messages  # noqa: E402
from liver_p2p_reg.livegraph.graph import NodeProcess, level_of, stamp_ns, values_of  # noqa: E402
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm  # noqa: E402
from liver_p2p_reg.ros.topics import TOPIC_INTRAOP, TOPIC_POSE, TOPIC_PREOP  # noqa: E402
from liver_p2p_reg.stream.health import STREAM_DIAG_NAME  # noqa: E402
from liver_p2p_reg.stream.outputs import DIAG_NAME, ERROR, OK, STALE, WARN  # noqa: E402


def play(bag, *extra):
    """`liver-p2p bag play BAG ...` as its own process, on this test's domain."""
    cmd = [sys.executable, "-m", "liver_p2p_reg", "bag", "play", str(bag), *extra]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=dict(os.environ), text=True)


def bag_fiducials_mm(bag):
    """The bag's preop fiducials and its intraop fiducials by stamp, mm."""
    items = list(read_messages(bag, ["/preop/fiducials", "/intraop/fiducials"]))
    fid_ct = next(cloud_to_points_mm(m.msg) for m in items if m.topic == "/preop/fiducials")
    by_stamp = {stamp_ns(m.msg): cloud_to_points_mm(m.msg) for m in items if m.topic == "/intraop/fiducials"}
    return fid_ct, by_stamp


def pose_mm(msg):
    p, q = msg.pose.position, msg.pose.orientation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    T[:3, 3] = [1e3 * p.x, 1e3 * p.y, 1e3 * p.z]
    return T


def registrations(graph, since=0):
    return [values_of(s) | {"level": level_of(s)} for s in graph.attempts(since)]


def quiet(graph, quiet_s):
    """A condition true once no pose and no diagnostic has reached the probe for `quiet_s` seconds."""
    seen = {"counts": None, "since": time.monotonic()}

    def condition():
        counts = (graph.probe.count(TOPIC_POSE), len(graph.attempts(0)))
        if counts != seen["counts"]:
            seen["counts"], seen["since"] = counts, time.monotonic()
        return time.monotonic() - seen["since"] >= quiet_s

    return condition


@pytest.fixture
def graph(tmp_path, request):
    params = getattr(request, "param", {})
    g = start_graph(tmp_path, params)
    yield g
    stop_graph(g)


@pytest.mark.parametrize("graph", [{"use_sim_time": True}], indirect=True)
def test_a_looped_bag_with_its_clock_jumping_back(graph):
    player = play(BAG_A, "--loop", "--clock", "--rate", "2")
    try:
        # 5 clouds in 2.5 s at rate 2: three loops in ~4 s, each starting the clock again at the bag's start
        assert graph.probe.wait_for(lambda: len(registrations(graph)) >= 12, 90), graph.node.stderr()[-3000:]
    finally:
        player.send_signal(signal.SIGINT)
        player.wait(20)
    # the node may still be answering a cloud taken before the player stopped: its pose comes before its
    # diagnostic, so read both only once the graph has been quiet a while (a CI run read 13 poses, 12 diagnostics)
    assert graph.probe.wait_for(quiet(graph, 1.5), 60), "the node kept publishing after the player stopped"
    # the bag's first cloud may be handled before its model (two topics' callbacks come in either order: seen once
    # under a loaded clean-clone run): the node says so and waits; every attempt after the first model is scored
    attempts = graph.attempts(0)
    first = next(i for i, s in enumerate(attempts) if "stamp_ns" in values_of(s))
    assert all("before any preop model" in s.message for s in attempts[:first]), [s.message for s in attempts]
    done = registrations(graph)[first:]
    stamps = [int(v["stamp_ns"]) for v in done]
    assert len(set(stamps)) <= 5 < len(stamps)  # the same stamps again: the clock went back at each loop
    assert all(v["level"] in (OK, WARN) for v in done), [v.get("level") for v in done]
    # no stale TRE: every registration, repeats of a stamp included, is scored against that stamp's own
    # fiducials under the pose it published (pose i answers registration i: one pose per OK/WARN attempt)
    poses = [p.msg for p in graph.probe.since(TOPIC_POSE)]
    assert len(poses) == len(done)
    fid_ct, fid_cam = bag_fiducials_mm(BAG_A)
    # a TRE may be absent (a cloud's fiducials handled before the loop's repeated model, which forgets them:
    # callbacks of two topics come in either order), never stale; before the fix no later loop had one at all
    scored = [v for v in done[5:] if "rms_tre_mm" in v]
    assert len(scored) >= len(done[5:]) // 2, [(v["stamp_ns"][-10:], v.get("rms_tre_mm")) for v in done]
    for values, pose in zip(done, poses, strict=True):
        assert stamp_ns(pose) == int(values["stamp_ns"])
        if "rms_tre_mm" not in values:
            continue
        T = pose_mm(pose)
        own = np.sqrt(np.mean(np.sum((fid_ct @ T[:3, :3].T + T[:3, 3] - fid_cam[stamp_ns(pose)]) ** 2, axis=1)))
        assert abs(float(values["rms_tre_mm"]) - own) < 0.01, (values["stamp_ns"], values["rms_tre_mm"], own)
    # the periodic status keeps coming on the steady clock; the node logs nothing above INFO
    statuses = [s for s, _ in graph.probe.diagnostics(0, DIAG_NAME) if "received_clouds" in values_of(s)]
    assert len(statuses) >= 3
    assert clean_stderr(graph.node.stderr()) == []


def test_status_goes_stale_without_clouds_and_a_level_change_is_published_at_once(tmp_path):
    g = start_graph(tmp_path, {"stale_after_s": 1.0})
    try:
        g.send_model(BAG_A)
        since = g.mark()
        g.send_frame(BAG_A)
        assert g.wait_attempts(since)
        stale = g.probe.wait_for(lambda: stale_status(g, since), 10)
        assert stale and stale.message.startswith("no intraop data for"), "no STALE status after 1 s without clouds"
        stream = [s for s, _ in g.probe.diagnostics(since, STREAM_DIAG_NAME)]
        assert stream and level_of(stream[-1]) == STALE and "frequency_hz" in values_of(stream[-1])
        # the probe's /intraop/points publisher is matched and silent: the stream's status counts it and says so
        assert values_of(stream[-1])["publishers"] == "1", values_of(stream[-1])
        assert stream[-1].message.endswith("1 publisher matched, nothing arrives"), stream[-1].message
        # the next cloud ends the silence: the status leaves STALE when the cloud arrives, not a period later
        since = g.mark()
        sent_s = g.send_frame(BAG_A, 1)
        assert g.wait_attempts(since)
        after = g.probe.wait_for(lambda: first_status(g, since, OK), 5)
        assert after is not None and after - sent_s < 0.15, (after - sent_s, "s after the cloud")
    finally:
        stop_graph(g)


def stale_status(g, since):
    found = [
        s
        for s, _ in g.probe.diagnostics(since, DIAG_NAME)
        # not the "no registration yet" a period may publish before the first registration is done
        if level_of(s) == STALE and "received_clouds" in values_of(s) and "no intraop data" in s.message
    ]
    return found[-1] if found else None


def first_status(g, since, level):
    found = [
        t
        for s, t in g.probe.diagnostics(since, DIAG_NAME)
        if level_of(s) == level and "received_clouds" in values_of(s)
    ]
    return found[0] if found else None


def test_loader_restart_reuses_the_model_and_node_restart_registers_again(tmp_path, graph):
    first = graph.send_model(BAG_A)
    assert level_of(first) == OK
    # the loader restarted: the same model again is recognised by its content, nothing is recomputed
    again = graph.send_model(BAG_A)
    assert level_of(again) == OK and "unchanged" in again.message, again.message
    since = graph.mark()
    graph.send_frame(BAG_A)
    assert graph.wait_attempts(since)[-1] and registrations(graph, since)[-1]["model_cache_computed"] == "none"
    # register_node killed while clouds flow, started again: it gets the latched model and registers the next cloud
    stop = threading.Event()

    def stream():
        while not stop.is_set():
            graph.send_frame(BAG_A, 2)
            time.sleep(0.2)

    feeder = threading.Thread(target=stream, daemon=True)
    feeder.start()
    try:
        graph.node.proc.send_signal(signal.SIGKILL)
        graph.node.wait(10)
        restarted = NodeProcess("register_node", {}, env=None, log_dir=tmp_path, name="register_node_again")
        replaced = Graph(restarted, graph.probe)
        since = replaced.mark()
        ok = graph.probe.wait_for(lambda: [r for r in registrations(replaced, since) if r["level"] == OK], 120)
        assert ok, restarted.stderr()[-3000:]
        # clouds that beat the latched model to the new process are refused with one line each, nothing worse
        bad = [line for line in clean_stderr(restarted.stderr()) if "before any preop model" not in line]
        assert bad == []
    finally:
        stop.set()
        feeder.join(5)
        restarted.stop()


def test_reliable_and_best_effort_publishers_and_an_incompatible_one_reported(graph):
    graph.send_model(BAG_B)
    raw = bag_raw(BAG_B)[TOPIC_INTRAOP][0]
    node = graph.probe.node
    reliable = node.create_publisher(
        PointCloud2, TOPIC_INTRAOP, QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
    )
    best_effort = node.create_publisher(
        PointCloud2, TOPIC_INTRAOP, QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
    )
    for publisher in (reliable, best_effort):
        assert graph.probe.wait_for(lambda p=publisher: p.get_subscription_count() > 0, 20)
        poses = graph.probe.count(TOPIC_POSE)
        # streamed as a camera does: one best-effort sample of a 300 kB cloud may be lost on a busy machine
        end = time.monotonic() + 60
        while graph.probe.count(TOPIC_POSE) <= poses and time.monotonic() < end:
            publisher.publish(raw)
            graph.probe.wait_for(lambda n=poses: graph.probe.count(TOPIC_POSE) > n, 1.0)
        assert graph.probe.count(TOPIC_POSE) > poses, publisher.qos_profile.reliability
    # /preop/points is latched (reliable, transient local): a volatile publisher can never reach it; said once
    since = graph.mark()
    volatile = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
    wrong = node.create_publisher(PointCloud2, TOPIC_PREOP, volatile)
    warned = graph.probe.wait_for(lambda: incompatible(graph, since), 20)
    assert warned and level_of(warned[0]) == WARN and "durability" in warned[0].message, warned
    time.sleep(1.5)
    assert len(incompatible(graph, since)) == 1
    node.destroy_publisher(wrong)


def incompatible(graph, since):
    return [s for s, _ in graph.probe.diagnostics(since, DIAG_NAME) if "incompatible QoS" in s.message]


def test_parameter_sets_flooding_during_registrations(graph):
    graph.send_model(BAG_B)
    stop = threading.Event()
    answers = []

    def flood():
        rate = 1.0
        while not stop.is_set():
            rate = 3.0 if rate == 1.0 else 1.0
            answers.append(("ok", graph.probe.set_parameters_atomically({"max_rate_hz": rate, "k": 3}).successful))
            answers.append(("bad", graph.probe.set_parameters_atomically({"max_rate_hz": 2.5, "k": -1}).successful))

    flooder = threading.Thread(target=flood, daemon=True)
    flooder.start()
    since = graph.mark()
    try:
        for index in range(3):
            graph.send_frame(BAG_B, index, fiducials=False)
            time.sleep(0.6)
        assert graph.wait_attempts(since, 1, 60)
    finally:
        stop.set()
        flooder.join(30)
    assert not flooder.is_alive(), "a parameter set never returned: deadlock"
    assert {ok for kind, ok in answers if kind == "ok"} == {True} and {ok for kind, ok in answers if kind == "bad"} == {
        False
    }
    values = graph.probe.get_parameters(["max_rate_hz", "k"])
    assert values[1] == 3 and values[0] in (1.0, 3.0)  # all or nothing: the bad sets changed neither
    assert graph.probe.reregister(timeout_s=60).success
    assert all(r["level"] != ERROR for r in registrations(graph, since))
    assert np.isfinite([float(r["residual_mm"]) for r in registrations(graph, since)]).all()
