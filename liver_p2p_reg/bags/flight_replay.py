"""Read a flight recording back (record by record, through its rotated files) and re-run every registration in it.

The re-run drives a NodeCore with the recorded parameters, models and survey resets in their
recorded order and registers exactly the recorded clouds with their recorded reasons (no intake,
no rate limit, no drop), with the fiducial pair each one used; `liver-p2p register` recordings
(reason `register`) go through the Registrar as the command did. Every pose is compared bit for
bit with the recorded one, and where the non-rigid stage was applied the deformed preop surface (by its
recorded digest); a recorded /preop/mesh is given to the core as register_node gets it. The subsurface
structures each registration moved are given back before it, and where it placed some, their positions and
bounds are compared with the recorded ones (digest, then the published cloud for round-off). Each verdict (OK, WARN,
ERROR) is compared too: the same pose can come with another verdict (a recalibrated error bound, a threshold).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from liver_p2p_reg.bags.command_recording import command_output
from liver_p2p_reg.bags.flight_read import ReadState, is_recording, read_recording
from liver_p2p_reg.bags.flight_records import Damaged, RecordedMessage, checked_values
from liver_p2p_reg.bags.io import bag_error_reason
from liver_p2p_reg.bags.recorded_points import message_points_mm, message_structures, placed_sha256, points_sha256
from liver_p2p_reg.bags.recorder import (
    TOPIC_CONFIG,
    TOPIC_EVENT,
    TOPIC_META,
    TOPIC_REGISTRATION,
    recorder_factory,
    run_environment,
)
from liver_p2p_reg.bags.rerun_report import Rerun, deformed_within_roundoff, structures_within_roundoff, within_roundoff
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.registration.weights_id import weights_sha256
from liver_p2p_reg.ros.messages import mesh_marker_mm
from liver_p2p_reg.ros.pointcloud2 import stamp_to_ns
from liver_p2p_reg.ros.topics import (
    TOPIC_DEFORMED_PREOP,
    TOPIC_INTRAOP,
    TOPIC_INTRAOP_FIDUCIALS,
    TOPIC_PREOP,
    TOPIC_PREOP_FIDUCIALS,
    TOPIC_PREOP_MESH,
    TOPIC_PREOP_STRUCTURES,
    TOPIC_STRUCTURE_LABELS,
    TOPIC_STRUCTURES,
)
from liver_p2p_reg.stream.core import NodeCore
from liver_p2p_reg.stream.deformation import PreopMesh
from liver_p2p_reg.stream.outputs import LEVEL_NAMES
from liver_p2p_reg.stream.record_hooks import restore_tracker
from liver_p2p_reg.structures_io import PlacedStructure, Structure, place_structures

# what a pose's bits depend on besides its inputs: a difference is said before the comparison
ENVIRONMENT_KEYS = ("package_version", "code_version", "numpy", "torch", "open3d", "usable_cores", "omp_num_threads")

MISSING = object()  # a digest a recording from before it was kept does not have

# the reading lives in flight_read; these names are read from here too (replay_cmd, the tests)
__all__ = ["ReadState", "is_recording", "read_recording", "rerun_recording"]


# ---------------------------------------------------------------- the re-run
class _Rerunner:
    """The state of one re-run: the core, the preop model as recorded, the cloud of the registration being read."""

    def __init__(self, record_path: str | None, overwrite: bool) -> None:
        self.record_path = record_path or ""
        self.factory = recorder_factory("overwrite" if overwrite else "refuse") if record_path else None
        self.core: NodeCore | None = None
        self.source: np.ndarray | None = None  # the preop model as recorded (`register` uses it unfiltered)
        self.mesh: PreopMesh | None = None  # the last recorded /preop/mesh (`register --deform` deforms on it)
        self.cloud: np.ndarray | None = None
        self.preop_fiducials: np.ndarray | None = None  # the last /preop/fiducials: a pair's preop side
        self.intraop_fiducials: np.ndarray | None = None  # the registration's own
        self.deformed: np.ndarray | None = None  # the registration's deformed surface as recorded (float32 metres)
        self.structure_points: RecordedMessage | None = None  # /preop/structures, until its names follow
        self.structures: list[Structure] = []  # the set the next registration moves (`register` places them)
        self.placed: RecordedMessage | None = None  # the registration's /registration/structures (float32 metres)
        self.report = Rerun([])

    def config(self, values: dict[str, Any]) -> None:
        config = Config.from_dict({**values["config"], "record_path": self.record_path})
        if self.core is None:
            self.core = NodeCore(config, recorder_factory=self.factory)
        else:
            self.core.reconfigure(config.to_dict())  # also a change of record_path only: a new registrar, as live
        here = weights_sha256(config)
        if values.get("weights_sha256", "") != here:
            self.note(f"recorded with weights sha256 {values.get('weights_sha256') or '-'}, re-run with {here or '-'}")

    def note(self, text: str) -> None:
        if text not in self.report.notes:
            self.report.notes.append(text)

    def message(self, item: RecordedMessage, values: dict[str, Any] | None) -> None:
        topic = item.topic
        if topic == TOPIC_CONFIG:
            self.config(values)
            return
        core = self._core()
        if topic == TOPIC_PREOP:
            self.source = _decoded(item, message_points_mm)
            core.set_preop(self.source, item.msg.header.frame_id, stamp_to_ns(item.msg.header.stamp))
        elif topic == TOPIC_PREOP_MESH:  # as register_node: kept for its model, the elastic model prepared
            vertices, triangles = _decoded(item, mesh_marker_mm)
            frame_id, stamp_ns = item.msg.header.frame_id, stamp_to_ns(item.msg.header.stamp)
            self.mesh = PreopMesh(vertices, triangles, frame_id, stamp_ns)
            core.set_preop_mesh(vertices, triangles, frame_id, stamp_ns)
            core.prepare_deformation()
        elif topic == TOPIC_PREOP_FIDUCIALS:
            points = _decoded(item, message_points_mm)
            self.preop_fiducials = points if len(points) else None
            core.set_preop_fiducials(self.preop_fiducials, stamp_to_ns(item.msg.header.stamp))
        elif topic == TOPIC_INTRAOP:
            self.cloud = _decoded(item, message_points_mm)
        elif topic == TOPIC_INTRAOP_FIDUCIALS:
            self.intraop_fiducials = _decoded(item, message_points_mm)
        elif topic == TOPIC_DEFORMED_PREOP:
            self.deformed = _decoded(item, message_points_mm)
        elif topic == TOPIC_PREOP_STRUCTURES:
            self.structure_points = item
        elif topic == TOPIC_STRUCTURE_LABELS:  # written right after its /preop/structures
            points, self.structure_points = self.structure_points, None
            if points is None:
                raise Damaged(item.file, f"{item.where} follows no {TOPIC_PREOP_STRUCTURES} record")
            self.structures = _decoded(points, lambda msg: message_structures(msg, item.msg.data))
            core.structures.set_structures(self.structures)
        elif topic == TOPIC_STRUCTURES:
            self.placed = item
        elif topic == TOPIC_EVENT and values["event"] == "tracker":
            restore_tracker(core, values)
        elif topic == TOPIC_EVENT and values["event"] == "reset_survey":
            core.reset_survey()
        elif topic == TOPIC_REGISTRATION:
            self.registration(values)

    def _core(self) -> NodeCore:
        if self.core is None:
            raise InputError(f"flight recording: a record before the first {TOPIC_CONFIG}")
        return self.core

    def registration(self, values: dict[str, Any]) -> None:
        points, self.cloud = self.cloud, None
        fid_t, self.intraop_fiducials = self.intraop_fiducials, None
        fiducials = (self.preop_fiducials, fid_t) if values["fiducials"] else None
        if fiducials is not None and (fiducials[0] is None or fid_t is None):
            raise InputError(f"flight recording: registration {values['seq']} lacks its fiducials")
        if values["decoded"] and points is None:
            raise InputError(f"flight recording: registration {values['seq']} lacks its {TOPIC_INTRAOP} cloud")
        T, deformed, placed, level = self._run(values, points, fiducials)
        report = self.report
        report.registrations += 1
        where = f"registration {values['seq']} (stamp {values['stamp_ns']}, {values['reason']})"
        before = len(report.differences)
        self._compare_pose(values["pose"], T, where)  # first: a registration's first line is its most telling
        self._compare_deformed(values, deformed, where)
        self._compare_structures(values, placed, where)
        self._compare_verdict(values, level, where)
        report.registrations_differing += len(report.differences) > before

    def _compare_pose(self, recorded: dict[str, Any] | None, T: np.ndarray | None, where: str) -> None:
        """The re-run's pose against the recorded one: bitwise, within round-off, or a difference."""
        report = self.report
        if recorded is None:
            if T is None:
                report.no_pose += 1
            else:
                report.differences.append(f"{where}: recorded without a pose, re-run with one")
            return
        report.poses += 1
        want = np.asarray(recorded["T_sensor_ct_mm"], dtype=np.float64)
        got = None if T is None else np.asarray(T, dtype=np.float64)
        if got is None:
            report.differences.append(f"{where}: recorded with a pose, re-run without one")
        elif got.tobytes() == want.tobytes():
            report.identical += 1
        elif within_roundoff(got, want):
            report.roundoff += 1
        else:
            delta = float(np.max(np.abs(got - want)))
            report.differences.append(f"{where}: pose differs (max |dT| {delta:.3g}, mm in its translation)")

    def _compare_deformed(self, values: dict[str, Any], deformed: np.ndarray | None, where: str) -> None:
        """The re-run's deformed preop surface against the recorded digest (recordings that keep one), and where
        the digests differ, against the recorded surface itself (round-off, or a difference)."""
        recorded, self.deformed = self.deformed, None
        counts = self._compare_digest(
            values.get("deformed_preop_sha256", MISSING), points_sha256(deformed),
            lambda: recorded is not None and deformed_within_roundoff(deformed, recorded),
            f"{where}: deformed preop surface", "one",
        )  # fmt: skip
        self._count("deformed", counts)

    def _compare_structures(self, values: dict[str, Any], placed: list[PlacedStructure], where: str) -> None:
        """The re-run's placed structures against the recorded digest (recordings that keep one), and where the
        digests differ, against the recorded /registration/structures cloud (round-off, or a difference)."""
        recorded, self.placed = self.placed, None
        counts = self._compare_digest(
            values.get("structures_sha256", MISSING), placed_sha256(placed),
            lambda: recorded is not None and _decoded(recorded, lambda msg: structures_within_roundoff(placed, msg)),
            f"{where}: placed structures", "some",
        )  # fmt: skip
        self._count("structures", counts)

    def _compare_verdict(self, values: dict[str, Any], level: int | None, where: str) -> None:
        """The re-run's verdict (OK / WARN / ERROR) against the recorded one: a pose can be bitwise the same while
        its verdict changed (another error-bound calibration file behind the recorded path, or the bundled one: the
        path is recorded, not the file's contents; or another version of the code)."""
        want = values.get("level")
        if level is None or not isinstance(want, int) or isinstance(want, bool):
            return
        if "structures_sha256" not in values:  # recorded before structures were kept: re-run without them, a WARN
            return  # that followed a structure's bound would not come again
        self.report.verdicts += 1
        if level == want:
            self.report.verdicts_same += 1
            return
        names = {k: LEVEL_NAMES.get(k, str(k)) for k in (want, level)}
        self.report.differences.append(
            f"{where}: verdict differs (recorded {names[want]}, re-run {names[level]}; recorded: {values.get('message')})"
        )

    def _count(self, kind: str, counts: tuple[int, int, int]) -> None:
        """Add (recorded, identical, within round-off) to the report's `kind`, `kind`_identical, `kind`_roundoff."""
        for name, n in zip((kind, f"{kind}_identical", f"{kind}_roundoff"), counts, strict=True):
            setattr(self.report, name, getattr(self.report, name) + n)

    def _compare_digest(
        self, want: Any, got: str | None, near: Callable[[], bool], what: str, one: str
    ) -> tuple[int, int, int]:
        """A re-run's digest against the recorded one (MISSING: a recording from before it was kept): (recorded,
        bitwise the same, within round-off by `near()`), each 0 or 1; a difference goes into the report."""
        if want is MISSING:
            return 0, 0, 0
        kept = int(want is not None)
        if got == want:
            return kept, kept, 0
        if want and got and near():
            return kept, 0, 1
        shown = {True: one, False: "none"}
        detail = "not bitwise the same" if want and got else f"recorded {shown[bool(want)]}, re-run {shown[bool(got)]}"
        self.report.differences.append(f"{what} differs ({detail})")
        return kept, 0, 0

    def _run_command(
        self, values: dict[str, Any], points: np.ndarray | None, fid_s: Any, fid_t: Any
    ) -> tuple[np.ndarray | None, np.ndarray | None, list[PlacedStructure], int | None]:
        """`liver-p2p register`'s Registrar call again, on the recorded mesh with `deform`: its pose (mm) or None,
        the deformed surface as the command's recording computed it (None when the stage was not applied), the
        recorded structures placed as the command placed them and the verdict as the command gave it (None: not
        comparable)."""
        core, extras = self._core(), values["extras"]
        mesh = {} if self.mesh is None else self.mesh.stage_kwargs
        try:
            result = core.registrar.register(
                self.source,
                points,
                method=core.config.method,
                source_fiducials_mm=fid_s,
                target_fiducials_mm=fid_t,
                initial_T_mm=None if extras.get("initial_T_mm") is None else np.asarray(extras["initial_T_mm"]),
                sensor_origin_mm=extras.get("sensor_origin_mm"),
                **mesh,  # the recorded mesh: the contenders' judge's surface, as the command's (read only by a judge)
            )
        except LiverP2PError as exc:
            return None, None, [], command_output(exc, 0, "", core.config, self.source, None, None).level
        ok = result.ok and np.isfinite(result.T_target_source).all()
        T = result.T_target_source if ok else None
        staged = core.config.deform and T is not None
        if staged and not values.get("deformation"):  # written before `register` recordings kept the stage
            self.note("recorded without the non-rigid stage's values: its deformed surface and verdict are not checked")
            return T, None, place_structures(result, self.structures), None
        # the core's registrar is rigid only (the node runs the stage itself): the stage as the command ran it
        if staged:
            core.registrar.deform(
                result, self.source, points, source_fiducials_mm=fid_s, target_fiducials_mm=fid_t, **mesh
            )
        out = command_output(result, values["seq"], values["frame_id"], core.config, self.source, self.mesh,
                             self.structures)  # fmt: skip
        return T, out.deformed_preop_mm, out.structures, out.level

    def _run(
        self, values: dict[str, Any], points: np.ndarray | None, fiducials: tuple | None
    ) -> tuple[np.ndarray | None, np.ndarray | None, list[PlacedStructure], int | None]:
        """The re-run registration's pose, T_sensor_ct (mm), or None, its deformed preop surface (mm) or None, the
        structures it placed and its verdict (the diagnostic level)."""
        core = self._core()
        fid_s, fid_t = fiducials or (None, None)
        if values["reason"] == "register":  # `liver-p2p register`: the Registrar call the command made
            return self._run_command(values, points, fid_s, fid_t)
        core.fiducials.set_preop(fid_s, None)  # the pair the recorded registration used, whatever came when
        if fid_t is not None:
            core.fiducials.set_intraop(fid_t, values["stamp_ns"])
        n_raw, error = values["n_raw"], values["decode_error"] or "the recording holds no points for it"

        def decode() -> tuple[np.ndarray, int]:
            if points is None:
                raise InputError(error)
            return points, n_raw

        output = core.register_now(values["frame_id"], values["stamp_ns"], decode, values["reason"])
        if output.pose is None:
            return None, None, [], output.level
        return output.pose.T_sensor_ct_mm, output.deformed_preop_mm, output.structures, output.level


