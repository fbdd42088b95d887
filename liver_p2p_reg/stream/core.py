"""ROS-free node logic: preop model, latest intraop cloud, modes, rate limit, outputs and diagnostics as plain data.

The rclpy register_node and bag replay drive this same object. Inputs are millimetre arrays
(or PointCloud2-like messages, decoded here with `pointcloud2`); outputs are `CoreOutput`s
holding a pose (T_sensor_ct, mm), the moved preop cloud (mm) and `Diagnostic`s.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from liver_p2p_reg.cloud_io import extent_mm, implausible_extent
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.registration.confidence import result_warnings
from liver_p2p_reg.registration.methods import check_method_name
from liver_p2p_reg.registration.preprocess import voxel_downsample
from liver_p2p_reg.registration.registrar import Registrar
from liver_p2p_reg.result import RegistrationResult
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm, stamp_to_ns
from liver_p2p_reg.stream.fiducials import FiducialStore
from liver_p2p_reg.stream.survey import Survey

LOG = logging.getLogger("liver_p2p_reg.node")

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR", STALE: "STALE"}
DIAG_NAME = "liver_p2p_reg: registration"
PREOP_DIAG_NAME = "liver_p2p_reg: preop model"
HARDWARE_ID = "liver_p2p_reg"
# A cloud arriving at exactly max_rate_hz is due although its arrival jitters this share of a period early.
RATE_TOLERANCE = 0.05
# While ground truth is expected, a cloud waits at most this long for its own same-stamp fiducials
# (published just before it, on another topic) so its TRE is not lost to delivery order. The wait
# counts from the first cloud the pending slot held: a newer cloud replacing it does not restart it
# (else a stream faster than 1 / FIDUCIAL_WAIT_S without fiducials was never registered).
FIDUCIAL_WAIT_S = 0.3


@dataclass
class Diagnostic:
    """diagnostic_msgs/DiagnosticStatus as plain data (values are strings, as on the wire)."""

    level: int
    name: str
    message: str
    values: dict[str, str] = field(default_factory=dict)
    hardware_id: str = HARDWARE_ID

    @property
    def level_name(self) -> str:
        return LEVEL_NAMES.get(self.level, str(self.level))


@dataclass
class PoseOutput:
    """Pose of the preop (`ct`) frame in the sensor frame: p_sensor = T_sensor_ct p_ct (mm)."""

    stamp_ns: int
    frame_id: str  # the sensor frame (parent)
    child_frame_id: str  # the preop frame, `ct`
    T_sensor_ct_mm: np.ndarray  # (4, 4)

    @property
    def translation_m(self) -> np.ndarray:
        return np.asarray(self.T_sensor_ct_mm)[:3, 3] * 1e-3

    @property
    def quaternion_xyzw(self) -> np.ndarray:
        return Rotation.from_matrix(np.asarray(self.T_sensor_ct_mm)[:3, :3]).as_quat()


@dataclass
class CoreOutput:
    """What one registration attempt produced; `pose is None` whenever the attempt failed."""

    diagnostics: list[Diagnostic]
    pose: PoseOutput | None = None
    registered_preop_mm: np.ndarray | None = None  # preop cloud moved into the sensor frame
    result: RegistrationResult | None = None
    reason: str = ""  # continuous | once | reregister

    @property
    def level(self) -> int:
        return max((d.level for d in self.diagnostics), default=OK)

    @property
    def summary(self) -> str:
        return "; ".join(d.message for d in self.diagnostics)


@dataclass
class _Cloud:
    """An intraop cloud as received (raw message or decoded mm points)."""

    frame_id: str
    stamp_ns: int
    msg: Any = None
    points_mm: np.ndarray | None = None
    n_raw: int = 0
    received_s: float | None = None  # arrival on the caller's clock (None: not given)
    waiting_since_s: float | None = None  # arrival of the first cloud in the pending slot (fiducial wait)


@dataclass
class _TrackState:
    """The last good pose, to start the next frame's ICP from (continuous mode)."""

    T_mm: np.ndarray  # T_sensor_ct of the last accepted registration
    reference_residual_mm: float  # residual of the last full (global) registration
    frame_id: str
    frames: int = 0  # tracked frames since that full registration


