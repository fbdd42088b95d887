"""The rclpy `~/reset_survey` service of register_node (survey mode), through a real service call."""

import random
import time

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from ros_support import stop_executor  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from liver_p2p_reg.ros.register_node import RegisterNode  # noqa: E402


@pytest.fixture
def ros_context(monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", str(random.randint(1, 200)))  # isolated from other test runs
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    rclpy.init()
    yield
    rclpy.try_shutdown()


def test_reset_survey_service_answers(ros_context):
    node = RegisterNode(parameter_overrides=[Parameter("mode", value="survey")])
    helper = rclpy.create_node("test_reset_survey_helper")
    executor = MultiThreadedExecutor(num_threads=2)
    executor.add_node(node)
    executor.add_node(helper)
    try:
        client = helper.create_client(Trigger, "/register_node/reset_survey")
        assert client.wait_for_service(timeout_sec=10)
        future = client.call_async(Trigger.Request())
        end = time.monotonic() + 20
        while not future.done() and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        assert future.done() and future.result().success
        assert future.result().message.startswith("survey reset: nothing fused yet")
    finally:
        stop_executor(executor)
        node.destroy_node()
        helper.destroy_node()
