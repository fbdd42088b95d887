"""The error bound's split-conformal calibration: reading it, and turning a pose's evidence into bounds (mm)."""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from liver_p2p_reg.config import FeatureSection, FreeSpaceSection, IcpSection, P2PSection, PreprocessSection
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.error_bound import FEATURES, INTERIOR_STAND_IN, RIVAL_RATIO_CAP, PoseEvidence
from liver_p2p_reg.registration.methods import canonical_method
from liver_p2p_reg.registration.weights_id import weights_sha256

BUNDLED_CALIBRATION = Path(__file__).resolve().parents[1] / "weights" / "error_bound_v1.json"
# The bound of the positions the non-rigid stage gives, calibrated on the validation poses where it was applied.
BUNDLED_DEFORMED_CALIBRATION = BUNDLED_CALIBRATION.with_name("error_bound_deformed_v1.json")
# ... and where the stage fitted survey mode's fused sweep (scripts/calibrate_survey_bound.py): far more accurate
# than on one view, which the frame's pose evidence does not show
BUNDLED_SURVEY_CALIBRATION = BUNDLED_CALIBRATION.with_name("error_bound_deformed_survey_v1.json")
# ... and the rigid pose of a frame tracked on survey mode's fused surface (scored on the frame alone by
# SURVEY_TRACKED_METHOD): more accurate than a single view's global registration, which its evidence does not show
BUNDLED_SURVEY_RIGID_CALIBRATION = BUNDLED_CALIBRATION.with_name("error_bound_survey_v1.json")
SURVEY_TRACKED_METHOD = "evaluate"
RIGID, DEFORMED = "rigid", "deformed"  # which positions a calibration's errors were measured at
FRAME, SURVEY = "frame", "survey"  # what the non-rigid stage fitted: one frame, or survey mode's fused surface
FORMAT = "liver_p2p_reg error-bound calibration"


def error_scale_mm(features: np.ndarray, coefficients: np.ndarray) -> np.ndarray:
    """The scale model exp(features . coefficients) (mm) of each row; inf where it is not finite. The coefficients
    follow a prefix of FEATURES (a calibration of fewer features): the columns beyond it are not used at all, so
    such a calibration's bound is bitwise what it was before the later features existed."""
    coefficients = np.asarray(coefficients, float)
    with np.errstate(over="ignore", invalid="ignore"):
        scale = np.exp(np.asarray(features, float)[..., : len(coefficients)] @ coefficients)
    return np.where(np.isfinite(scale), scale, np.inf)


def group_index(
    visibility: Any, rival_ratio: Any, visibility_edges: tuple[float, ...], rival_edges: tuple[float, ...] = ()
) -> np.ndarray:
    """The quantiles' group of each pose: its visibility group (its voxelized M/N, known at run time; 0 where not
    finite) plus, with rival edges, its rival class (its best rival's residual over the best; at or above an edge:
    clear; not finite: clear) times the number of visibility groups. The product and the calibration's bench both
    group poses here, so a judged bound is the bound the product computes."""
    v = np.where(np.isfinite(visibility), visibility, 0.0)
    r = np.where(np.isfinite(rival_ratio), rival_ratio, RIVAL_RATIO_CAP)
    by_visibility = np.searchsorted(np.asarray(visibility_edges, float), v, side="right")
    rival_class = np.searchsorted(np.asarray(rival_edges, float), r, side="right")  # no edges: 0
    return by_visibility + (len(visibility_edges) + 1) * rival_class


