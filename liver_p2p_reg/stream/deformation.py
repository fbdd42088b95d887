"""The node core's non-rigid stage: the preop mesh it is built on, the elastic model's warm-up, the stage after each pose.

The stage runs after the rigid pose has gone out, on the same model and frame, and never changes the
pose or the verdict: a stage that is not applied only says why (`deform_reason`). Its surface is the
/preop/mesh of the current model (same frame and stamp as its /preop/points) when one arrived, else
the surface rebuilt from the points; the deformed surface it outputs is then that mesh's welded vertices, in
their order (its triangles pair with them), else the deformed /preop/points.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.registration.deform import Deformation, not_applied
from liver_p2p_reg.registration.error_calibration import FRAME, SURVEY
from liver_p2p_reg.registration.registrar import Registrar
from liver_p2p_reg.stream.outputs import OK, PREOP_DIAG_NAME, WARN, CoreOutput, Diagnostic
from liver_p2p_reg.stream.solve import Frame
from liver_p2p_reg.structures_io import Structure, place_structures

LOG = logging.getLogger("liver_p2p_reg.node")
# A CT liver mesh has 10^4-10^5 triangles; one of 300k triangles took 3 GB and 35 s to build on: 10^6 is refused.
MAX_MESH_TRIANGLES = 1_000_000
MESHES_KEPT = 4  # meshes kept for models of other stamps (the next model's may come before its points)


@dataclass(frozen=True)
class PreopMesh:
    """A closed preop mesh: welded vertices (mm, preop frame) and triangles indexing them, of the model stamped so."""

    vertices_mm: np.ndarray  # (V, 3)
    triangles: np.ndarray  # (F, 3) int64
    frame_id: str
    stamp_ns: int

    @property
    def stage_kwargs(self) -> dict[str, np.ndarray]:
        """The Registrar's arguments for this surface."""
        return {"source_triangles": self.triangles, "mesh_vertices_mm": self.vertices_mm}


def checked_mesh(
    vertices_mm: np.ndarray,
    triangles: np.ndarray,
    frame_id: str,
    stamp_ns: int,
    max_triangles: int | None = MAX_MESH_TRIANGLES,
) -> PreopMesh:
    """A PreopMesh of finite vertices and triangles that index them; InputError (one line) when it is not one.
    `max_triangles`: the most a mesh to deform on may have (None: no limit, for a mesh about to be decimated)."""
    vertices = np.asarray(vertices_mm, dtype=np.float64)
    tris = np.asarray(triangles)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 4:
        raise InputError(f"a mesh needs (V >= 4, 3) vertices, got shape {vertices.shape}")
    if not np.isfinite(vertices).all():
        raise InputError("mesh vertices must all be finite")
    if tris.ndim != 2 or tris.shape[1] != 3 or len(tris) == 0 or tris.dtype.kind not in "iu":
        raise InputError(f"mesh triangles must be a non-empty (F, 3) integer array, got shape {tris.shape}")
    if tris.min() < 0 or tris.max() >= len(vertices):
        raise InputError(f"mesh triangles index vertex {int(tris.max())} of {len(vertices)}")
    if max_triangles is not None and len(tris) > max_triangles:
        raise InputError(f"mesh of {len(tris)} triangles (more than {max_triangles}); decimate it")
    return PreopMesh(vertices, tris.astype(np.int64), frame_id or "ct", int(stamp_ns))


