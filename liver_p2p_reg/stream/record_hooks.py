"""The flight recorder's hook in the stream core: what NodeCore tells a recorder and when (bags/recorder.py writes it).

NodeCore holds one `Recording`: it opens a recorder from the factory when `config.record_path` is
set ("" = off), closes it when the path changes, writes a snapshot of the core's state at the head of
every file (the config, the current model, its mesh and fiducials, the tracking prior) and hands every
model, mesh, fiducial set, parameter change, survey reset and registration (with the structures it moved) over
in the order they took effect. A recorder that fails (disk full, ...) is dropped with one ERROR: registrations go on.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.stream.intake import IntraopCloud
from liver_p2p_reg.stream.outputs import CoreOutput

if TYPE_CHECKING:
    from liver_p2p_reg.stream.core import NodeCore
    from liver_p2p_reg.stream.deformation import PreopMesh
    from liver_p2p_reg.structures_io import Structure

LOG = logging.getLogger("liver_p2p_reg.node")


@dataclass
class RegistrationRecord:
    """One registration as the core ran it: its inputs exactly as registered, its reason and its output."""

    reason: str  # continuous | once | survey | reregister (register: the CLI's)
    frame_id: str
    stamp_ns: int
    points_mm: np.ndarray | None  # what the cloud's decoder returned (finite, mm); None: never decoded
    n_raw: int  # the cloud's raw point count (width x height)
    decode_error: str  # the decoder's InputError ("" if none)
    fiducials_mm: tuple[np.ndarray, np.ndarray] | None  # the (preop, intraop) pair the registration used
    output: CoreOutput  # its deformed_preop_mm and `deform_*` diagnostic values: the non-rigid stage's, when it ran
    extras: dict[str, Any] = field(default_factory=dict)  # the CLI's: sensor_origin_mm, initial_T_mm
    # the subsurface structures (preop frame) it moved, as named then; None: it placed none (no pose, nothing given)
    structures: list[Structure] | None = None


class Recorder(Protocol):
    """What the core calls; `snapshot` marks the state written at the head of a file (not a change)."""

    path: str  # the file being written now

    def config(self, config: Config, snapshot: bool = False) -> None: ...

    def preop(self, points_mm: np.ndarray, frame_id: str, stamp_ns: int, snapshot: bool = False) -> None: ...

    def preop_fiducials(self, points_mm: np.ndarray | None, stamp_ns: int, snapshot: bool = False) -> None: ...

    def preop_mesh(self, mesh: PreopMesh, snapshot: bool = False) -> None: ...  # the non-rigid stage's surface

    def event(self, name: str, values: dict[str, Any] | None = None) -> None: ...

    def registration(self, record: RegistrationRecord) -> None: ...  # written and flushed

    def rotate_due(self) -> bool: ...

    def rotate(self) -> None: ...  # close this file, open the next numbered one (the snapshot follows)

    def close(self) -> None: ...


# (record_path, the config) -> an open Recorder; raises InputError when the path cannot be written
RecorderFactory = Callable[[str, Config], Recorder]


class _Tap:
    """A cloud's decoder that keeps what it returned (or why it failed), to record the input as registered."""

    def __init__(self, decode: Callable[[], tuple[np.ndarray, int]]) -> None:
        self._decode = decode
        self.points: np.ndarray | None = None
        self.n_raw = 0
        self.error = ""

    def __call__(self) -> tuple[np.ndarray, int]:
        try:
            self.points, self.n_raw = self._decode()
        except InputError as exc:
            self.error = str(exc)
            raise
        return self.points, self.n_raw


