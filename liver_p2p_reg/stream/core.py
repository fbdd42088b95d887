"""The stream core: register_node's state machine without ROS, composing intake, tracking, survey and outputs.

The rclpy register_node and bag replay drive this same object (ROS messages reach it through
`ros.messages`). Inputs are millimetre arrays, or clouds whose decoding waits until they are
registered; outputs are `CoreOutput`s holding a pose (T_sensor_ct, mm), the moved preop cloud
(mm) and `Diagnostic`s. With `deform` on, the non-rigid stage (deformation.py) follows each pose.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from liver_p2p_reg.cloud_io import extent_mm
from liver_p2p_reg.config import Config
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.registration.methods import check_method_name
from liver_p2p_reg.registration.registrar import Registrar
from liver_p2p_reg.stream.checks import Refused, checked_points, same_model
from liver_p2p_reg.stream.deformation import (
    ElasticPreparation,
    MeshStore,
    PreparedStage,
    checked_mesh,
    mesh_diagnostic,
    rigid_registrar,
    run_stage,
)
from liver_p2p_reg.stream.fiducials import FiducialStore
from liver_p2p_reg.stream.intake import Decoder, Intake, IntraopCloud, finite_rows, points_decoder
from liver_p2p_reg.stream.outputs import (
    DIAG_NAME,
    ERROR,
    OK,
    PREOP_DIAG_NAME,
    STALE,
    WARN,
    CoreOutput,
    Diagnostic,
    PoseOutput,
    registered_diagnostic,
    result_values,
    units_warning,
)
from liver_p2p_reg.stream.record_hooks import RecorderFactory, Recording
from liver_p2p_reg.stream.solve import Frame, solve_frame
from liver_p2p_reg.stream.structures import StructureStore
from liver_p2p_reg.stream.survey import Survey, stage_view_mm
from liver_p2p_reg.stream.tracking import Tracker
from liver_p2p_reg.structures_io import place_structures

LOG = logging.getLogger("liver_p2p_reg.node")
PoseHook = Callable[[CoreOutput], None]  # gets the rigid pose before the non-rigid stage runs (the node publishes it)


class NodeCore:
    """State machine of register_node; thread-safe (callbacks vs. one registration worker).

    recorder_factory: opens the flight recorder when `config.record_path` is set (bags/recorder.py).
    The registrar runs the rigid pipeline only (`rigid_registrar`): the core runs the non-rigid stage itself."""

    def __init__(
        self,
        config: Config | None = None,
        registrar: Registrar | None = None,
        recorder_factory: RecorderFactory | None = None,
    ) -> None:
        self.config = (config or Config()).validate()
        check_method_name(self.config.method)  # an unknown method is refused now, not with an ERROR per frame
        self.registrar = rigid_registrar(self.config, registrar)
        self._lock = threading.Lock()  # guards the model state below (cheap, callbacks)
        self._register_lock = threading.Lock()  # one registration at a time
        self.preop_mm: np.ndarray | None = None
        self.preop_frame, self.preop_stamp_ns = "ct", 0
        self.fiducials = FiducialStore()
        self.structures = StructureStore()  # moved with every pose (structures.py: the latest set received)
        self.mesh = MeshStore()  # the non-rigid stage's surface, for the model of its stamp (deformation.py)
        self._elastic = ElasticPreparation()  # what the elastic model was last prepared for
        self._preop_scale_mm: float | None = None
        self._preop_problem = ""  # why the current model cannot be registered against (wrong units)
        self._intake = Intake(self.fiducials)
        self._tracker = Tracker()
        self._survey_state: Survey | None = None  # survey mode only
        self.last_output: CoreOutput | None = None
        self.processed = 0
        self._registering = False  # a registration has read the model (a new one waits for its end)
        self._next_model: tuple[np.ndarray, str, int, str] | None = None
        self._recording = Recording(recorder_factory, self)
        self._recording.follow(self.config)  # opens the recording when record_path is set

    # ---------------------------------------------------------------- inputs
    @property
    def received(self) -> int:
        """Intraop clouds received."""
        return self._intake.received

    @property
    def dropped(self) -> int:
        """Clouds superseded before they were registered (latest-only)."""
        return self._intake.dropped

    @property
    def preop_fiducials_mm(self) -> np.ndarray | None:
        """Fiducials of the current preop model (mm, preop frame), or None."""
        return self.fiducials.preop_mm

    def reconfigure(self, changes: dict[str, Any]) -> Config:
        """Apply parameter changes atomically (all valid or none; InputError says why). The Registrar's cache is
        kept: its entries are keyed by the source's content and the parameters they depend on, so only what a
        change invalidates is computed again."""
        config = self.config.replace(**changes)
        check_method_name(config.method)
        registrar = rigid_registrar(config)
        registrar.cache = self.registrar.cache
        with self._register_lock, self._lock:  # never swap under a running registration
            self._recording.follow(config)  # InputError (record_path cannot be written): nothing changed
            self.config, self.registrar = config, registrar
        return config

    def preload(self) -> float:
        """Load the method (modules, weights) and run it once on a synthetic liver: a model's warm-up does its share only; ms."""
        start = time.perf_counter()
        d = np.random.default_rng(0).normal(size=(3000, 3))
        shell = d / np.linalg.norm(d, axis=1, keepdims=True) * [80.0, 55.0, 40.0]
        with self._register_lock:
            self.registrar.warm_up(shell, elastic=False)  # a stand-in shape: no elastic model of it
        return (time.perf_counter() - start) * 1e3

    def set_preop(
        self, points_mm: np.ndarray, frame_id: str = "ct", stamp_ns: int = 0, *, warm_up: bool = True
    ) -> Diagnostic:
        """New preop model (mm, preop frame). Returns its diagnostic; bad models are rejected.

        warm_up=False leaves the model's warm-up to a later `warm_up_model()` call (the node
        runs it on its worker so callbacks stay fast).
        """
        points = finite_rows(np.asarray(points_mm, dtype=np.float64).reshape(-1, 3))
        if len(points) < self.config.min_points:
            message = f"preop model has {len(points)} valid points (< {self.config.min_points}); ignored"
            return Diagnostic(ERROR, PREOP_DIAG_NAME, message)
        with self._lock:
            current = self._next_model or (self.preop_mm, self.preop_frame, self.preop_stamp_ns)
        if same_model(current, points, frame_id or "ct", int(stamp_ns)):
            self.fiducials.forget_frames()
            message = f"preop model unchanged ({len(points)} points, same content and stamp): kept"
            return Diagnostic(OK, PREOP_DIAG_NAME, message, {"points": str(len(points)), "unchanged": "true"})
        extent = extent_mm(points)
        unit_warning = units_warning(extent, "preop model", self.config)
        model = (points, frame_id or "ct", int(stamp_ns), unit_warning)
        with self._lock:  # a registration running now ends against the model it started with
            if self._registering:
                self._next_model = model
            else:
                self._use_model(*model)
        values = {"points": str(len(points)), "extent_mm": f"{extent:.1f}", "frame_id": model[1]}
        if unit_warning:
            return Diagnostic(WARN, PREOP_DIAG_NAME, unit_warning, values)
        if warm_up:
            return self.warm_up_model()
        return Diagnostic(OK, PREOP_DIAG_NAME, f"preop model received ({len(points)} points)", values)

    def _use_model(self, points: np.ndarray, frame_id: str, stamp_ns: int, problem: str) -> None:
        """Make a model current (under self._lock, between registrations)."""
        self.preop_mm, self.preop_frame, self.preop_stamp_ns = points, frame_id, stamp_ns
        self._preop_scale_mm = float(np.max(np.linalg.norm(points - points.mean(axis=0), axis=1)))
        self._preop_problem = problem
        self._intake.new_model()
        self._tracker.forget()  # a pose of another model is no prior
        self._survey_state = None  # nor is a surface fused against it
        self.fiducials.new_model(stamp_ns)
        self._recording.preop(points, frame_id, stamp_ns)

    def warm_up_model(self) -> Diagnostic:
        """Do the current model's own share of the work (its features, ICP index, ...) now, once,
        instead of inside the first frame's latency; its diagnostic carries `warm_up_ms`."""
        with self._register_lock:
            points = self.preop_mm
            if points is None:
                return Diagnostic(ERROR, PREOP_DIAG_NAME, "no preop model to warm up")
            start = time.perf_counter()
            self.registrar.warm_up(points, elastic=False)  # the elastic model: the next line's, of the mesh if any
            stage = self._prepare_stage_locked(force=True)  # that model (seconds), when deform or the judge is on
            ms = (time.perf_counter() - start) * 1e3
        values = {
            "points": str(len(points)),
            "extent_mm": f"{extent_mm(points):.1f}",
            "frame_id": self.preop_frame,
            "warm_up_ms": f"{ms:.1f}",
        }
        diag = Diagnostic(OK, PREOP_DIAG_NAME, f"preop model received ({len(points)} points)", values)
        return diag if stage is None else stage.diagnostic(diag)

    def set_preop_mesh(
        self, vertices_mm: np.ndarray, triangles: np.ndarray, frame_id: str, stamp_ns: int
    ) -> Diagnostic:
        """A /preop/mesh (welded vertices, mm): the stage's surface for its model; InputError when it is not a mesh."""
        mesh = checked_mesh(vertices_mm, triangles, frame_id, stamp_ns)
        self.mesh.set(mesh)
        self._recording.preop_mesh(mesh)
        with self._lock:
            points, key = self.preop_mm, (self.preop_frame, self.preop_stamp_ns)
        current = points is not None and self.mesh.for_model(*key, points) is mesh  # a looped bag's next model's: no
        return mesh_diagnostic(mesh, current)

    def prepare_deformation(self) -> Diagnostic | None:
        """Build the elastic model now if `deform` or the judge needs it and it is not built: the diagnostic or None."""
        with self._register_lock:
            stage = self._prepare_stage_locked(force=False)
        return None if stage is None else stage.diagnostic()

    def _prepare_stage_locked(self, force: bool) -> PreparedStage | None:
        with self._lock:
            points, key = self.preop_mm, (self.preop_frame, self.preop_stamp_ns)
        return self._elastic.prepare(self.registrar, self.config, points, *self.mesh.find(*key, points), force=force)

    def set_preop_fiducials(self, points_mm: np.ndarray | None, stamp_ns: int | None = None) -> None:
        """Ordered fiducials inside the preop model stamped `stamp_ns` (None: the current model), mm."""
        self.fiducials.set_preop(points_mm, stamp_ns)
        self._recording.preop_fiducials(points_mm, stamp_ns)

    def set_intraop_fiducials(self, points_mm: np.ndarray, stamp_ns: int) -> None:
        """Ground-truth fiducials in the sensor frame for the cloud with the same header stamp."""
        self.fiducials.set_intraop(points_mm, stamp_ns)

    def on_intraop_cloud(
        self, frame_id: str, stamp_ns: int, decode: Decoder, now_s: float | None = None
    ) -> list[Diagnostic]:
        """An intraop cloud (sensor frame); O(1): `decode` runs only when the cloud is registered."""
        return self._receive(IntraopCloud(frame_id, int(stamp_ns), decode, received_s=now_s))

    def on_intraop_points(
        self, points_mm: np.ndarray, frame_id: str, stamp_ns: int = 0, now_s: float | None = None
    ) -> list[Diagnostic]:
        """An intraop cloud as plain (N, 3) points (mm, sensor frame)."""
        points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        return self.on_intraop_cloud(frame_id, stamp_ns, points_decoder(points), now_s)

    def _receive(self, cloud: IntraopCloud) -> list[Diagnostic]:
        if self._intake.receive(cloud):
            return []
        diag = Diagnostic(ERROR, DIAG_NAME, "intraop cloud received before any preop model (/preop/points); waiting")
        self.last_output = CoreOutput([diag])
        return [diag]

    # ---------------------------------------------------------------- scheduling (intake.py)
    def next_due_s(self) -> float | None:
        """When the pending cloud becomes due (the caller's clock; -inf: now), None if it never will
        by itself (nothing pending, no model, on_demand, once already done)."""
        return self._intake.next_due_s(self.config)

    def due(self, now_s: float | None = None) -> bool:
        """Whether `process_pending` would register now (mode, rate limit, inputs present)."""
        return self._intake.due(self.config, time.monotonic() if now_s is None else now_s)

    def process_pending(self, now_s: float | None = None, on_pose: PoseHook | None = None) -> CoreOutput | None:
        """Register the latest pending cloud if due (continuous/once modes); else None.

        on_pose(output) gets a pose as soon as it is known, before the non-rigid stage (`deform`) runs; the
        returned output is the final one (the same pose, with the stage's values and deformed surface)."""
        cloud = self._intake.take_due(self.config, time.monotonic() if now_s is None else now_s)
        if cloud is None:
            return None
        output = self._register(cloud, self.config.mode, on_pose)
        if self.config.mode == "once" and output.pose is not None:
            self._intake.mark_once_done()
        return output

    def reregister(self, now_s: float | None = None, on_pose: PoseHook | None = None) -> CoreOutput:
        """Register the latest intraop cloud now, whatever the mode (the ~/reregister service); on_pose as above."""
        cloud = self._intake.take_latest(time.monotonic() if now_s is None else now_s)
        if cloud is None:
            diag = Diagnostic(ERROR, DIAG_NAME, "no intraop cloud received yet (/intraop/points)")
            self.last_output = CoreOutput([diag], reason="reregister")
            return self.last_output
        return self._register(cloud, "reregister", on_pose)

    def register_now(self, frame_id: str, stamp_ns: int, decode: Decoder, reason: str) -> CoreOutput:
        """Register this cloud now as `reason` says, past the mode and the rate limit (a recording's replay)."""
        return self._register(IntraopCloud(frame_id, int(stamp_ns), decode), reason)

    def close_recording(self) -> None:
        """Close the flight recording, if one is open (its file is complete then)."""
        self._recording.close()

    def flush(self) -> CoreOutput | None:
        """Register a still-pending cloud ignoring the rate limit (end of a replayed bag)."""
        self._intake.release()
        return self.process_pending(0.0)

    def status(self) -> Diagnostic:
        """The current diagnostic for periodic publishing (STALE before any attempt)."""
        last = self.last_output
        if last is None or not last.diagnostics:
            return Diagnostic(STALE, DIAG_NAME, "no registration yet", self._counters())
        diag = last.diagnostics[0]
        return Diagnostic(diag.level, diag.name, diag.message, {**diag.values, **self._counters()})

    # ---------------------------------------------------------------- registration
    def _register(self, cloud: IntraopCloud, reason: str, on_pose: PoseHook | None = None) -> CoreOutput:
        with self._register_lock:
            cloud = self._recording.begin(cloud)
            try:
                output = self._register_locked(cloud, reason, on_pose)
                self._tracker.remember(output, cloud.frame_id)
                self._recording.registration(cloud, reason, output)
            finally:
                with self._lock:
                    self._registering, model, self._next_model = False, self._next_model, None
                    if model is not None:  # it came during the registration
                        self._use_model(*model)
        self.last_output = output
        with self._lock:
            self.processed += 1
        return output

    def _register_locked(self, cloud: IntraopCloud, reason: str, on_pose: PoseHook | None) -> CoreOutput:
        start = time.perf_counter()
        values: dict[str, str] = {"frame_id": cloud.frame_id, "stamp_ns": str(cloud.stamp_ns), "mode": self.config.mode}
        with self._lock:
            self._registering = True
            preop, preop_frame, preop_stamp = self.preop_mm, self.preop_frame, self.preop_stamp_ns
            scale_mm, preop_problem = self._preop_scale_mm, self._preop_problem
        fid_s, fid_t = self.fiducials.pair(cloud.stamp_ns)
        self._recording.paired(fid_s, fid_t)
        try:
            if preop is None:
                raise Refused(ERROR, "no preop model received yet (/preop/points)")
            if preop_problem:  # kept with a WARN on arrival; a pose against it would be meaningless
                raise Refused(ERROR, f"{preop_problem}; not registered")
            points, n_raw, warnings = checked_points(cloud, self.config, scale_mm, values)
            self._intake.keep_latest(IntraopCloud(cloud.frame_id, cloud.stamp_ns, points_decoder(points, n_raw)))
            prep_ms = (time.perf_counter() - start) * 1e3
            cached = set(self.registrar.cache)
            surface = self.mesh.judge_kwargs(self.config, preop_frame, preop_stamp, preop)  # the stage's elastic model
            frame = Frame(preop, points, fid_s, fid_t, cloud.frame_id, reason, self._origin(), surface)
            result = solve_frame(frame, self.registrar, self.config, self._tracker, self._survey, values, warnings)
        except Refused as refused:
            return CoreOutput([Diagnostic(refused.level, DIAG_NAME, refused.message, values)], reason=reason)
        result.runtime_ms.setdefault("node_prepare", prep_ms)
        values.update(result_values(result))
        # what this registration had to compute about the model (normally nothing: the warm-up did)
        computed = {str(k).split(":")[0] for k in self.registrar.cache if k not in cached}
        values["model_cache_computed"] = ",".join(sorted(computed)) or "none"
        if not result.ok or not np.all(np.isfinite(result.T_target_source)):
            message = f"registration failed: {result.message or 'no valid transform'}"
            return CoreOutput([Diagnostic(ERROR, DIAG_NAME, message, values)], result=result, reason=reason)
        T = np.asarray(result.T_target_source, dtype=np.float64)
        structures = self._recording.moved(self.structures.current())  # the set it places, recorded with it
        placed = place_structures(result, structures, T)
        diag = registered_diagnostic(result, values, warnings, self.config, placed)
        pose = PoseOutput(cloud.stamp_ns, cloud.frame_id, preop_frame, T)
        output = CoreOutput([diag], pose, transform_points(T, preop), result, reason, placed)
        if on_pose is not None:
            try:  # the rigid pose goes out first, whatever the stage then does
                on_pose(output)
            except Exception:
                LOG.exception("the pose hook raised")
        if not self.config.deform:
            return output
        mesh = self.mesh.for_model(preop_frame, preop_stamp, preop)
        view = stage_view_mm(self._survey_state, self.config, reason)  # survey mode: the fused surface
        return run_stage(self.registrar, output, frame, structures, mesh, view)

    # ---------------------------------------------------------------- survey mode
    def _survey(self) -> Survey:
        """The survey state, bound to the current registrar and config (a parameter change starts over)."""
        state = self._survey_state
        if state is None or (state.registrar, state.config) != (self.registrar, self.config):
            self._survey_state = state = Survey(self.registrar, self.config)
        return state

    def reset_survey(self) -> str:
        """Forget the fused surface and the pose (the ~/reset_survey service); returns what was dropped."""
        with self._register_lock:
            survey = self._survey_state
            dropped = "nothing fused yet"
            if survey is not None and survey.frames:
                dropped = f"dropped {survey.frames} fused frames (visibility {survey.visibility:.2f})"
            if survey is not None:
                survey.reset()
            self._recording.event("reset_survey")
        return f"survey reset: {dropped}; the next frame is registered globally"

    def _origin(self) -> np.ndarray | None:
        """Where the sensor stood, in the intraop cloud's frame: its origin, by the ROS convention (free space)."""
        return np.zeros(3) if self.config.sensor_at_frame_origin else None

    def _counters(self) -> dict[str, str]:
        return {
            "received_clouds": str(self.received),
            "registered_clouds": str(self.processed),
            "dropped_clouds": str(self.dropped),
            **self.fiducials.status(),
            **self._recording.status(),
        }
