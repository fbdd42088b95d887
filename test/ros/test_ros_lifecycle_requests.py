"""register_node as a managed node in this process: a request waiting on the worker is answered through deactivate
and cleanup (a destroyed service crashed the process), one worker per configuration, configure checks settings."""

import threading
import time

import pytest
from conftest import require_rclpy

rclpy = require_rclpy()

from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.lifecycle import TransitionCallbackReturn  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from ros_support import stop_executor  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from liver_p2p_reg.ros.register_lifecycle_node import ManagedRegisterNode  # noqa: E402

SUCCESS = TransitionCallbackReturn.SUCCESS


@pytest.fixture
def graph():
    rclpy.init()
    node = ManagedRegisterNode(
        parameter_overrides=[Parameter("method", value="procrustes"), Parameter("mode", value="on_demand")]
    )
    helper = rclpy.create_node("lifecycle_request_helper")
    executor = MultiThreadedExecutor(num_threads=4)
    executor.add_node(node)
    executor.add_node(helper)
    try:
        yield node, helper, executor
    finally:
        stop_executor(executor)
        node.destroy_node()
        helper.destroy_node()
        rclpy.try_shutdown()


def spin_until(executor, condition, timeout_s=30.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not condition():
        executor.spin_once(timeout_sec=0.05)  # an exception in a callback (the old crash) is raised here
    return condition()


def workers() -> int:
    return sum(t.name == "registration" and t.is_alive() for t in threading.enumerate())


def test_a_waiting_request_is_answered_through_deactivate_and_cleanup(graph) -> None:
    node, helper, executor = graph
    client = helper.create_client(Trigger, "/register_node/reregister")
    assert client.wait_for_service(timeout_sec=10)  # the services live as long as the node
    answer = client.call_async(Trigger.Request())
    assert spin_until(executor, answer.done)
    assert not answer.result().success and "not active" in answer.result().message  # unconfigured: at once
    assert node.trigger_configure() == SUCCESS and node.trigger_activate() == SUCCESS

    def waiting_request() -> tuple:
        gate = threading.Event()
        node._submit(gate.wait)  # the worker busy, as in a model's warm-up
        future = client.call_async(Trigger.Request())
        assert spin_until(executor, lambda: len(node._pending) == 1), "the request never reached the worker"
        return gate, future

    gate, future = waiting_request()
    assert node.trigger_deactivate() == SUCCESS  # this crashed the process once the request was answered
    gate.set()
    assert spin_until(executor, future.done), "never answered after deactivate"
    assert not future.result().success and "no intraop cloud" in future.result().message  # it ran: no cloud yet
    assert node.trigger_activate() == SUCCESS
    gate, future = waiting_request()
    assert node.trigger_deactivate() == SUCCESS and node.trigger_cleanup() == SUCCESS
    assert spin_until(executor, future.done), "never answered after cleanup"
    assert not future.result().success and "stopped" in future.result().message
    gate.set()  # the abandoned worker ends; a new configuration has one worker, not two
    assert node.trigger_configure() == SUCCESS and node.trigger_activate() == SUCCESS
    assert spin_until(executor, lambda: workers() == 1, 10.0), workers()
    again = client.call_async(Trigger.Request())
    assert spin_until(executor, again.done) and "no intraop cloud" in again.result().message


def test_configure_refuses_settings_every_frame_would_fail_on(graph) -> None:
    node, _, _ = graph
    node.set_parameters([Parameter("error_coverage", value=0.5)])  # unconfigured: not checked when set
    assert node.trigger_configure() == TransitionCallbackReturn.FAILURE  # it configured, then failed every frame
    node.set_parameters([Parameter("error_coverage", value=0.9)])
    assert node.trigger_configure() == SUCCESS


def test_destroying_the_node_with_a_request_waiting_raises_nothing(graph) -> None:
    """An executor shut down first (rclpy's usual order) could not schedule the failed answer: stop() raised, and
    the flight recording was left without its footer."""
    node, helper, executor = graph
    client = helper.create_client(Trigger, "/register_node/reregister")
    assert node.trigger_configure() == SUCCESS and node.trigger_activate() == SUCCESS
    gate = threading.Event()
    node._submit(gate.wait)
    client.call_async(Trigger.Request())
    assert spin_until(executor, lambda: len(node._pending) == 1)
    stop_executor(executor)
    try:
        node.stop()  # what destroy_node does first
    finally:
        gate.set()
    assert not node._submit(lambda: None)  # stopped: a late request would be answered at once, never left waiting
