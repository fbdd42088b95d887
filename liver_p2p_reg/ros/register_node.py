"""rclpy adapter: the register_node wiring topics, parameters, QoS, the ~/reregister service and tf to NodeCore."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TransformStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.service import Service
from rclpy.subscription import Subscription
from rclpy.task import Future
from rclpy.timer import Timer
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker

from liver_p2p_reg.config import Config
from liver_p2p_reg.ros import openmp_wait_warning
from liver_p2p_reg.ros.messages import (
    feed_intraop_fiducials_msg,
    feed_intraop_msg,
    feed_preop_fiducials_msg,
    feed_preop_mesh_msg,
    feed_preop_msg,
    feed_structure_labels_msg,
    feed_structures_msg,
)
from liver_p2p_reg.ros.node_main import RclpyLogHandler, declare_from, read_from, run_node
from liver_p2p_reg.ros.node_settings import refuse_unusable
from liver_p2p_reg.ros.pointcloud2 import stamp_to_ns
from liver_p2p_reg.ros.rclpy_types import RCLPY_TYPES  # noqa: F401  (also imported from here: tests, scripts)
from liver_p2p_reg.ros.register_outputs import RegisterOutputs
from liver_p2p_reg.ros.topics import (
    TOPIC_DEFORMED_PREOP,
    TOPIC_DIAGNOSTICS,
    TOPIC_INTRAOP,
    TOPIC_INTRAOP_FIDUCIALS,
    TOPIC_POSE,
    TOPIC_PREOP,
    TOPIC_PREOP_FIDUCIALS,
    TOPIC_PREOP_MESH,
    TOPIC_PREOP_STRUCTURES,
    TOPIC_REGISTERED,
    TOPIC_STRUCTURE_LABELS,
    TOPIC_STRUCTURES,
    TOPIC_TRANSFORM,
    rclpy_qos,
)
from liver_p2p_reg.stream.core import NodeCore
from liver_p2p_reg.stream.health import StreamHealth
from liver_p2p_reg.stream.outputs import DIAG_NAME, ERROR, OK, WARN, Diagnostic
from liver_p2p_reg.stream.worker import Worker, current_worker

DIAGNOSTICS_PERIOD_S = 1.0
JOIN_ON_EXIT_S = 0.2  # a registration still running at shutdown is abandoned after this
REPLACE_WAIT_S = 10.0  # configure waits this long for a worker abandoned at cleanup to finish its registration
REPEAT_QUIET_S = 5.0  # the same intraop problem (no model yet, ...) is logged once per this, not once per cloud


class RegisterWiring(RegisterOutputs):
    """register_node's wiring in the phases of a managed node (mixed into an rclpy Node or LifecycleNode).

    Callbacks only hand work over; one worker thread does every heavy step (start-up preload,
    a new model's warm-up, registrations, service requests), woken by events, never polling.
    `_bring_up` (configure): parameters, the method's weights, the `/preop/*` subscriptions, the
    publishers and the worker; `_go_live` (activate): the `/intraop/*` subscriptions and the status timer, the
    services served (they live as long as the node); `_go_quiet` (deactivate): those removed, no output, state kept;
    `_tear_down` (cleanup, shutdown): everything released. The plain node does the first two at once.
    """

    def _declare(self: Any) -> None:
        self.declared = declare_from(self, Config, lambda f: f"{f.name} ({f.type}); see msg_docs/")
        self.core: NodeCore | None = None
        self._live: list[Any] = []  # what _go_live made and _go_quiet destroys
        self._intraop_sub: Any = None  # /intraop/points' subscription while live (its matched publishers are counted)
        self._kept: list[Any] = []  # what _bring_up made and _tear_down destroys
        self.active = False
        self._worker: Worker | None = None
        self._pending: set[Future] = set()  # requests handed to the worker and not answered yet
        self._intake_said: tuple[str, float] = ("", 0.0)  # the last intraop problem logged, and when
        # The services live as long as the node: a request waiting on the worker when the node is deactivated or
        # cleaned up is answered through them (a destroyed service crashed the process then); outside `active`
        # they answer at once that the node is inactive. In a group of their own: while one waits for the worker,
        # the default group's callbacks (topics, parameters, status) run.
        self._service_group = MutuallyExclusiveCallbackGroup()  # not `_services`: rclpy's Node has a list so named
        for name, callback in (("~/reregister", self._on_reregister), ("~/reset_survey", self._on_reset_survey)):
            self.create_service(Trigger, name, callback, callback_group=self._service_group)

    @property
    def _stopping(self: Any) -> bool:
        """No output (from this thread): the worker is stopped or was never started, or this is a worker abandoned
        at cleanup, whose late result belongs to no configuration now."""
        here = current_worker()
        return self._worker is None or self._worker.stopping or (here is not None and here is not self._worker)

    def _bring_up(self: Any, preload_now: bool = False) -> None:
        from liver_p2p_reg.bags.recorder import recorder_factory  # the flight recorder (record_path)

        config = read_from(self, Config, self.declared)
        refuse_unusable(config)  # configure fails with the reason, not every frame after it
        self.core = NodeCore(config, recorder_factory=recorder_factory())
        self._accepted = self.core.config  # the configuration the parameter sets so far describe
        self.health = StreamHealth()
        self._status_level: int | None = None  # the last status level published (a change is published at once)
        self._log_handler = RclpyLogHandler(self._log)  # the package's `logging` records, to /rosout
        logging.getLogger("liver_p2p_reg").addHandler(self._log_handler)
        if self._worker is not None:  # one abandoned in a registration at cleanup: let it end before another starts
            self._worker.join(REPLACE_WAIT_S)
        core = self.core  # the worker's own: one abandoned at cleanup never publishes for the next configuration
        self._worker = Worker(lambda: self._process_pending(core), core.next_due_s, self._worker_error)
        self.add_on_set_parameters_callback(self._on_parameters)  # first: _tear_down removes it if the preload fails
        if preload_now:  # configure: the weights are loaded when the transition returns
            self._preload()
        else:
            self._worker.submit(self._preload)
        self.pose_pub = self.create_publisher(PoseStamped, TOPIC_POSE, rclpy_qos(TOPIC_POSE))
        self.transform_pub = self.create_publisher(TransformStamped, TOPIC_TRANSFORM, rclpy_qos(TOPIC_TRANSFORM))
        self.cloud_pub = self.create_publisher(PointCloud2, TOPIC_REGISTERED, rclpy_qos(TOPIC_REGISTERED))
        self.structures_pub = self.create_publisher(PointCloud2, TOPIC_STRUCTURES, rclpy_qos(TOPIC_STRUCTURES))
        self.deformed_pub = self.create_publisher(PointCloud2, TOPIC_DEFORMED_PREOP, rclpy_qos(TOPIC_DEFORMED_PREOP))
        self.diag_pub = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, rclpy_qos(TOPIC_DIAGNOSTICS))
        self._kept = [self.pose_pub, self.transform_pub, self.cloud_pub, self.structures_pub, self.deformed_pub]
        self._kept.append(self.diag_pub)
        self._kept.append(self._subscribe(TOPIC_PREOP, self._on_preop))
        self._kept.append(self._subscribe(TOPIC_PREOP_MESH, self._on_mesh, Marker))  # the non-rigid stage's surface
        self._kept.append(self._subscribe(TOPIC_PREOP_FIDUCIALS, self._on_preop_fiducials))
        # the structures: moved with every pose (stream/structures.py says which set is kept)
        on_labels = lambda msg: self._report_any(feed_structure_labels_msg(self.core, msg.data))  # noqa: E731
        self._kept.append(self._subscribe(TOPIC_PREOP_STRUCTURES, self._on_structures))
        self._kept.append(self._subscribe(TOPIC_STRUCTURE_LABELS, on_labels, String))
        self.tf_broadcaster = None
        try:  # /tf is optional: tf2_ros has no PyPI wheel, so pip-only installs lack it
            from tf2_ros import TransformBroadcaster

            self.tf_broadcaster = TransformBroadcaster(self)
        except ImportError:
            self.get_logger().info("tf2_ros not importable: publishing /registration/transform only, no /tf")
        if (spinning := openmp_wait_warning()) is not None:
            self.get_logger().warning(spinning)
        self._worker.start()

    def _go_live(self: Any) -> None:
        # fiducials before points: when both are waiting, a cloud's own fiducials are taken first
        fiducials = self._subscribe(TOPIC_INTRAOP_FIDUCIALS, self._on_intraop_fiducials)
        self._intraop_sub = self._subscribe(TOPIC_INTRAOP, self._on_intraop)
        self._live = [
            fiducials,
            self._intraop_sub,
            # on the steady clock: with use_sim_time a ROS-time timer stops while a looped bag's /clock runs
            # back over time it has already passed
            self.create_timer(
                DIAGNOSTICS_PERIOD_S, self._publish_status, clock=Clock(clock_type=ClockType.STEADY_TIME)
            ),
        ]
        self.active = True
        cfg = self.core.config
        self.get_logger().info(
            f"register_node ready: method={cfg.method} mode={cfg.mode} max_rate_hz={cfg.max_rate_hz}"
        )

    def _go_quiet(self: Any) -> None:
        self.active = False
        for entity in self._live:
            self._destroy(entity)
        self._live, self._intraop_sub = [], None

    def _tear_down(self: Any) -> None:
        self._go_quiet()
        if self.core is None:
            return
        self.stop()
        self.remove_on_set_parameters_callback(self._on_parameters)  # bound methods compare equal
        for entity in self._kept:
            self._destroy(entity)
        self._kept, self.core, self.tf_broadcaster = [], None, None

    def _subscribe(self: Any, topic: str, callback: Callable[[Any], None], msg_type: type = PointCloud2) -> Any:
        """A subscription that reports a publisher with incompatible QoS once, as a WARN diagnostic."""
        events = SubscriptionEventCallbacks(incompatible_qos=lambda info: self._incompatible(topic, info))
        return self.create_subscription(msg_type, topic, callback, rclpy_qos(topic), event_callbacks=events)

    def _incompatible(self: Any, topic: str, info: Any) -> None:
        if info.total_count_change <= 0:
            return
        policy = getattr(info.last_policy_kind, "name", str(info.last_policy_kind)).lower()
        text = f"a publisher of {topic} offers an incompatible QoS ({policy}): its messages never arrive; see msg_docs/"
        self._report([Diagnostic(WARN, DIAG_NAME, text, {"topic": topic, "policy": policy})])

    def _destroy(self: Any, entity: Any) -> None:
        kinds = (
            (Subscription, self.destroy_subscription),
            (Service, self.destroy_service),
            (Timer, self.destroy_timer),
            (Publisher, self.destroy_publisher),
        )
        for kind, destroy in kinds:
            if isinstance(entity, kind):
                destroy(entity)
                return

    # ---------------------------------------------------------------- callbacks (cheap, executor thread)
    def _on_preop(self, msg: PointCloud2) -> None:
        diag = feed_preop_msg(self.core, msg, warm_up=False)
        if diag.level == OK and diag.values.get("unchanged") != "true":  # reported once warmed up, with warm_up_ms
            self.get_logger().info(f"preop model of {diag.values['points']} points: warming up")
            self._submit(self._warm_up, key="warm_up")  # it warms the model current when it runs: one is enough
        else:
            self._report([diag])

    def _on_mesh(self, msg: Marker) -> None:
        diag = feed_preop_mesh_msg(self.core, msg)  # ERROR for a malformed marker (ignored); else kept for its model
        self._report([diag])
        # a mesh of the current model: its elastic model is built again (deform on); a next model's waits for it
        if diag.level == OK and diag.values.get("for_current_model") == "true":
            self._submit(lambda: self._report_any(self.core.prepare_deformation()), key="prepare")

    def _on_preop_fiducials(self, msg: PointCloud2) -> None:
        self._report_any(feed_preop_fiducials_msg(self.core, msg))

    def _on_structures(self, msg: PointCloud2) -> None:
        self._report_any(feed_structures_msg(self.core, msg))
        self.get_logger().info(f"{len(self.core.structures.current())} structures ({msg.width * msg.height} points)")

    def _on_intraop_fiducials(self, msg: PointCloud2) -> None:
        self._report_any(feed_intraop_fiducials_msg(self.core, msg))
        self._submit()  # a cloud may be waiting for exactly these

    def _on_intraop(self, msg: PointCloud2) -> None:
        now_s = time.monotonic()
        self.health.on_cloud(now_s, stamp_to_ns(msg.header.stamp), self._now_ns())
        self._publish_status_on_change()  # a silence ended: STALE no more
        diags = feed_intraop_msg(self.core, msg, now_s)  # O(1): decoding happens in the worker
        said, at_s = self._intake_said
        if diags and (diags[0].message != said or now_s - at_s >= REPEAT_QUIET_S):  # clouds at 20 kHz: not each
            self._intake_said = (diags[0].message, now_s)
            self._report(diags)
        self._submit()

    def _on_worker(self, name: str, work: Callable[[], Any]) -> Future:
        """A Future the worker completes with `work()`'s value, after any registration in progress; with the exception
        where `work` raised (reported as an ERROR): a request must be answered whatever happens, or it waits forever."""
        done = Future(executor=self.executor)
        done.add_done_callback(self._pending.discard)  # also makes set_result wake the executor
        self._pending.add(done)

        def job() -> None:
            try:
                value = work()
            except Exception as exc:
                if not done.done():
                    done.set_result(exc)  # first: the request is answered whatever reporting does
                self._report([Diagnostic(ERROR, DIAG_NAME, f"{name} failed: {type(exc).__name__}: {exc}", {})])
                return
            if not done.done():  # stop() may have answered it already
                done.set_result(value)

        if not self._submit(job):  # the worker stopped meanwhile (a transition on another thread): answered now
            done.set_result(RuntimeError("register_node stopped before the request ran"))
        return done

    def _reregister_now(self) -> Any:
        output = self.core.reregister(time.monotonic(), on_pose=self._publish_pose)
        self._publish(output)
        return output

    def _inactive(self: Any, response: Trigger.Response) -> bool:
        """True (and `response` filled in) when a service is called outside the active state."""
        if self.active and self.core is not None:
            return False
        response.success, response.message = False, "register_node is not active (lifecycle): activate it first"
        return True

    async def _on_reregister(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        # The registration runs on the worker; this coroutine waits without holding a thread (its own callback group:
        # the node's topics, parameters and status are served meanwhile).
        if self._inactive(response):
            return response
        output = await self._on_worker("reregister", self._reregister_now)
        failed = isinstance(output, Exception)
        response.success = not failed and output.pose is not None
        response.message = f"reregister failed: {type(output).__name__}: {output}" if failed else output.summary
        return response

    async def _on_reset_survey(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        # On the worker, after any registration in progress; this coroutine waits without a thread.
        if self._inactive(response):
            return response
        core = self.core
        message = await self._on_worker("reset_survey", core.reset_survey)
        response.success = not isinstance(message, Exception)
        response.message = str(message) if response.success else f"reset_survey failed: {message}"
        self.get_logger().info(response.message)
        return response

    def _on_parameters(self, params: list[Any]) -> SetParametersResult:
        known = {f.name for f in dataclasses.fields(Config)}
        changes = {p.name: p.value for p in params if p.name in known}  # rclpy handles its own (use_sim_time)
        if not changes:
            return SetParametersResult(successful=True)
        try:  # validate now (against earlier sets not yet applied), so the answer carries the reason ...
            config = self._accepted.replace(**changes)
            refuse_unusable(config, self._accepted)
        except Exception as exc:  # a parameter must never take the node down: refused, with why
            return SetParametersResult(successful=False, reason=f"{str(exc) or type(exc).__name__}"[:500])
        # ... and apply on the worker, between registrations, without blocking this callback
        self._accepted = config
        self._submit(lambda: self._reconfigure(self._accepted), key="reconfigure")  # the latest: it holds all sets
        return SetParametersResult(successful=True)

    def _reconfigure(self, config: Config) -> None:
        self.core.reconfigure(config.to_dict())
        self._report_any(self.core.prepare_deformation())  # deform turned on, or its model's settings changed

    # ---------------------------------------------------------------- worker thread
    def _submit(self, job: Callable[[], None] | None = None, key: str | None = None) -> bool:
        """Hand `job` to the worker; False when it will never run (no worker, or a stopped one)."""
        return self._worker is not None and self._worker.submit(job, key)

    def _process_pending(self, core: NodeCore) -> None:
        current = lambda: core is self.core  # noqa: E731
        output = core.process_pending(time.monotonic(), on_pose=lambda o: self._publish_pose(o) if current() else None)
        if output is not None and current():
            self._publish(output)

    def _worker_error(self, exc: Exception) -> None:
        """Log an unexpected worker error and say it on /diagnostics (never raising: the worker must go on)."""
        text = f"registration worker: {type(exc).__name__}: {exc}"
        try:
            self._report([Diagnostic(ERROR, DIAG_NAME, text, {})])  # logged there too, at ERROR
        except Exception:
            self.get_logger().error(text)

    def _preload(self) -> None:
        ms = self.core.preload()
        self.get_logger().info(f"method {self.core.config.method} loaded in {ms:.0f} ms")

    def _warm_up(self) -> None:
        self._report([self.core.warm_up_model()])

    def stop(self) -> bool:
        """Stop the worker; False when a registration is still running (it is abandoned). Requests it had not
        answered are answered now, as failed: a request must never wait forever."""
        if self.core is None or self._worker is None:
            return True
        ended = self._worker.stop(JOIN_ON_EXIT_S)
        logging.getLogger("liver_p2p_reg").removeHandler(self._log_handler)
        try:
            for request in list(self._pending):
                try:  # an executor already shut down cannot schedule the answer: nobody waits for it then
                    if not request.done():
                        request.set_result(RuntimeError("register_node stopped before the request ran"))
                except Exception:
                    pass
        finally:
            self.core.close_recording()  # its file complete; a registration still running is not recorded
        return ended

    def destroy_node(self) -> None:
        self.stop()  # first: the worker must not publish through a destroyed node
        super().destroy_node()


class RegisterNode(RegisterWiring, Node):
    """Registers the preop model to each intraop cloud (per the mode) and publishes pose, tf, diagnostics."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("register_node", **node_kwargs)  # node_kwargs: e.g. parameter_overrides (tests)
        self._declare()
        self._bring_up()
        self._go_live()


def main(args: list[str] | None = None) -> int:
    """`ros2 run liver_p2p_reg register_node`; exits the process.

    SIGINT/SIGTERM end the node within JOIN_ON_EXIT_S even during a registration: the worker's
    unfinished result is dropped and the process leaves without waiting for it.
    """
    return run_node(RegisterNode, "register_node", args, exit_process=True)


if __name__ == "__main__":
    raise SystemExit(main())
