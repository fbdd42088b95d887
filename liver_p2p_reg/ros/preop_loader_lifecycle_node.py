"""rclpy adapter: preop_loader_node as a managed (lifecycle) node: configure loads the files, activate publishes."""

from __future__ import annotations

from typing import Any

from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn

from liver_p2p_reg.errors import LiverP2PError
from liver_p2p_reg.ros.managed import ManagedNode
from liver_p2p_reg.ros.node_main import run_node
from liver_p2p_reg.ros.preop_loader_node import PreopLoaderWiring


class ManagedPreopLoaderNode(PreopLoaderWiring, ManagedNode):
    """preop_loader_node under the ROS 2 node lifecycle: configure reads model_path (a missing or unreadable
    file fails the transition with the reason; the node stays up to be configured again; a bad structure file
    does not: it is an ERROR on /diagnostics once active), activate publishes the model and its structures
    latched and starts the status on /diagnostics, deactivate withdraws them, cleanup forgets the model."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("preop_loader_node", **node_kwargs)
        self._declare()

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._load()
        except LiverP2PError as exc:
            self.get_logger().error(f"configure failed: {exc}")
            return TransitionCallbackReturn.FAILURE
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._publish_model()
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._unpublish()
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._unpublish()
        self.loaded = None
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self.on_cleanup(state)


def main(args: list[str] | None = None) -> int:
    """`ros2 run liver_p2p_reg preop_loader_lifecycle_node`: starts unconfigured; exits the process."""
    return run_node(ManagedPreopLoaderNode, "preop_loader_node", args, exit_process=True)


if __name__ == "__main__":
    raise SystemExit(main())