@dataclass(frozen=True)
class BoundCalibration:
    """Scale model exp(features . coefficients) and, per group (visibility, and rival class where the calibration
    has rival edges) and coverage, conformal quantiles."""

    coefficients: np.ndarray  # (k,): of the first k FEATURES (files made before log_halves: the first seven)
    visibility_edges: tuple[float, ...]  # groups: below the first edge, between edges, above the last
    coverages: tuple[float, ...]
    point_quantiles: np.ndarray  # (groups, coverages): error / scale at one point
    pose_quantiles: np.ndarray  # (groups, coverages): interior RMS error / RMS scale over the interior's stand-in
    weights_sha256: str  # of the matcher weights the calibration ran with ("" for a method without weights)
    method: str
    provenance: dict[str, Any]  # data, seed, command: what `liver-p2p calibrate-bound` recorded
    positions: str = RIGID  # RIGID: the pose's; DEFORMED: the non-rigid stage's (of `deform` settings)
    deform: dict[str, Any] | None = None  # the non-rigid stage's settings a DEFORMED calibration ran with
    view: str = FRAME  # the poses or fits it was made of: of single frames, or survey mode's (fused surveys)
    pose: dict[str, Any] | None = None  # the pose's settings it ran with (pose_settings); None: not recorded
    # where its pose quantiles' scale was taken: INTERIOR_STAND_IN, as the product does; older files: the fiducials
    pose_interior: str = "fiducials"
    # rival classes (Mondrian quantiles): a pose whose best rival hypothesis fits within this ratio of the best
    # residual is contested, else clear; its group is visibility group + (number of visibility groups) x class.
    # Empty (older files, survey calibrations): one class, the visibility group alone.
    rival_ratio_edges: tuple[float, ...] = ()

    def scale_mm(self, features: np.ndarray) -> np.ndarray:
        """Predicted error scale (mm) of each row of features; inf where a feature is not finite."""
        return error_scale_mm(features, self.coefficients)

    def group(self, visibility: float, rival_ratio: float = RIVAL_RATIO_CAP) -> int:
        """Index of the group a pose belongs to (`group_index`, with this calibration's edges)."""
        return int(group_index(visibility, rival_ratio, self.visibility_edges, self.rival_ratio_edges))

    def column(self, coverage: float) -> int:
        """The quantiles' column of this coverage; a coverage it was not calibrated for is refused."""
        for i, c in enumerate(self.coverages):
            if abs(c - coverage) < 1e-9:
                return i
        held = ", ".join(f"{c:g}" for c in self.coverages)
        raise InputError(f"error_coverage {coverage:g} is not calibrated (this calibration holds {held})")


@dataclass(frozen=True)
class ErrorModel:
    """One pose's bounds: evaluate at any preop points (mm) with the configured coverage."""

    evidence: PoseEvidence
    calibration: BoundCalibration
    coverage: float

    def bounds_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """Per point: the distance (mm) within which its true position lies with `coverage`."""
        cal = self.calibration
        q = cal.point_quantiles[self._group(), cal.column(self.coverage)]
        return q * cal.scale_mm(self.evidence.features(points_mm, len(cal.coefficients)))

    def pose_bound_mm(self) -> float:
        """The bound of the interior's RMS error, from the scale over the interior's stand-in (the shrunk preop
        surface: error_bound.interior_stand_in), calibrated against the true interior's RMS error."""
        cal = self.calibration
        scale = cal.scale_mm(self.evidence.features(self.evidence.interior_mm, len(cal.coefficients)))
        q = cal.pose_quantiles[self._group(), cal.column(self.coverage)]
        return float(q * np.sqrt(np.mean(scale**2)))

    def _group(self) -> int:
        return self.calibration.group(self.evidence.visibility, self.evidence.rival_ratio)


def read_calibration(path: str | Path = "", bundled: Path = BUNDLED_CALIBRATION) -> BoundCalibration:
    """Read a calibration file (empty: the bundled one); one-line InputError when it is missing or malformed."""
    p = Path(path) if path else bundled
    try:
        stat = p.stat()
    except OSError:
        raise InputError(f"error-bound calibration {p} not found (make one: liver-p2p calibrate-bound)") from None
    return _read(str(p.resolve()), stat.st_mtime_ns)


@functools.lru_cache(maxsize=8)
def _read(path: str, _mtime_ns: int) -> BoundCalibration:
    try:
        raw = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"error-bound calibration {path} is not usable: {exc}") from None
    return calibration_from_dict(raw, f"error-bound calibration {path}")


