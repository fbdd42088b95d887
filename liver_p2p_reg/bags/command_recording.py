"""`liver-p2p register --record`: the command's flight recording (config, SOURCE, mesh, then its registrations)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from liver_p2p_reg.bags.io import rosbags_marker_types
from liver_p2p_reg.bags.recorded_points import exact_metres
from liver_p2p_reg.bags.recorder import McapRecorder
from liver_p2p_reg.config import Config
from liver_p2p_reg.ros.messages import mesh_marker_mm, triangle_list_marker
from liver_p2p_reg.stream.record_hooks import RegistrationRecord

if TYPE_CHECKING:
    from liver_p2p_reg.stream.deformation import PreopMesh
    from liver_p2p_reg.stream.outputs import CoreOutput
    from liver_p2p_reg.structures_io import Structure


def open_command_recording(
    path: str | Path,
    config: Config,
    source_mm: np.ndarray,
    *,
    overwrite: bool,
    mesh: tuple[np.ndarray, np.ndarray] | None = None,
) -> McapRecorder:
    """A recording of `liver-p2p register`: the config, SOURCE and (with `deform`) SOURCE's mesh as its head;
    registrations follow. The mesh is kept as /preop/mesh, as the node's recordings keep theirs."""
    recorder = McapRecorder(str(path), config, existing="overwrite" if overwrite else "refuse")
    recorder.command_mesh = command_mesh(mesh) if mesh is not None and config.deform else None
    _command_head(recorder, config, source_mm)
    return recorder


def command_mesh(mesh: tuple[np.ndarray, np.ndarray]) -> PreopMesh:
    """SOURCE's mesh as a re-run reads it back from /preop/mesh (corners welded, vertices sorted). The stage's
    result does not depend on the vertices' order (checked bitwise on a permuted liver mesh), so the deformed
    surface on these vertices is what the re-run must reproduce bit for bit."""
    from liver_p2p_reg.stream.deformation import PreopMesh

    vertices, triangles = (np.asarray(a) for a in mesh)
    marker = triangle_list_marker(exact_metres(vertices), triangles, rosbags_marker_types(), "ct", 0)
    return PreopMesh(*mesh_marker_mm(marker), "ct", 0)


def _command_head(recorder: McapRecorder, config: Config, source_mm: np.ndarray) -> None:
    recorder.config(config, snapshot=True)
    recorder.preop(source_mm, "ct", 0, snapshot=True)
    if recorder.command_mesh is not None:
        recorder.preop_mesh(recorder.command_mesh, snapshot=True)
    recorder.event("snapshot_end")


def record_command_registration(
    recorder: McapRecorder,
    index: int,
    target: str,
    target_mm: np.ndarray,
    fiducials: tuple[np.ndarray | None, np.ndarray | None],
    extras: dict[str, Any],
    result: Any,
    config: Config,
    source_mm: np.ndarray,
    structures: list[Structure] | None = None,
) -> None:
    """One registration of `liver-p2p register` (reason `register`; `result` a RegistrationResult or the
    LiverP2PError it raised); rotates beyond record_max_mb like the node's recordings. `structures`: the
    command's --structures, placed as the command places them (`place_structures(result, structures)`)."""
    output = command_output(result, index, target, config, source_mm, recorder.command_mesh, structures)
    fid_s, fid_t = fiducials
    pair = None if fid_s is None or fid_t is None else (np.asarray(fid_s), np.asarray(fid_t))
    points = np.asarray(target_mm, dtype=np.float64).reshape(-1, 3)
    moved = None if isinstance(result, Exception) else list(structures or [])
    record = RegistrationRecord("register", target, index, points, len(points), "", pair, output, extras, moved)
    recorder.registration(record)
    if recorder.rotate_due():
        recorder.rotate()
        _command_head(recorder, config, source_mm)


def command_output(
    result: Any,
    index: int,
    target: str,
    config: Config,
    source_mm: np.ndarray,
    mesh: PreopMesh | None,
    structures: list[Structure] | None,
) -> CoreOutput:
    """One registration of `liver-p2p register` in the node's output form: the verdict (the diagnostic), the
    pose, the placed structures and, with the stage applied, the deformed surface. `result`: a RegistrationResult
    (with `deform`, its stage already run) or the LiverP2PError it raised (ERROR, no pose). What the command's
    recording keeps and what its re-run compares with it."""
    from liver_p2p_reg.registration.confidence import origin_warnings
    from liver_p2p_reg.stream.outputs import (
        DIAG_NAME,
        ERROR,
        CoreOutput,
        Diagnostic,
        PoseOutput,
        registered_diagnostic,
        result_values,
    )
    from liver_p2p_reg.structures_io import place_structures

    if isinstance(result, Exception):
        return CoreOutput([Diagnostic(ERROR, DIAG_NAME, f"registration failed: {result}")], reason="register")
    values, deformed = result_values(result), None
    if result.deformation is not None:  # deform on: its values, and the deformed surface the re-run must match
        values, deformed = command_deformation(result, mesh, source_mm, values)
    placed = place_structures(result, structures or [])
    # the verdict follows their bounds, and the command's own warning, as its JSON's status
    diag = registered_diagnostic(result, values, origin_warnings(result), config, placed)
    pose = PoseOutput(index, target, "ct", np.asarray(result.T_target_source, dtype=np.float64))
    return CoreOutput([diag], pose, result=result, reason="register", structures=placed, deformed_preop_mm=deformed)


def command_deformation(
    result: Any, mesh: PreopMesh | None, source_mm: np.ndarray, values: dict[str, str]
) -> tuple[dict[str, str], np.ndarray | None]:
    """A `register` result's non-rigid stage as the node would record it: the diagnostic's `deform_*` values and,
    when applied, the deformed surface (the mesh's vertices as /preop/mesh reads back, else SOURCE's points)."""
    from liver_p2p_reg.stream.deformation import stage_values

    deformation = result.deformation
    ms = float(result.runtime_ms.get("deform", 0.0))
    values = {**values, **stage_values(deformation, mesh, ms, result.deformed_rms_tre_mm)}
    if not deformation.applied:
        return values, None
    surface = source_mm if mesh is None else mesh.vertices_mm
    return values, deformation.deformed_position_mm(np.asarray(surface, dtype=np.float64))
