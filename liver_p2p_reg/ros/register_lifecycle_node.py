"""rclpy adapter: register_node as a managed (lifecycle) node, for a supervisor that brings a robot up in order."""

from __future__ import annotations

from typing import Any

from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn

from liver_p2p_reg.errors import LiverP2PError
from liver_p2p_reg.ros.managed import ManagedNode
from liver_p2p_reg.ros.node_main import run_node
from liver_p2p_reg.ros.register_node import RegisterWiring


class ManagedRegisterNode(RegisterWiring, ManagedNode):
    """register_node under the ROS 2 node lifecycle (same name, topics, parameters and services once active).

    unconfigured -> configure: parameters read and checked, the method's weights loaded, `/preop/*`
    subscribed (a model arriving now is warmed up at once), publishers created -> inactive ->
    activate: `/intraop/*` subscribed, `~/reregister`, `~/reset_survey` served and the status timer live ->
    active -> deactivate: those removed, nothing published, model and pose state kept -> inactive ->
    cleanup: everything released -> unconfigured. shutdown from any state releases everything.
    The two services exist in every state (outside active they answer `not active`): a request waiting on the
    worker is answered whatever transition comes meanwhile.
    """

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("register_node", **node_kwargs)
        self._declare()

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._bring_up(preload_now=True)
        except LiverP2PError as exc:  # bad parameters: the transition fails with the reason, the node stays up
            self.get_logger().error(f"configure failed: {exc}")
            self._tear_down()
            return TransitionCallbackReturn.FAILURE
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._go_live()
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._go_quiet()
        self.get_logger().info("register_node inactive: no output; model and state kept")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._tear_down()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._tear_down()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._tear_down()  # back to unconfigured, nothing held
        return TransitionCallbackReturn.SUCCESS

    def destroy_node(self) -> None:
        self._tear_down()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """`ros2 run liver_p2p_reg register_lifecycle_node`: starts unconfigured; exits the process."""
    return run_node(ManagedRegisterNode, "register_node", args, exit_process=True)


if __name__ == "__main__":
    raise SystemExit(main())