def calibration_from_dict(raw: Any, where: str = "error-bound calibration") -> BoundCalibration:
    """A calibration from its JSON's content (a file's, or `bound_fit.calibrate`'s before it is written); one-line
    InputError naming `where` when it is malformed."""
    try:
        if not isinstance(raw, dict) or raw.get("format") != FORMAT:
            raise ValueError(f"format is not '{FORMAT}'")
        coefficients = np.asarray(raw["coefficients"], float)
        names = list(raw["features"])
        if not names or names != list(FEATURES[: len(names)]) or coefficients.shape != (len(names),):
            raise ValueError(f"features must be the first of {list(FEATURES)}, one coefficient each")
        edges = tuple(float(e) for e in raw["visibility_edges"])
        rival_edges = tuple(float(e) for e in raw.get("rival_ratio_edges", ()))
        # below the cap: the collections hold the ratio capped (log_rival_ratio), so the bench groups a pose as this does
        if not all(1.0 < e < RIVAL_RATIO_CAP for e in rival_edges) or list(rival_edges) != sorted(set(rival_edges)):
            raise ValueError(f"rival_ratio_edges must be increasing ratios in (1, {RIVAL_RATIO_CAP:g})")
        coverages = tuple(float(c) for c in raw["coverages"])
        point_q, pose_q = np.asarray(raw["point_quantiles"], float), np.asarray(raw["pose_quantiles"], float)
        shape = ((len(edges) + 1) * (len(rival_edges) + 1), len(coverages))
        if point_q.shape != shape or pose_q.shape != shape:
            raise ValueError(f"quantiles must be {shape[0]} groups x {shape[1]} coverages")
        if not (np.all(np.isfinite(point_q)) and np.all(np.isfinite(pose_q)) and np.all(np.isfinite(coefficients))):
            raise ValueError("non-finite numbers")
        return BoundCalibration(
            coefficients=coefficients,
            visibility_edges=edges,
            coverages=coverages,
            point_quantiles=point_q,
            pose_quantiles=pose_q,
            weights_sha256=str(raw.get("weights_sha256", "")),
            method=str(raw.get("method", "")),
            provenance=dict(raw.get("provenance", {})),
            positions=str(raw.get("positions", RIGID)),
            deform=dict(raw["deform"]) if raw.get("deform") is not None else None,
            view=str(raw.get("view", FRAME)),
            pose_interior=str(raw.get("pose_interior", "fiducials")),
            pose=dict(raw["pose"]) if raw.get("pose") is not None else None,
            rival_ratio_edges=rival_edges,
        )
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{where} is not usable: {exc}") from None


def attach_error_model(result: Any, source_mm: np.ndarray, target_mm: np.ndarray, config: Any) -> None:
    """Give a registered pose its error model and interior bound (`result.error_bound_mm`); ~5 ms.

    The bound is calibrated for one method and its weights: another method, or other weights, is
    told in `result.error_calibration_note` (the bound is still given: the best available, not a calibrated one).
    """
    from liver_p2p_reg.registration.error_bound import pose_evidence

    T = np.asarray(result.T_target_source, float)
    if not result.ok or T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return
    calibration = check_calibrations(config)
    evidence = pose_evidence(
        T,
        source_mm,
        target_mm,
        residual_mm=result.residual_mm,
        visibility=result.visibility,
        trim_ratio=config.icp_trim_ratio,
        hypotheses=[(c.T_target_source, c.residual_mm) for c in (result.screened or result.candidates) if c.ok],
    )
    model = ErrorModel(evidence, calibration, config.error_coverage)
    result.error_model = model
    result.error_bound_mm = model.pose_bound_mm()
    result.error_coverage = config.error_coverage
    result.error_calibration_note = calibration_note(calibration, result.method, config)


def check_calibrations(config: Any) -> BoundCalibration:
    """The pose's calibration (`error_calibration_path`, empty: the bundled one) holding `error_coverage`, and with
    `deform` a set `deform_error_calibration_path` alike; InputError (one line) for either that cannot be used.
    One check for the command (before any work), the node (at configure and parameter set) and each pose."""
    calibration = read_calibration(config.error_calibration_path)
    if calibration.positions != RIGID:
        raise InputError(f"{config.error_calibration_path}: a calibration of deformed positions, not of the pose's")
    calibration.column(config.error_coverage)  # an uncalibrated coverage is refused before any work
    if getattr(config, "deform", False) and config.deform_error_calibration_path:  # the user's own, refused alike
        read_deformed_calibration(config.deform_error_calibration_path, BUNDLED_DEFORMED_CALIBRATION, config)
    return calibration