class Recording:
    """The core's recording: follows config.record_path; thread-safe; never raises into a registration."""

    def __init__(self, factory: RecorderFactory | None, core: NodeCore) -> None:
        self._factory = factory
        self._core = core
        self._lock = threading.Lock()
        self._recorder: Recorder | None = None
        self._path = ""  # the record_path followed
        self._failure = ""
        self._tap: _Tap | None = None
        self._pair: tuple[np.ndarray, np.ndarray] | None = None
        self._structures: list[Structure] | None = None

    def follow(self, config: Config) -> None:
        """A new config: recorded, or the recording closed / opened when record_path changed.
        InputError when the new path cannot be opened (nothing changed then)."""
        with self._lock:
            if config.record_path == self._path:
                self._call(lambda r: r.config(config))
                return
            if config.record_path and self._factory is None:
                raise InputError("record_path is set but this core has no recorder (flight recording unavailable)")
            recorder = self._factory(config.record_path, config) if config.record_path else None
            if self._recorder is not None:
                self._call(lambda r: r.close())
            self._recorder, self._path, self._failure = recorder, config.record_path, ""
            self._call(lambda r: self._snapshot(r, config))

    def _snapshot(self, recorder: Recorder, config: Config) -> None:
        core = self._core
        recorder.config(config, snapshot=True)
        if core.preop_mm is not None:
            mesh = core.mesh.for_model(core.preop_frame, core.preop_stamp_ns, core.preop_mm)
            if mesh is not None:  # before its points, as bags log it: a re-run builds the elastic model once
                recorder.preop_mesh(mesh, snapshot=True)
            recorder.preop(core.preop_mm, core.preop_frame, core.preop_stamp_ns, snapshot=True)
            if core.preop_fiducials_mm is not None:
                recorder.preop_fiducials(core.preop_fiducials_mm, core.preop_stamp_ns, snapshot=True)
        track = core._tracker.state  # the prior the next tracked frame starts from
        if track is not None:
            values = {"T_mm": track.T_mm.tolist(), "reference_residual_mm": track.reference_residual_mm}
            recorder.event("tracker", {**values, "frame_id": track.frame_id, "frames": track.frames})
        recorder.event("snapshot_end")

    def _call(self, write: Callable[[Recorder], None]) -> None:
        """write(recorder) if recording; a failure drops the recorder with one ERROR (under self._lock)."""
        if self._recorder is None:
            return
        try:
            write(self._recorder)
        except Exception as exc:
            self._failure = f"{type(exc).__name__}: {exc}"
            LOG.error("flight recorder %s failed, recording stopped: %s", self._recorder.path, self._failure)
            recorder, self._recorder = self._recorder, None
            try:
                recorder.close()
            except Exception:
                pass

    def preop(self, points_mm: np.ndarray, frame_id: str, stamp_ns: int) -> None:
        with self._lock:
            self._call(lambda r: r.preop(points_mm, frame_id, stamp_ns))

    def preop_fiducials(self, points_mm: np.ndarray | None, stamp_ns: int | None) -> None:
        stamp = self._core.preop_stamp_ns if stamp_ns is None else int(stamp_ns)
        with self._lock:
            self._call(lambda r: r.preop_fiducials(points_mm, stamp))

    def preop_mesh(self, mesh: PreopMesh) -> None:
        with self._lock:
            self._call(lambda r: r.preop_mesh(mesh))

    def event(self, name: str) -> None:
        with self._lock:
            self._call(lambda r: r.event(name))

    # ---------------------------------------------------------------- one registration (under the core's lock)
    def begin(self, cloud: IntraopCloud) -> IntraopCloud:
        """The cloud to register: with a decoder that keeps its points while recording."""
        self._tap, self._pair, self._structures = None, None, None
        if self._recorder is None:
            return cloud
        self._tap = _Tap(cloud.decode)
        return IntraopCloud(cloud.frame_id, cloud.stamp_ns, self._tap, cloud.received_s, cloud.waiting_since_s)

    def paired(self, fid_s: np.ndarray | None, fid_t: np.ndarray | None) -> None:
        """The fiducial pair the registration uses (None, None: no TRE)."""
        self._pair = None if fid_s is None or fid_t is None else (fid_s, fid_t)

    def moved(self, structures: list[Structure]) -> list[Structure]:
        """The structures the registration moves with its pose (a set that came meanwhile waits for the next);
        returns them."""
        self._structures = list(structures)
        return structures

    def registration(self, cloud: IntraopCloud, reason: str, output: CoreOutput) -> None:
        tap = self._tap
        if tap is None:
            return
        record = RegistrationRecord(
            reason, cloud.frame_id, cloud.stamp_ns, tap.points, tap.n_raw, tap.error, self._pair, output,
            structures=self._structures,
        )  # fmt: skip
        with self._lock:
            self._call(lambda r: r.registration(record))
            self._call(lambda r: r.rotate_due() and (r.rotate(), self._snapshot(r, self._core.config)))

    def close(self) -> None:
        with self._lock:
            self._call(lambda r: r.close())
            self._recorder = None

    def status(self) -> dict[str, str]:
        """Diagnostic values: the file being written, or why recording stopped (none when off)."""
        if self._failure:
            return {"recording": f"failed: {self._failure}"}
        recorder = self._recorder
        return {"recording": recorder.path} if recorder is not None else {}


def restore_tracker(core: NodeCore, values: dict[str, Any]) -> None:
    """Give a core the tracking prior a recording's head carries (its `tracker` event), as `_snapshot` wrote it."""
    from liver_p2p_reg.stream.tracking import TrackState

    T = np.asarray(values["T_mm"], dtype=np.float64)
    core._tracker.state = TrackState(
        T, float(values["reference_residual_mm"]), values["frame_id"], int(values["frames"])
    )