def mesh_fit_problem(mesh: PreopMesh, points_mm: np.ndarray) -> str:
    """Why `mesh` is not the surface of the model with these points ("" when they lie on it): a frame and a stamp
    do not tell two models apart (every bundled bag stamps its model alike), so the geometry must."""
    from liver_p2p_reg.cloud_io import sample_mesh_surface
    from liver_p2p_reg.registration.nearest import NearestIndex

    used = np.unique(mesh.triangles)  # a vertex no triangle uses is no part of the surface
    surface = sample_mesh_surface(mesh.vertices_mm[used], np.searchsorted(used, mesh.triangles), seed=0)
    if len(surface) == len(used):  # no sample drawn: the triangles have no area
        return "its triangles have no area"
    points = np.asarray(points_mm, dtype=np.float64)
    distances, _ = NearestIndex(surface).query(points[:: max(len(points) // 2000, 1)])
    p90_mm = float(np.quantile(distances, 0.9))
    tolerance_mm = max(3.0, 0.02 * float(np.linalg.norm(np.ptp(points, axis=0))))
    if p90_mm <= tolerance_mm:
        return ""
    return (
        f"its /preop/mesh of the same frame and stamp lies {p90_mm:.1f} mm from the model's points (90th "
        f"percentile; tolerance {tolerance_mm:.1f} mm): not this model's surface, not used"
    )


class MeshStore:
    """The latest preop meshes received (one per frame and stamp, the last MESHES_KEPT); each serves only the model
    of its frame and stamp whose points lie on its surface."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._meshes: dict[tuple[str, int], PreopMesh] = {}
        self._fits: list[tuple[PreopMesh, np.ndarray, str]] = []  # the last answers of mesh_fit_problem

    def set(self, mesh: PreopMesh) -> None:
        with self._lock:
            key = (mesh.frame_id, mesh.stamp_ns)
            self._meshes.pop(key, None)
            self._meshes[key] = mesh  # the newest last
            while len(self._meshes) > MESHES_KEPT:
                self._meshes.pop(next(iter(self._meshes)))

    def for_model(self, frame_id: str, stamp_ns: int, points_mm: np.ndarray | None = None) -> PreopMesh | None:
        """The mesh of the model with this frame, stamp and points, or None (the surface is then rebuilt from its
        points); `find` says why a mesh of that frame and stamp was not taken."""
        return self.find(frame_id, stamp_ns, points_mm)[0]

    def judge_kwargs(
        self, config: Config, frame_id: str, stamp_ns: int, points_mm: np.ndarray
    ) -> dict[str, np.ndarray]:
        """The model's mesh as the Registrar's arguments when the contenders' judge is on, so that it judges on the
        stage's own elastic model; {} otherwise (or without a mesh: the surface is then rebuilt from the points)."""
        mesh = self.for_model(frame_id, stamp_ns, points_mm) if config.contender_judge_ratio else None
        return {} if mesh is None else mesh.stage_kwargs

    def find(self, frame_id: str, stamp_ns: int, points_mm: np.ndarray | None) -> tuple[PreopMesh | None, str]:
        """(the mesh of this model or None, why a mesh of its frame and stamp does not serve it: "" when it does or
        when there is none)."""
        with self._lock:
            mesh = self._meshes.get((frame_id, int(stamp_ns)))
            if mesh is None or points_mm is None:
                return mesh, ""
            known = next((p for m, pts, p in self._fits if m is mesh and pts is points_mm), None)
        if known is None:  # once per mesh and model (~20 ms), outside the lock
            known = mesh_fit_problem(mesh, points_mm)
            with self._lock:
                self._fits = [*self._fits[-(2 * MESHES_KEPT - 1) :], (mesh, points_mm, known)]
        return (None if known else mesh), known


def rigid_registrar(config: Config, registrar: Registrar | None = None) -> Registrar:
    """The registrar of the rigid pose: `registrar` (or one of `config`) without the non-rigid stage, which the
    core runs itself once the pose is out; a replacement shares the given registrar's cache."""
    if registrar is not None and not registrar.config.deform:
        return registrar
    rigid = Registrar((registrar.config if registrar is not None else config).replace(deform=False))
    if registrar is not None:
        rigid.cache = registrar.cache
    return rigid


def surface_name(mesh: PreopMesh | None) -> str:
    """Which surface the elastic model is built on: `mesh` or `points` (rebuilt from /preop/points)."""
    return "points" if mesh is None else "mesh"


def prepare_stage(registrar: Registrar, preop_mm: np.ndarray, mesh: PreopMesh | None) -> dict[str, str]:
    """Build (and cache) the model's elastic model now; the preop diagnostic's `deform_*` values ("" problem: ready)."""
    start = time.perf_counter()
    try:
        problem = registrar.prepare_deformation(preop_mm, **({} if mesh is None else mesh.stage_kwargs))
    except LiverP2PError as exc:
        problem = f"no elastic model: {exc}"
    except Exception as exc:  # the node must outlive it; the stage then says why on every frame
        LOG.exception("building the elastic model raised")
        problem = f"no elastic model: {type(exc).__name__}: {exc}"
    return {
        "deform_model": problem or "ready",
        "deform_surface": surface_name(mesh),
        "deform_model_ms": f"{(time.perf_counter() - start) * 1e3:.1f}",
    }


@dataclass(frozen=True)
class PreparedStage:
    """The outcome of preparing the elastic model: the preop diagnostic's `deform_*` values, on which surface."""

    values: dict[str, str]
    mesh: PreopMesh | None

    def diagnostic(self, base: Diagnostic | None = None) -> Diagnostic:
        """The preop model's diagnostic (`base`: the model's warm-up, its values added); WARN when the stage cannot run."""
        values, mesh = self.values, self.mesh
        problem = "" if values["deform_model"] == "ready" else values["deform_model"]
        ignored = values.get("deform_mesh_problem", "")  # a mesh that is not this model's: said, and a WARN
        if base is not None:
            message = base.message + (f"; non-rigid stage unavailable: {problem}" if problem else "")
            message += f"; {ignored}" if ignored else ""
            level = WARN if problem or ignored else base.level
            return Diagnostic(level, base.name, message, {**base.values, **values})
        built = (
            f"its mesh ({len(mesh.triangles)} triangles)" if mesh is not None else "the surface rebuilt from its points"
        )
        message = f"non-rigid stage unavailable: {problem}" if problem else f"elastic model built on {built}"
        message += f"; {ignored}" if ignored else ""
        return Diagnostic(WARN if problem or ignored else OK, PREOP_DIAG_NAME, message, values)


class ElasticPreparation:
    """What the elastic model was last prepared for (model points, mesh, settings), so that a repeat is skipped."""

    def __init__(self) -> None:
        self._for: tuple[Any, ...] | None = None
        self._problem = ""  # why the last mesh of the model was refused (said once per mesh)

    def prepare(
        self,
        registrar: Registrar,
        config: Config,
        points: np.ndarray | None,
        mesh: PreopMesh | None,
        mesh_problem: str = "",
        *,
        force: bool = False,
    ) -> PreparedStage | None:
        """Prepare it when `deform` is on and (or `force`) it was not prepared for these; None when nothing was done.
        `mesh_problem`: why a /preop/mesh of the model's frame and stamp was not taken (said in the diagnostic)."""
        if not (config.deform or config.contender_judge_ratio > 0) or points is None:  # the judge needs the model too
            return None
        key = (points, mesh, config.deform_modes, config.deform_target_tets)
        if not force and self._for is not None and all(a is b for a, b in zip(key, self._for, strict=True)):
            if not mesh_problem or mesh_problem == self._problem:
                return None
        self._problem = mesh_problem
        self._for = key
        values = prepare_stage(registrar, points, mesh)
        if mesh_problem:
            values["deform_mesh_problem"] = mesh_problem
        return PreparedStage(values, mesh)


def mesh_diagnostic(mesh: PreopMesh, for_current_model: bool) -> Diagnostic:
    """What register_node says when a /preop/mesh arrives (OK: kept for the model of its stamp)."""
    waits = "" if for_current_model else "; kept for the model of its stamp"
    values = {
        "mesh_vertices": str(len(mesh.vertices_mm)),
        "mesh_triangles": str(len(mesh.triangles)),
        "frame_id": mesh.frame_id,
        "stamp_ns": str(mesh.stamp_ns),
        "for_current_model": str(bool(for_current_model)).lower(),
    }
    message = f"preop mesh received ({len(mesh.triangles)} triangles, {len(mesh.vertices_mm)} vertices){waits}"
    return Diagnostic(OK, PREOP_DIAG_NAME, message, values)


def stage_values(
    deformation: Deformation,
    mesh: PreopMesh | None,
    ms: float,
    tre_mm: float | None,
    bound_mm: float | None = None,
    bound_note: str = "",
    *,
    view: str = FRAME,
    view_points: int = 0,
) -> dict[str, str]:
    """The registration diagnostic's `deform_*` key/values (`bound_mm`: the deformed positions' interior bound;
    `view`: what the stage fitted, `frame` or `survey`, and its `view_points`)."""
    values = {
        "deform_applied": str(bool(deformation.applied)).lower(),
        "deform_reason": deformation.reason,
        "deform_surface": surface_name(mesh),
        "deform_view": view,
        "deform_view_points": str(view_points),
        "deform_rms_displacement_mm": f"{deformation.rms_displacement_mm:.3f}",
        "deform_max_displacement_mm": f"{deformation.max_displacement_mm:.3f}",
        "deform_residual_before_mm": f"{deformation.residual_before_mm:.3f}",
        "deform_residual_after_mm": f"{deformation.residual_after_mm:.3f}",
        "deform_holdout_gain": f"{deformation.holdout_gain:.3f}",
        "deform_ms": f"{ms:.1f}",
    }
    if tre_mm is not None and deformation.applied:
        values["deformed_rms_tre_mm"] = f"{tre_mm:.3f}"
    if bound_mm is not None and deformation.applied:
        values["deformed_error_bound_mm"] = f"{bound_mm:.3f}"
    if bound_note and deformation.applied:
        values["deformed_error_calibration_note"] = bound_note
    return values


def run_stage(
    registrar: Registrar,
    rigid: CoreOutput,
    frame: Frame,
    structures: list[Structure],
    mesh: PreopMesh | None,
    view_mm: np.ndarray | None = None,
) -> CoreOutput:
    """The non-rigid stage on a registered frame (its pose already out): the same output with the `deform_*`
    values and, when applied, the deformed preop surface (the mesh's welded vertices when it ran on `mesh`, else
    the model's points; sensor frame, mm) and structures. `view_mm`: what it fits instead of the frame's points
    (the survey's fused surface, in the frame's sensor frame). Never raises; pose and verdict stand."""
    result, start = rigid.result, time.perf_counter()
    view, fitted = (frame.points_mm, FRAME) if view_mm is None else (view_mm, SURVEY)
    T = np.asarray(result.T_target_source, dtype=np.float64).copy()
    kwargs: dict[str, Any] = {"source_fiducials_mm": frame.fid_s, "target_fiducials_mm": frame.fid_t}
    kwargs.update({} if mesh is None else mesh.stage_kwargs)
    deformed, placed = None, rigid.structures
    try:
        registrar.deform(result, frame.preop_mm, view, **kwargs, view=fitted)
        if result.deformation.applied:
            # on a mesh: its vertices, so that a holder of /preop/mesh (welded alike) pairs them with its triangles
            surface = frame.preop_mm if mesh is None else mesh.vertices_mm
            deformed = result.deformation.deformed_position_mm(surface)
            placed = place_structures(result, structures)  # the rigid positions and bounds, the deformed positions
    except LiverP2PError as exc:
        _stands(result, T, f"not run: {exc}")
        deformed, placed = None, rigid.structures
    except Exception as exc:  # the node must outlive anything the stage raises
        LOG.exception("the non-rigid stage raised")
        _stands(result, T, f"crashed: {type(exc).__name__}: {exc}")
        deformed, placed = None, rigid.structures
    result.T_target_source = T  # the rigid pose is the published one, whatever happened
    ms = (time.perf_counter() - start) * 1e3
    diag = rigid.diagnostics[0]
    deformation: Deformation = result.deformation
    seen = {"view": fitted, "view_points": len(view)}
    values = {**diag.values, **stage_values(deformation, mesh, ms, result.deformed_rms_tre_mm, *_bound(result), **seen)}
    diagnostics = [Diagnostic(diag.level, diag.name, diag.message, values, diag.hardware_id), *rigid.diagnostics[1:]]
    return dataclasses.replace(rigid, diagnostics=diagnostics, structures=placed, deformed_preop_mm=deformed)


def _stands(result: Any, T: np.ndarray, reason: str) -> None:
    """The rigid result stands: the stage's outputs on `result` say so, none of its deformed values remain."""
    result.deformation, result.deformed_rms_tre_mm = not_applied(T, reason), None
    result.deformed_error_model, result.deformed_error_bound_mm = None, float("nan")
    result.deformed_error_calibration_note = ""


def _bound(result: Any) -> tuple[float | None, str]:
    """The deformed positions' interior bound (None without one) and its calibration note."""
    bound = result.deformed_error_bound_mm if result.deformed_error_model is not None else None
    return bound, result.deformed_error_calibration_note