def use_survey_calibration(result: Any, config: Any) -> None:
    """Re-bound a frame's pose tracked on survey mode's fused surface with the bundled survey calibration (the same
    evidence, its quantiles); a user's own `error_calibration_path` is kept as it is."""
    if result.error_model is None or config.error_calibration_path:
        return
    try:  # a missing or damaged bundled file leaves the single-view bound, said, never the pose without one
        calibration = read_calibration("", BUNDLED_SURVEY_RIGID_CALIBRATION)
        calibration.column(config.error_coverage)
    except InputError as exc:
        result.error_calibration_note = f"single-view error bound on a survey frame: {exc}"
        return
    model = ErrorModel(result.error_model.evidence, calibration, config.error_coverage)
    result.error_model = model
    result.error_bound_mm = model.pose_bound_mm()
    result.error_calibration_note = calibration_note(calibration, result.method, config)


def calibration_note(calibration: BoundCalibration, method: str, config: Any) -> str:
    """Why a calibration's coverage is not known for this method and weights ("" when it is)."""
    # Not a WARN: the bound is still the best estimate there is; the user is told it is not a calibrated one.
    # A tracked pose is the calibrated method's ICP refinement from the previous pose: its calibration holds.
    # A survey calibration was made of survey mode's frames, its tracked ones scored by `evaluate` among them.
    if calibration.view == SURVEY and method == SURVEY_TRACKED_METHOD:  # the survey of the configured method
        method = getattr(config, "method", method)
    if canonical_method(method) not in (canonical_method(calibration.method), "track"):
        return f"error bound calibrated for {calibration.method}, not {method}: its coverage is not known"
    if calibration.weights_sha256 and weights_sha256(config) != calibration.weights_sha256:
        return (
            "error bound calibrated with other matcher weights: its coverage is not known "
            "(recalibrate: liver-p2p calibrate-bound)"
        )
    if calibration.pose is not None:  # calibrations made before the settings were recorded are taken as they are
        differ = differing_settings(calibration.pose, pose_settings(config))
        if differ:
            shown = ", ".join(differ[:3]) + (f" and {len(differ) - 3} more" if len(differ) > 3 else "")
            return f"error bound calibrated with other {shown}: its coverage is not known"
    if calibration.pose_interior != INTERIOR_STAND_IN:
        return (
            "interior error bound calibrated at the fiducials, not where it is taken: its coverage is not known "
            f"(recalibrate: {_recalibration_command(calibration)})"
        )
    return ""


def _recalibration_command(calibration: BoundCalibration) -> str:
    """The command that remakes a calibration of this kind."""
    if calibration.view == SURVEY:
        return "scripts/calibrate_survey_bound.py" + ("" if calibration.positions == DEFORMED else " --positions rigid")
    return "liver-p2p calibrate-bound" + (" --deformed" if calibration.positions == DEFORMED else "")


# The settings that move the pose: preprocessing, features, matching and P2P, ICP, free space. A calibration holds for
# the poses these values give. Not among them: the weights (checked by their hash: a path differs from machine to
# machine), the frame the input comes in (`sensor_at_frame_origin` says where a cloud's sensor is, not how to
# register it), and the random streams (the seed, RANSAC's thread count: another draw of the same distribution of
# errors; the benchmark gives every case a seed of its own), nor threads and the verdict's thresholds.
POSE_SECTIONS = (PreprocessSection, FeatureSection, P2PSection, IcpSection, FreeSpaceSection)
NOT_POSE_SETTINGS = ("weights_path", "sensor_at_frame_origin", "open3d_threads")


# Pose settings added after calibrations began recording them, each with the value that gives the poses of before
# (a calibration that lacks one was made with that value, not with an unknown one).
ADDED_POSE_SETTINGS = {"surface_search_visibility": 0.0}


def differing_settings(recorded: dict[str, Any], ours: dict[str, Any]) -> list[str]:
    """The names, sorted, whose value a calibration recorded differs from this run's (or one of them lacks)."""
    recorded = {**{k: v for k, v in ADDED_POSE_SETTINGS.items() if k in ours}, **recorded}
    return sorted(k for k in set(recorded) | set(ours) if recorded.get(k) != ours.get(k))


