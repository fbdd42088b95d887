"""What the stream core hands out, as plain data: poses, diagnostics and their levels, names and key/values."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from liver_p2p_reg.cloud_io import implausible_extent
from liver_p2p_reg.config import Config
from liver_p2p_reg.registration.confidence import result_warnings
from liver_p2p_reg.result import RegistrationResult
from liver_p2p_reg.structures_io import PlacedStructure, structure_bounds

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR", STALE: "STALE"}
DIAG_NAME = "liver_p2p_reg: registration"
PREOP_DIAG_NAME = "liver_p2p_reg: preop model"
LOADER_DIAG_NAME = "liver_p2p_reg: preop loader"  # preop_loader_node's status: the files it read, or why not
HARDWARE_ID = "liver_p2p_reg"


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
    structures: list[PlacedStructure] = field(default_factory=list)  # moved into the sensor frame by the pose
    # the preop surface after the non-rigid stage (sensor frame, mm): the /preop/mesh's welded vertices in their
    # order when the stage ran on that mesh, else the /preop/points; None: the stage was off or not applied
    deformed_preop_mm: np.ndarray | None = None

    @property
    def level(self) -> int:
        return max((d.level for d in self.diagnostics), default=OK)

    @property
    def summary(self) -> str:
        return "; ".join(d.message for d in self.diagnostics)


def units_warning(extent: float, what: str, config: Config) -> str:
    """Why a cloud of this extent (mm) is in the wrong units, with the ROS convention's hint; "" when plausible."""
    problem = implausible_extent(extent, what, config.expected_extent_min_mm, config.expected_extent_max_mm)
    if not problem:
        return ""
    if extent > config.expected_extent_max_mm:
        return problem + " (ROS messages must be in metres; millimetre values published as metres look 1000x too large)"
    return problem + " (ROS messages must be in metres; a liver is 0.05-0.3 m across)"


def registered_diagnostic(
    result: RegistrationResult,
    values: dict[str, str],
    warnings: list[str],
    config: Config,
    structures: list[PlacedStructure] | None = None,
) -> Diagnostic:
    """The diagnostic of a frame registered to a valid pose: how (tracked or registered), residual,
    RMS-TRE, and WARN with every reason (the frame's own `warnings`, then the result's, whose
    error-bound rule follows the structures' bounds when there are structures)."""
    verb = "tracked from the previous pose" if result.method == "track" else "registered"
    message = f"{verb}: residual {result.residual_mm:.2f} mm"
    if result.rms_tre_mm is not None:
        message += f", RMS-TRE {result.rms_tre_mm:.2f} mm"
    bounds = structure_bounds(structures or [])
    if bounds:
        worst = max((float(np.max(b)) for b in bounds.values() if len(b)), default=float("nan"))
        values["structures"] = str(len(bounds))
        values["structure_error_bound_max_mm"] = f"{worst:.3f}"
    reasons = result_warnings(result, config, structure_bounds_mm=bounds or None)
    # machine-readable why (the tracker keeps a pose that only its error bound warns as the next prior)
    values["warn_reasons"] = ",".join([*(["input"] if warnings else []), *reasons])
    warnings = [*warnings, *reasons.values()]
    level = OK
    if warnings:
        level = WARN
        message += " (" + "; ".join(warnings) + ")"
    return Diagnostic(level, DIAG_NAME, message, values)


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
    if not np.isnan(result.error_bound_mm):  # inf: unconstrained, and said so
        values["error_bound_mm"] = f"{result.error_bound_mm:.3f}"
        values["error_coverage"] = f"{result.error_coverage:g}"
    if result.error_calibration_note:
        values["error_calibration_note"] = result.error_calibration_note
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