class NodeCore:
    """State machine of register_node; thread-safe (callbacks vs. one registration worker)."""

    def __init__(self, config: Config | None = None, registrar: Registrar | None = None) -> None:
        self.config = (config or Config()).validate()
        check_method_name(self.config.method)  # an unknown method is refused now, not with an ERROR per frame
        self.registrar = registrar or Registrar(self.config)
        self._lock = threading.Lock()  # guards the state below (cheap, callbacks)
        self._register_lock = threading.Lock()  # one registration at a time
        self.preop_mm: np.ndarray | None = None
        self.preop_frame = "ct"
        self.fiducials = FiducialStore()
        self._preop_scale_mm: float | None = None
        self._preop_problem = ""  # why the current model cannot be registered against (wrong units)
        self._pending: _Cloud | None = None
        self._latest: _Cloud | None = None
        # the rate limit counts from the arrival of the last registered cloud (its start time when
        # no arrival is known): counting from start times let waits creep up frame after frame
        self._rate_ref_s: float | None = None
        self._once_done = False
        self._track: _TrackState | None = None
        self._survey_state: Survey | None = None  # survey mode only
        self.last_output: CoreOutput | None = None
        self.received = 0
        self.processed = 0
        self.dropped = 0  # clouds superseded before they were registered (latest-only)

    # ---------------------------------------------------------------- inputs
    @property
    def preop_fiducials_mm(self) -> np.ndarray | None:
        """Fiducials of the current preop model (mm, preop frame), or None."""
        return self.fiducials.preop_mm

    def reconfigure(self, changes: dict[str, Any]) -> Config:
        """Apply parameter changes atomically (all valid or none; InputError says why).

        The Registrar's cache is kept: its entries are keyed by the source's content and the
        parameters they depend on, so only what a change invalidates is computed again.
        """
        config = self.config.replace(**changes)
        check_method_name(config.method)
        registrar = Registrar(config)
        registrar.cache = self.registrar.cache
        with self._register_lock:  # never swap under a running registration
            self.config, self.registrar = config, registrar
        return config

    def preload(self) -> float:
        """Import the method's modules, load its weights and run it once on a synthetic
        liver-sized surface, so a real model's warm-up only computes that model's share; ms."""
        start = time.perf_counter()
        d = np.random.default_rng(0).normal(size=(3000, 3))
        shell = d / np.linalg.norm(d, axis=1, keepdims=True) * [80.0, 55.0, 40.0]
        with self._register_lock:
            self.registrar.warm_up(shell)
        return (time.perf_counter() - start) * 1e3

    def set_preop(
        self, points_mm: np.ndarray, frame_id: str = "ct", stamp_ns: int = 0, *, warm_up: bool = True
    ) -> Diagnostic:
        """New preop model (mm, preop frame). Returns its diagnostic; bad models are rejected.

        warm_up=False leaves the model's warm-up to a later `warm_up_model()` call (the node
        runs it on its worker so callbacks stay fast).
        """
        points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        points = points[np.isfinite(points).all(axis=1)]
        if len(points) < self.config.min_points:
            return Diagnostic(
                ERROR,
                PREOP_DIAG_NAME,
                f"preop model has {len(points)} valid points (< {self.config.min_points}); ignored",
            )
        extent = extent_mm(points)
        unit_warning = self._units_warning(extent, "preop model")
        with self._lock:
            self.preop_mm = points
            self.preop_frame = frame_id or "ct"
            centre = points.mean(axis=0)
            self._preop_scale_mm = float(np.max(np.linalg.norm(points - centre, axis=1)))
            self._preop_problem = unit_warning
            self._once_done = False
            self._track = None  # a pose of another model is no prior
            self._survey_state = None  # nor is a surface fused against it
            self.fiducials.new_model(stamp_ns)
        values = {"points": str(len(points)), "extent_mm": f"{extent:.1f}", "frame_id": self.preop_frame}
        if unit_warning:
            return Diagnostic(WARN, PREOP_DIAG_NAME, unit_warning, values)
        if warm_up:
            return self.warm_up_model()
        return Diagnostic(OK, PREOP_DIAG_NAME, f"preop model received ({len(points)} points)", values)

    def warm_up_model(self) -> Diagnostic:
        """Do the current model's own share of the work (its features, ICP index, ...) now, once,
        instead of inside the first frame's latency; its diagnostic carries `warm_up_ms`."""
        with self._register_lock:
            points = self.preop_mm
            if points is None:
                return Diagnostic(ERROR, PREOP_DIAG_NAME, "no preop model to warm up")
            ms = self.registrar.warm_up(points)
        values = {
            "points": str(len(points)),
            "extent_mm": f"{extent_mm(points):.1f}",
            "frame_id": self.preop_frame,
            "warm_up_ms": f"{ms:.1f}",
        }
        return Diagnostic(OK, PREOP_DIAG_NAME, f"preop model received ({len(points)} points)", values)

    def set_preop_fiducials(self, points_mm: np.ndarray | None, stamp_ns: int | None = None) -> None:
        """Ordered fiducials inside the preop model stamped `stamp_ns` (None: the current model), mm."""
        self.fiducials.set_preop(points_mm, stamp_ns)

    def set_intraop_fiducials(self, points_mm: np.ndarray, stamp_ns: int) -> None:
        """Ground-truth fiducials in the sensor frame for the cloud with the same header stamp."""
        self.fiducials.set_intraop(points_mm, stamp_ns)

    def on_preop_msg(self, msg: Any, *, warm_up: bool = True) -> Diagnostic:
        """A /preop/points PointCloud2 (metres)."""
        try:
            points = cloud_to_points_mm(msg)
        except InputError as exc:
            return Diagnostic(ERROR, PREOP_DIAG_NAME, f"bad /preop/points: {exc}")
        return self.set_preop(points, msg.header.frame_id, stamp_to_ns(msg.header.stamp), warm_up=warm_up)

    def on_preop_fiducials_msg(self, msg: Any) -> Diagnostic | None:
        """A /preop/fiducials PointCloud2; a WARN diagnostic when it cannot be used."""
        try:
            self.set_preop_fiducials(cloud_to_points_mm(msg), stamp_to_ns(msg.header.stamp))
        except InputError as exc:
            return Diagnostic(WARN, PREOP_DIAG_NAME, f"ignoring bad /preop/fiducials: {exc}")
        return None

    def on_intraop_fiducials_msg(self, msg: Any) -> Diagnostic | None:
        """A /intraop/fiducials PointCloud2; a WARN diagnostic when it cannot be used."""
        try:
            self.set_intraop_fiducials(cloud_to_points_mm(msg), stamp_to_ns(msg.header.stamp))
        except InputError as exc:
            return Diagnostic(WARN, DIAG_NAME, f"ignoring bad /intraop/fiducials: {exc}")
        return None

    def on_intraop_msg(self, msg: Any, now_s: float | None = None) -> list[Diagnostic]:
        """A /intraop/points PointCloud2; O(1): decoding waits until the cloud is registered."""
        cloud = _Cloud(msg.header.frame_id, stamp_to_ns(msg.header.stamp), msg=msg, received_s=now_s)
        return self._receive(cloud)

    def on_intraop_points(
        self, points_mm: np.ndarray, frame_id: str, stamp_ns: int = 0, now_s: float | None = None
    ) -> list[Diagnostic]:
        """Plain-data variant of `on_intraop_msg` (mm, sensor frame)."""
        points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        return self._receive(_Cloud(frame_id, int(stamp_ns), points_mm=points, n_raw=len(points), received_s=now_s))

    def _receive(self, cloud: _Cloud) -> list[Diagnostic]:
        with self._lock:
            self.received += 1
            cloud.waiting_since_s = cloud.received_s
            if self._pending is not None:
                self.dropped += 1  # latest-only: the older cloud is never registered
                if cloud.received_s is not None and self._pending.waiting_since_s is not None:
                    cloud.waiting_since_s = min(cloud.received_s, self._pending.waiting_since_s)
            self._pending = cloud
            have_preop = self.preop_mm is not None
        if not have_preop:
            diag = Diagnostic(
                ERROR, DIAG_NAME, "intraop cloud received before any preop model (/preop/points); waiting"
            )
            self.last_output = CoreOutput([diag])
            return [diag]
        return []

    # ---------------------------------------------------------------- scheduling
    def next_due_s(self) -> float | None:
        """When the pending cloud becomes due (the caller's clock; -inf: now), None if it never will
        by itself (nothing pending, no model, on_demand, once already done)."""
        with self._lock:
            cloud = self._pending
            if cloud is None or self.preop_mm is None or self.config.mode == "on_demand":
                return None
            if self.config.mode == "once" and self._once_done:
                return None
            due_s = -np.inf
            if self.config.mode == "continuous" and self._rate_ref_s is not None:
                due_s = self._rate_ref_s + (1.0 - RATE_TOLERANCE) / self.config.max_rate_hz
        waiting_since_s = cloud.waiting_since_s
        if waiting_since_s is not None and self.fiducials.expected() and not self.fiducials.has_frame(cloud.stamp_ns):
            due_s = max(due_s, waiting_since_s + FIDUCIAL_WAIT_S)
        return due_s

    def due(self, now_s: float | None = None) -> bool:
        """Whether `process_pending` would register now (mode, rate limit, inputs present)."""
        now_s = time.monotonic() if now_s is None else now_s
        due_s = self.next_due_s()
        return due_s is not None and now_s >= due_s - 1e-9

    def process_pending(self, now_s: float | None = None) -> CoreOutput | None:
        """Register the latest pending cloud if due (continuous/once modes); else None."""
        now_s = time.monotonic() if now_s is None else now_s
        if not self.due(now_s):
            return None
        with self._lock:
            cloud, self._pending = self._pending, None
            if cloud is not None:
                self._rate_ref_s = now_s if cloud.received_s is None else cloud.received_s
        if cloud is None:
            return None
        output = self._register(cloud, self.config.mode)
        if self.config.mode == "once" and output.pose is not None:
            self._once_done = True
        return output

    def reregister(self, now_s: float | None = None) -> CoreOutput:
        """Register the latest intraop cloud now, whatever the mode (the ~/reregister service)."""
        with self._lock:
            cloud = self._pending or self._latest
            self._pending = None
            self._rate_ref_s = time.monotonic() if now_s is None else now_s
        if cloud is None:
            diag = Diagnostic(ERROR, DIAG_NAME, "no intraop cloud received yet (/intraop/points)")
            self.last_output = CoreOutput([diag], reason="reregister")
            return self.last_output
        return self._register(cloud, "reregister")

    def flush(self) -> CoreOutput | None:
        """Register a still-pending cloud ignoring the rate limit (end of a replayed bag)."""
        with self._lock:
            self._rate_ref_s = None
            if self._pending is not None:
                self._pending.received_s = None  # no fiducials are coming after the bag's end
                self._pending.waiting_since_s = None
        return self.process_pending(0.0)

    def status(self) -> Diagnostic:
        """The current diagnostic for periodic publishing (STALE before any attempt)."""
        last = self.last_output
        if last is None or not last.diagnostics:
            return Diagnostic(STALE, DIAG_NAME, "no registration yet", self._counters())
        diag = last.diagnostics[0]
        return Diagnostic(diag.level, diag.name, diag.message, {**diag.values, **self._counters()})

    # ---------------------------------------------------------------- registration
    def _register(self, cloud: _Cloud, reason: str) -> CoreOutput:
        with self._register_lock:
            output = self._register_locked(cloud, reason)
            self._remember_for_tracking(output, cloud.frame_id)
        self.last_output = output
        with self._lock:
            self.processed += 1
        return output

    def _register_locked(self, cloud: _Cloud, reason: str) -> CoreOutput:
        start = time.perf_counter()
        values: dict[str, str] = {"frame_id": cloud.frame_id, "stamp_ns": str(cloud.stamp_ns), "mode": self.config.mode}

        def fail(level: int, message: str) -> CoreOutput:
            return CoreOutput([Diagnostic(level, DIAG_NAME, message, values)], reason=reason)

        with self._lock:
            preop, preop_frame = self.preop_mm, self.preop_frame
            scale_mm, preop_problem = self._preop_scale_mm, self._preop_problem
        fid_s, fid_t = self.fiducials.pair(cloud.stamp_ns)
        if preop is None:
            return fail(ERROR, "no preop model received yet (/preop/points)")
        if preop_problem:  # kept with a WARN on arrival; a pose against it would be meaningless
            return fail(ERROR, f"{preop_problem}; not registered")
        if not cloud.frame_id:
            return fail(ERROR, "intraop cloud has an empty header.frame_id (a pose needs its frame); not registered")
        try:
            points, n_raw = self._decode(cloud)
        except InputError as exc:
            return fail(ERROR, f"bad intraop cloud: {exc}")
        values["input_points"] = str(n_raw)
        if n_raw == 0:
            return fail(ERROR, "empty intraop cloud (0 points)")
        if len(points) == 0:
            return fail(ERROR, f"intraop cloud has no valid points (all {n_raw} are NaN/inf)")
        warnings: list[str] = []
        if len(points) >= self.config.max_input_points:
            voxel_mm = (scale_mm or extent_mm(points)) * self.config.voxel_size_norm / 2
            points = voxel_downsample(points, voxel_mm)
            warnings.append(f"{n_raw} input points voxelized to {len(points)} ({voxel_mm:.2f} mm voxels)")
        values["valid_points"] = str(len(points))
        if len(points) < self.config.min_points:
            return fail(ERROR, f"too few valid intraop points: {len(points)} < min_points {self.config.min_points}")
        extent = extent_mm(points)
        values["extent_mm"] = f"{extent:.1f}"
        unit_warning = self._units_warning(extent, "intraop cloud")
        if unit_warning:
            return fail(WARN, unit_warning + "; not registered")
        with self._lock:
            self._latest = _Cloud(cloud.frame_id, cloud.stamp_ns, points_mm=points, n_raw=n_raw)
        prep_ms = (time.perf_counter() - start) * 1e3
        cached = set(self.registrar.cache)

        def guarded(what: str, call: Callable[[], Any]) -> tuple[Any, CoreOutput | None]:
            """(call(), None), or (None, the frame's ERROR output): the node must survive anything a method raises."""
            try:
                return call(), None
            except LiverP2PError as exc:
                return None, fail(ERROR, f"registration failed: {exc}")
            except Exception as exc:
                LOG.exception("%s raised", what)
                return None, fail(ERROR, f"registration crashed: {type(exc).__name__}: {exc}")

        if self.config.mode == "survey" and reason != "reregister":  # ---- survey mode (survey.py)
            step, failed = guarded(
                "survey registration",
                lambda: self._survey().step(
                    preop, points, source_fiducials_mm=fid_s, target_fiducials_mm=fid_t, sensor_origin_mm=self._origin()
                ),
            )
            if failed is not None:
                return failed
            result, track_ms = step.result, None
            values.update(step.values)
            warnings += step.warnings
        else:
            result, track_ms = self._try_tracking(preop, points, fid_s, fid_t, cloud.frame_id, reason)
        values["tracked"] = str(result is not None and result.method == "track").lower()
        if result is None:
            result, failed = guarded(
                "registration",
                lambda: self.registrar.register(
                    preop, points, source_fiducials_mm=fid_s, target_fiducials_mm=fid_t, sensor_origin_mm=self._origin()
                ),
            )
            if failed is not None:
                return failed
            if track_ms is not None:  # a rejected tracking attempt is part of this frame's latency
                result.runtime_ms["track_rejected"] = track_ms
                result.runtime_ms["total"] = result.runtime_ms.get("total", 0.0) + track_ms
        result.runtime_ms.setdefault("node_prepare", prep_ms)
        values.update(result_values(result))
        # what this registration had to compute about the model (normally nothing: the warm-up did)
        computed = {str(k).split(":")[0] for k in self.registrar.cache if k not in cached}
        values["model_cache_computed"] = ",".join(sorted(computed)) or "none"

        if not result.ok or not np.all(np.isfinite(result.T_target_source)):
            return CoreOutput(
                [
                    Diagnostic(
                        ERROR, DIAG_NAME, f"registration failed: {result.message or 'no valid transform'}", values
                    )
                ],
                result=result,
                reason=reason,
            )
        level = OK
        verb = "tracked from the previous pose" if result.method == "track" else "registered"
        message = f"{verb}: residual {result.residual_mm:.2f} mm"
        if result.rms_tre_mm is not None:
            message += f", RMS-TRE {result.rms_tre_mm:.2f} mm"
        warnings += result_warnings(result, self.config).values()
        if warnings:
            level = max(level, WARN)
            message += " (" + "; ".join(warnings) + ")"
        T = np.asarray(result.T_target_source, dtype=np.float64)
        pose = PoseOutput(cloud.stamp_ns, cloud.frame_id, preop_frame, T)
        moved = transform_points(T, preop)
        return CoreOutput([Diagnostic(level, DIAG_NAME, message, values)], pose, moved, result, reason)

    def _try_tracking(
        self,
        preop: np.ndarray,
        points: np.ndarray,
        fid_s: np.ndarray | None,
        fid_t: np.ndarray | None,
        frame_id: str,
        reason: str,
    ) -> tuple[RegistrationResult | None, float | None]:
        """ICP from the last good pose; (result, None) if it fits as well as the last full registration.

        Returns (None, ms spent) when the tracked pose is rejected and (None, None) when no
        tracking was attempted: outside continuous mode, on a re-register request, without a
        good previous pose, for another sensor frame, or when a full registration is due.
        """
        track = self._track
        cfg = self.config
        if (
            not cfg.track_previous_pose
            or reason != "continuous"
            or track is None
            or track.frame_id != frame_id
            or track.frames >= cfg.track_max_frames
        ):
            return None, None
        start = time.perf_counter()
        try:
            result = self.registrar.register(
                preop,
                points,
                method="track",
                initial_T_mm=track.T_mm,
                source_fiducials_mm=fid_s,
                target_fiducials_mm=fid_t,
                sensor_origin_mm=self._origin(),
            )
        except LiverP2PError:
            return None, (time.perf_counter() - start) * 1e3
        limit_mm = min(cfg.track_residual_ratio * track.reference_residual_mm, cfg.residual_warn_mm)
        if not (result.residual_mm <= limit_mm and np.isfinite(result.T_target_source).all()):
            return None, (time.perf_counter() - start) * 1e3
        return result, None

    def _remember_for_tracking(self, output: CoreOutput, frame_id: str) -> None:
        """Keep an OK pose as the next frame's prior; anything else (WARN, ERROR) clears it."""
        result = output.result
        if output.pose is None or result is None or output.level != OK:
            self._track = None
        elif result.method == "track" and self._track is not None:
            self._track.T_mm = np.asarray(result.T_target_source, dtype=np.float64)
            self._track.frames += 1
        else:
            self._track = _TrackState(np.asarray(result.T_target_source, float), result.residual_mm, frame_id)

    # ---------------------------------------------------------------- survey mode
    def _survey(self) -> Survey:
        """The survey state, bound to the current registrar and config (a parameter change starts over)."""
        if self._survey_state is None or (self._survey_state.registrar, self._survey_state.config) != (
            self.registrar,
            self.config,
        ):
            self._survey_state = Survey(self.registrar, self.config)
        return self._survey_state

    def reset_survey(self) -> str:
        """Forget the fused surface and the pose (the ~/reset_survey service); returns what was dropped."""
        with self._register_lock:
            survey = self._survey_state
            dropped = (
                "nothing fused yet"
                if survey is None or not survey.frames
                else (f"dropped {survey.frames} fused frames (visibility {survey.visibility:.2f})")
            )
            if survey is not None:
                survey.reset()
        return f"survey reset: {dropped}; the next frame is registered globally"

    def _origin(self) -> np.ndarray | None:
        """Where the sensor stood, in the intraop cloud's frame: its origin, by the ROS convention (free space)."""
        return np.zeros(3) if self.config.sensor_at_frame_origin else None

    def _decode(self, cloud: _Cloud) -> tuple[np.ndarray, int]:
        if cloud.points_mm is not None:
            points = cloud.points_mm
            return points[np.isfinite(points).all(axis=1)], cloud.n_raw
        msg = cloud.msg
        n_raw = int(msg.width) * int(msg.height)
        return cloud_to_points_mm(msg), n_raw

    def _units_warning(self, extent: float, what: str) -> str:
        cfg = self.config
        problem = implausible_extent(extent, what, cfg.expected_extent_min_mm, cfg.expected_extent_max_mm)
        if not problem:
            return ""
        if extent > cfg.expected_extent_max_mm:
            return (
                problem
                + " (ROS messages must be in metres; millimetre values published as metres look 1000x too large)"
            )
        return problem + " (ROS messages must be in metres; a liver is 0.05-0.3 m across)"

    def _counters(self) -> dict[str, str]:
        return {
            "received_clouds": str(self.received),
            "registered_clouds": str(self.processed),
            "dropped_clouds": str(self.dropped),
        }