def _decoded(item: RecordedMessage, decode: Callable[[Any], Any]) -> Any:
    """A recorded message's points or mesh; a message whose fields do not decode is one line naming its record."""
    try:
        return decode(item.msg)
    except InputError as exc:
        raise Damaged(item.file, f"{item.where}: {exc}") from None
    except (ValueError, TypeError, IndexError) as exc:  # fields that contradict each other (sizes, offsets)
        raise Damaged(item.file, f"{item.where}: {bag_error_reason(exc)}") from None


def rerun_recording(path: str | Path, *, record_path: str | None = None, overwrite: bool = False) -> Rerun:
    """Re-run every completed registration of a flight recording (from `path` through its rotated files).

    record_path: record the re-run itself there (refused if it exists unless `overwrite`).
    """
    state = ReadState([])
    rerun = _Rerunner(record_path, overwrite)
    here = run_environment()
    current: Path | None = None
    skipping = False  # inside the head of a rotated file, whose state the re-run already has
    try:
        for item in read_recording(path, state):
            values = checked_values(item)
            if item.file != current:
                current, skipping = item.file, len(state.files) > 1
            if item.topic == TOPIC_META:
                for key in ENVIRONMENT_KEYS:
                    if str(values.get(key)) != str(here[key]):
                        rerun.note(f"recorded with {key} {values.get(key)}, re-run with {here[key]}")
            elif item.topic == TOPIC_EVENT and values["event"] == "snapshot_end":
                skipping = False
            elif not skipping:
                rerun.message(item, values)
    finally:
        if rerun.core is not None:
            rerun.core.close_recording()
    rerun.report.files = [str(p) for p in state.files]
    rerun.report.truncated = state.truncated
    return rerun.report
