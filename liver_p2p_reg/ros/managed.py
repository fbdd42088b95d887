"""rclpy adapter: the base of the package's managed (lifecycle) nodes: a transition the state does not allow is refused."""

from __future__ import annotations

from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn


class ManagedNode(LifecycleNode):
    """A LifecycleNode whose ~/change_state refuses (success false, one WARN) a transition requested by id that the
    current state does not offer, as rclpy already does for one requested by label.

    Why: rclpy's handler lets rcl's "transition is not registered" error escape for an id (how supervisors such as
    nav2's lifecycle manager ask), which ended the process and left the request unanswered.
    """

    def _LifecycleNodeMixin__change_state(self, transition_id: int) -> TransitionCallbackReturn:  # rclpy's private hook
        offered = {t[0] for t in self._state_machine.available_transitions}
        if transition_id not in offered:
            state = self._state_machine.current_state[1]
            self.get_logger().warning(f"transition {transition_id} is not offered in state {state}: refused")
            return TransitionCallbackReturn.FAILURE
        return super()._LifecycleNodeMixin__change_state(transition_id)