def result_values(result: RegistrationResult) -> dict[str, str]:
    """The diagnostic key/values of a registration result."""
    values = {
        "method": result.method,
        "residual_mm": f"{result.residual_mm:.3f}",
        "visibility": f"{result.visibility:.3f}",
        "matches": str(result.n_matches),
        "n_source": str(result.n_source),
        "n_target": str(result.n_target),
        "ambiguous": str(bool(result.ambiguous)).lower(),
        "uncertainty_mm": f"{result.uncertainty_mm:.3f}",
    }
    if result.free_space:  # "on", or "off: <why the origin was refused>"; absent without an origin
        values["free_space"] = result.free_space
        values["free_space_violation"] = f"{result.free_space_violation:.3f}"
    if result.chosen is not None and 0 <= result.chosen < len(result.candidates):
        values["chosen_candidate"] = result.candidates[result.chosen].name
    if result.candidates:
        values["candidate_residuals_mm"] = ",".join(
            f"{c.name}={c.residual_mm:.2f}" if c.ok else f"{c.name}=failed" for c in result.candidates
        )
    if result.rms_tre_mm is not None:
        values["rms_tre_mm"] = f"{result.rms_tre_mm:.3f}"
        values["max_tre_mm"] = f"{result.max_tre_mm:.3f}"
    for stage, ms in result.runtime_ms.items():
        values[f"runtime_ms.{stage}"] = f"{ms:.1f}"
    return values
