"""register_node and preop_loader_node as managed nodes: every transition through the lifecycle services, real processes."""

import signal

import pytest
from conftest import require_rclpy

rclpy = require_rclpy()

from lifecycle_msgs.msg import State, Transition  # noqa: E402
from lifecycle_msgs.srv import ChangeState, GetState  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from ros_support import BAG_A, Graph, bag_frames_m  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402

from liver_p2p_reg.livegraph.graph import GraphProbe, NodeProcess, set_isolated_environment  # noqa: E402
from liver_p2p_reg.ply_pcd import write_ply  # noqa: E402
from liver_p2p_reg.ros.topics import TOPIC_INTRAOP, TOPIC_POSE, TOPIC_PREOP  # noqa: E402


def change(probe, node, transition):
    answer = probe.call(ChangeState, f"/{node}/change_state", ChangeState.Request(transition=Transition(id=transition)))
    assert answer is not None, f"{node}: no answer to transition {transition}"
    return answer.success


def state(probe, node):
    return probe.call(GetState, f"/{node}/get_state", GetState.Request()).current_state.id


def subscribers(probe, topic):
    return probe.node.count_subscribers(topic)


@pytest.fixture
def managed(tmp_path):
    env = set_isolated_environment()
    node = NodeProcess("register_lifecycle_node", env=env, log_dir=tmp_path)
    probe = GraphProbe()
    yield Graph(node, probe)
    node.stop()
    probe.close()


def test_register_node_through_every_transition(managed):
    graph, probe = managed, managed.probe
    assert probe.wait_for(lambda: state_or_none(probe) == State.PRIMARY_STATE_UNCONFIGURED, 90), graph.node.stderr()
    assert subscribers(probe, TOPIC_PREOP) == 0 and subscribers(probe, TOPIC_INTRAOP) == 0
    # a transition the state does not offer, asked by id (as nav2's lifecycle manager asks): refused, not fatal
    assert not change(probe, "register_node", Transition.TRANSITION_ACTIVATE)
    assert state(probe, "register_node") == State.PRIMARY_STATE_UNCONFIGURED and graph.node.alive()
    # a bad parameter is only checked at configure: the transition fails, the node stays up and unconfigured
    graph.set(method="no-such-method")
    assert not change(probe, "register_node", Transition.TRANSITION_CONFIGURE)
    assert state(probe, "register_node") == State.PRIMARY_STATE_UNCONFIGURED and graph.node.alive()
    graph.set(method="learned-p2p-icp")
    assert change(probe, "register_node", Transition.TRANSITION_CONFIGURE)  # weights loaded when this returns
    assert "loaded in" in graph.node.stderr()
    assert state(probe, "register_node") == State.PRIMARY_STATE_INACTIVE
    assert probe.wait_for(lambda: subscribers(probe, TOPIC_PREOP) == 1, 20)
    assert subscribers(probe, TOPIC_INTRAOP) == 0  # inactive: no intraop input
    probe.publish(TOPIC_PREOP, bag_raw_preop())
    assert probe.wait_for(lambda: "warming up" in graph.node.stderr(), 30)
    assert change(probe, "register_node", Transition.TRANSITION_ACTIVATE)
    assert probe.wait_for(lambda: subscribers(probe, TOPIC_INTRAOP) == 1, 20)
    poses = probe.count(TOPIC_POSE)
    graph.send_frame(BAG_A)
    assert probe.wait_for(lambda: probe.count(TOPIC_POSE) > poses, 60), graph.node.stderr()
    # deactivate: the intraop input goes, nothing is published, the model stays
    assert change(probe, "register_node", Transition.TRANSITION_DEACTIVATE)
    assert state(probe, "register_node") == State.PRIMARY_STATE_INACTIVE
    assert probe.wait_for(lambda: subscribers(probe, TOPIC_INTRAOP) == 0, 20)
    diagnostics = probe.count("/diagnostics")
    graph.send_frame(BAG_A)
    assert not probe.wait_for(lambda: probe.count("/diagnostics") > diagnostics, 2.5)  # not even the status
    assert change(probe, "register_node", Transition.TRANSITION_ACTIVATE)
    assert probe.wait_for(lambda: subscribers(probe, TOPIC_INTRAOP) == 1, 20)
    poses = probe.count(TOPIC_POSE)
    graph.send_frame(BAG_A, 1)  # registered against the model received while inactive: it was kept
    assert probe.wait_for(lambda: probe.count(TOPIC_POSE) > poses, 60), graph.node.stderr()
    # cleanup releases everything; shutdown ends in finalized with the process still answering
    assert change(probe, "register_node", Transition.TRANSITION_DEACTIVATE)
    assert change(probe, "register_node", Transition.TRANSITION_CLEANUP), graph.node.stderr()[-3000:]
    assert state(probe, "register_node") == State.PRIMARY_STATE_UNCONFIGURED
    assert probe.wait_for(lambda: subscribers(probe, TOPIC_PREOP) == 0, 20)
    assert change(probe, "register_node", Transition.TRANSITION_UNCONFIGURED_SHUTDOWN)
    assert state(probe, "register_node") == State.PRIMARY_STATE_FINALIZED
    # finalized: the process then exits on SIGINT; a loaded full suite has seen DDS shutdown take more than 10 s
    code, _ = graph.node.stop(signal.SIGINT, timeout_s=30.0)
    assert code == 0, graph.node.stderr()