def pose_settings(config: Any) -> dict[str, Any]:
    """The settings a calibration records and a pose is checked against (`calibration_note`)."""
    names = [f.name for section in POSE_SECTIONS for f in fields(section) if f.name not in NOT_POSE_SETTINGS]
    return {name: getattr(config, name) for name in names}


# The settings that change the deformed positions, and the gates that decide which poses the stage is applied on
# (the only ones a DEFORMED calibration holds for): it holds for these values only.
DEFORM_SETTINGS = (
    "deform_modes",
    "deform_target_tets",
    "deform_regularization",
    "deform_iterations",
    "deform_min_gain",
    "deform_min_points",
    "deform_max_residual_mm",
    "deform_max_displacement_mm",
)


# The held-out-half gate, named only when it is on (calibrations made before it existed ran without it).
HOLDOUT_SETTINGS = ("deform_holdout_check", "deform_min_holdout_gain")


def deform_settings(config: Any) -> dict[str, Any]:
    """The non-rigid stage's settings a deformed calibration is made with and checked against."""
    names = DEFORM_SETTINGS + (HOLDOUT_SETTINGS if config.deform_holdout_check else ())
    return {name: getattr(config, name) for name in names}


def read_deformed_calibration(path: str, bundled: Path, config: Any) -> BoundCalibration:
    """The calibration of deformed positions at `path` (empty: `bundled`) holding `config.error_coverage`;
    InputError (one line) for a missing or malformed file, a calibration of the pose's positions, or another
    coverage. A set `deform_error_calibration_path` is checked with the rigid one, before the stage runs."""
    try:
        calibration = read_calibration(path, bundled)
        if calibration.positions != DEFORMED:
            raise InputError(f"{path or bundled} is not a calibration of deformed positions")
        calibration.column(config.error_coverage)
    except InputError as exc:
        if path:  # said which setting: the same words would fit error_calibration_path's file
            raise InputError(f"deform_error_calibration_path: {exc}") from None
        raise
    return calibration


def attach_deformed_error_model(result: Any, config: Any, view: str = FRAME) -> None:
    """Give an applied deformation the bound of its deformed positions (`result.deformed_error_model`,
    `deformed_error_bound_mm`): the same pose evidence, the DEFORMED calibration's scale and quantiles.

    `view`: what the stage fitted (FRAME, or SURVEY: survey mode's fused surface, whose bundled calibration is its
    own). Settings other than the calibration's, or a calibration of the other view, are told in
    `result.deformed_error_calibration_note`."""
    result.deformed_error_model, result.deformed_error_bound_mm = None, float("nan")
    result.deformed_error_calibration_note = ""
    if result.error_model is None or result.deformation is None or not result.deformation.applied:
        return
    bundled = BUNDLED_SURVEY_CALIBRATION if view == SURVEY else BUNDLED_DEFORMED_CALIBRATION
    try:  # a bad or missing file costs the deformed positions their bound (said), never the deformation itself
        calibration = read_deformed_calibration(config.deform_error_calibration_path, bundled, config)
    except InputError as exc:  # a user's own file was refused before the rigid pose's bound (attach_error_model)
        result.deformed_error_calibration_note = f"the deformed positions have no bound: {exc}"
        return
    model = ErrorModel(result.error_model.evidence, calibration, config.error_coverage)
    result.deformed_error_model = model
    result.deformed_error_bound_mm = model.pose_bound_mm()
    differ = differing_settings(calibration.deform or {}, deform_settings(config))
    notes = [calibration_note(calibration, result.method, config)]
    if differ:
        notes.append(f"deformed-position bound calibrated with other {', '.join(differ)}: its coverage is not known")
    if calibration.view != view:
        fits = "single views" if calibration.view == FRAME else "fused surveys"
        notes.append(f"calibrated on {fits}; this fit used {'a fused survey' if view == SURVEY else 'one view'}")
    result.deformed_error_calibration_note = "; ".join(n for n in notes if n)
