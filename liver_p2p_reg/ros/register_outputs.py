"""register_node's outputs (a mixin of RegisterWiring): the rigid pose at once, then the non-rigid stage's surface, the structures and the diagnostics."""

from __future__ import annotations

import logging
import time
from typing import Any

from liver_p2p_reg.ros.messages import diagnostic_array, pose_stamped, registered_structures_cloud, transform_stamped
from liver_p2p_reg.ros.node_main import log_at
from liver_p2p_reg.ros.pointcloud2 import M_PER_MM, points_to_cloud
from liver_p2p_reg.ros.rclpy_types import RCLPY_TYPES
from liver_p2p_reg.stream.health import stale_when_silent
from liver_p2p_reg.stream.outputs import ERROR, OK, WARN, CoreOutput, Diagnostic


class RegisterOutputs:
    """What register_node publishes, through the publishers `RegisterWiring._bring_up` made.

    A registration goes out in two steps: `_publish_pose` the moment the rigid pose is known (NodeCore's
    `on_pose`: pose, transform, /tf, the registered preop cloud), then `_publish` once the frame is done
    (after the non-rigid stage when `deform` is on): the deformed preop surface when the stage was applied
    (the /preop/mesh's welded vertices when it ran on that mesh, else the /preop/points), the structures
    (deformed when it was applied) and the diagnostics.
    """

    def _publish_pose(self: Any, output: CoreOutput) -> None:
        if self._stopping or not self.active or output.pose is None:  # inactive (managed node): no output
            return
        self.pose_pub.publish(pose_stamped(output.pose, RCLPY_TYPES))
        transform = transform_stamped(output.pose, RCLPY_TYPES)
        self.transform_pub.publish(transform)
        if self.tf_broadcaster is not None:
            self.tf_broadcaster.sendTransform(transform)
        self.cloud_pub.publish(self._sensor_cloud(output, output.registered_preop_mm))

    def _publish(self: Any, output: CoreOutput) -> None:
        if self._stopping or not self.active:  # inactive (managed node): no output, the state is kept
            return
        stamp_ns = output.pose.stamp_ns if output.pose is not None else self._now_ns()
        if output.pose is not None:
            if output.deformed_preop_mm is not None:  # only when the non-rigid stage was applied
                self.deformed_pub.publish(self._sensor_cloud(output, output.deformed_preop_mm))
            structures = registered_structures_cloud(
                output.structures, RCLPY_TYPES.cloud, output.pose.frame_id, stamp_ns
            )
            self.structures_pub.publish(structures)  # with every pose (empty without structures)
        self._report(output.diagnostics, stamp_ns)
        self._publish_status_on_change()

    def _sensor_cloud(self: Any, output: CoreOutput, points_mm: Any) -> Any:
        """A cloud of the pose's sensor frame and stamp (metres, float32)."""
        frame_id, stamp_ns = output.pose.frame_id, output.pose.stamp_ns
        return points_to_cloud(points_mm * M_PER_MM, RCLPY_TYPES.cloud, frame_id=frame_id, stamp_ns=stamp_ns)

    def _report(self: Any, diags: list[Diagnostic], stamp_ns: int | None = None) -> None:
        """Log each diagnostic at its own severity and publish them on /diagnostics."""
        severity = {OK: logging.INFO, WARN: logging.WARNING, ERROR: logging.ERROR}
        for diag in diags:
            self._log(severity.get(diag.level, logging.WARNING), f"{diag.level_name}: {diag.message}")
        if not self._stopping and self.active:
            self.diag_pub.publish(
                diagnostic_array(diags, self._now_ns() if stamp_ns is None else stamp_ns, RCLPY_TYPES)
            )

    def _report_any(self: Any, diag: Diagnostic | None) -> None:
        if diag is not None:
            self._report([diag])

    def _publish_status(self: Any) -> None:
        """The periodic status (registration, then the intraop stream), as diagnostic_updater publishes it."""
        now_s, core = time.monotonic(), self.core
        if core is None or not self.active:
            return
        status = self._effective_status(now_s)
        self._status_level = status.level
        stream = self.health.status(now_s, core.config.stale_after_s, self._matched_intraop_publishers())
        self.diag_pub.publish(diagnostic_array([status, stream], self._now_ns(), RCLPY_TYPES))

    def _matched_intraop_publishers(self: Any) -> int | None:
        """How many publishers the middleware has matched to /intraop/points' subscription; None without one."""
        sub = self._intraop_sub  # one read: a deactivation on the executor's thread may destroy it meanwhile
        if sub is None:
            return None
        try:
            return sub.get_publisher_count()
        except Exception:  # destroyed between the read and the call (the worker publishes a status too)
            return None

    def _publish_status_on_change(self: Any) -> None:
        """A level change is published at once, not at the next period (diagnostic_updater's force_update):
        a registration's new level, or the end of a silence (STALE -> the last result's level) on a cloud."""
        core = self.core
        if core is None or not self.active:
            return
        if self._effective_status(time.monotonic()).level != self._status_level:
            self._publish_status()

    def _effective_status(self: Any, now_s: float) -> Diagnostic:
        """The registration status as published: STALE after stale_after_s without a cloud."""
        return stale_when_silent(self.core.status(), self.health.silent_for_s(now_s), self.core.config.stale_after_s)

    def _log(self: Any, level: int, text: str) -> None:
        log_at(self.get_logger(), level, text)

    def _now_ns(self: Any) -> int:
        return self.get_clock().now().nanoseconds