def state_or_none(probe):
    answer = probe.call(GetState, "/register_node/get_state", GetState.Request(), timeout_s=5)
    return None if answer is None else answer.current_state.id


def bag_raw_preop():
    from ros_support import bag_raw

    return bag_raw(BAG_A)[TOPIC_PREOP][0]


def test_preop_loader_configure_loads_activate_publishes(tmp_path):
    preop_m, _ = bag_frames_m(BAG_A)
    model = tmp_path / "liver.ply"
    write_ply(model, preop_m * 1e3)
    env = set_isolated_environment()
    loader = NodeProcess(
        "preop_loader_lifecycle_node", {"model_path": str(tmp_path / "no.ply")}, env=env, log_dir=tmp_path
    )
    probe = GraphProbe(target="preop_loader_node")
    got = []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    probe.node.create_subscription(PointCloud2, TOPIC_PREOP, got.append, latched)
    try:
        assert probe.wait_for(lambda: state_of(probe) == State.PRIMARY_STATE_UNCONFIGURED, 90), loader.stderr()
        # a missing file fails configure with the reason; the node stays up, unconfigured, to be configured again
        assert not change(probe, "preop_loader_node", Transition.TRANSITION_CONFIGURE)
        assert "model_path not found" in loader.stderr() and loader.alive()
        assert state_of(probe) == State.PRIMARY_STATE_UNCONFIGURED
        assert all(r.successful for r in probe.set_parameters({"model_path": str(model)}))
        assert change(probe, "preop_loader_node", Transition.TRANSITION_CONFIGURE)
        assert not probe.wait_for(lambda: got, 1.0)  # inactive: loaded, not published
        assert change(probe, "preop_loader_node", Transition.TRANSITION_ACTIVATE)
        assert probe.wait_for(lambda: got, 20) and loader_publishes(probe)
        assert got[0].width * got[0].height == len(preop_m)
        assert change(probe, "preop_loader_node", Transition.TRANSITION_DEACTIVATE)
        assert probe.wait_for(lambda: not loader_publishes(probe), 20)
        assert change(probe, "preop_loader_node", Transition.TRANSITION_CLEANUP)
        assert state_of(probe) == State.PRIMARY_STATE_UNCONFIGURED
    finally:
        # a loaded full suite has seen this node's DDS shutdown take more than the default 10 s
        code, _ = loader.stop(timeout_s=30.0)
        probe.close()
    assert code == 0, loader.stderr()


def loader_publishes(probe):
    return [i for i in probe.node.get_publishers_info_by_topic(TOPIC_PREOP) if i.node_name == "preop_loader_node"]


def state_of(probe):
    answer = probe.call(GetState, "/preop_loader_node/get_state", GetState.Request(), timeout_s=5)
    return None if answer is None else answer.current_state.id
