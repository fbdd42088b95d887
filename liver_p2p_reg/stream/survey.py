"""Survey mode: track the frames of a sweeping sensor, fuse them into one growing surface, re-register it as it grows.

One view of 20-30 % of the liver leaves the pose poorly constrained; a surgeon sweeping the
scope for a few seconds shows much more. Each frame is tracked (ICP from the current pose,
method `track`) and, when tracking holds, moved into the preoperative frame and merged into
the fused surface (a voxel grid of means, bounded in size). Each time the fused visibility has
grown by `survey_step`, the fused surface is registered globally (the configured method) and
the pose corrected by it. A frame that tracking rejects stops the fusion, with the reason, until
`reset()` (the node's `~/reset_survey`); frames are then registered one by one, as in
continuous mode. ROS-free: the node core and bag replay drive it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import LiverP2PError
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.registration.confidence import pose_bound_warnings
from liver_p2p_reg.registration.error_calibration import SURVEY_TRACKED_METHOD, use_survey_calibration
from liver_p2p_reg.registration.nearest import NearestIndex
from liver_p2p_reg.registration.preprocess import statistical_inliers, voxel_keys
from liver_p2p_reg.registration.refine import source_search_index, trimmed_icp
from liver_p2p_reg.registration.registrar import Registrar
from liver_p2p_reg.registration.visibility import VisibilityMeter
from liver_p2p_reg.result import RegistrationResult

IDLE, FUSING, STOPPED = "idle", "fusing", "stopped"


class FusedSurface:
    """Points merged into a voxel grid (one mean per voxel, mm); the voxel doubles when they exceed `max_points`."""

    def __init__(self, voxel_mm: float, max_points: int) -> None:
        self.voxel_mm = float(voxel_mm)
        self.max_points = int(max_points)
        self.sums = np.zeros((0, 3))
        self.counts = np.zeros(0)

    def __len__(self) -> int:
        return len(self.counts)

    @property
    def points(self) -> np.ndarray:
        return self.sums / self.counts[:, None]

    def add(self, points_mm: np.ndarray) -> None:
        self._merge(np.vstack([self.sums, points_mm]), np.concatenate([self.counts, np.ones(len(points_mm))]))
        while len(self) > self.max_points:  # bounded memory and registration time, whatever the sweep's length
            self.voxel_mm *= 2.0
            self._merge(self.sums, self.counts)

    def transform(self, T: np.ndarray) -> None:
        """Move the fused surface rigidly (a pose correction); merged again on the same grid."""
        points = transform_points(T, self.points)
        self._merge(points * self.counts[:, None], self.counts.copy())

    def _merge(self, sums: np.ndarray, counts: np.ndarray) -> None:
        if not len(counts):
            return
        # A voxel's mean decides its cell; sums and counts add up, so merging is order-free.
        means = sums / counts[:, None]
        _, inverse = np.unique(voxel_keys(means, self.voxel_mm), return_inverse=True)
        inverse = inverse.reshape(-1)
        n = int(inverse.max()) + 1
        self.sums = np.stack([np.bincount(inverse, weights=sums[:, i], minlength=n) for i in range(3)], axis=1)
        self.counts = np.bincount(inverse, weights=counts, minlength=n)


@dataclass
class SurveyStep:
    """What one frame did to the survey: its registration and the survey's diagnostics."""

    result: RegistrationResult
    values: dict[str, str] = field(default_factory=dict)  # survey_* diagnostic key/values
    warnings: list[str] = field(default_factory=list)  # e.g. why the fusion stopped


class Survey:
    """The survey's state machine (idle -> fusing -> stopped); one frame at a time, mm in and out."""

    def __init__(self, registrar: Registrar, config: Config) -> None:
        self.registrar = registrar
        self.config = config
        self._meter: tuple[np.ndarray, VisibilityMeter] | None = None
        self.reset()

    def reset(self, reason: str = "") -> None:
        """Start over: forget the fused surface and the pose (the next frame is registered globally)."""
        self.state = IDLE
        self.reason = reason
        self.T_mm: np.ndarray | None = None  # T_sensor_ct of the last accepted frame
        self.fused = FusedSurface(self.config.survey_voxel_mm, self.config.survey_max_points)
        self._index: tuple[NearestIndex, np.ndarray] | None = None  # closest-point index + normals of the fused surface
        self.frames = 0  # frames fused
        self.registrations = 0  # global registrations of the fused surface (the first frame's included)
        self.visibility = 0.0  # of the fused surface
        self.registered_visibility = 0.0  # the fused visibility at the last global registration

    def step(
        self,
        preop_mm: np.ndarray,
        points_mm: np.ndarray,
        *,
        source_fiducials_mm: np.ndarray | None = None,
        target_fiducials_mm: np.ndarray | None = None,
        sensor_origin_mm: np.ndarray | None = None,
        surface: dict[str, np.ndarray] | None = None,
    ) -> SurveyStep:
        """Process one frame (sensor frame, mm). Raises what `Registrar.register` raises (no pose then). `surface`:
        the preop mesh's Registrar arguments for a frame's global registration (the contenders' judge)."""
        fid = {
            "source_fiducials_mm": source_fiducials_mm,
            "target_fiducials_mm": target_fiducials_mm,
            "sensor_origin_mm": sensor_origin_mm,
        }
        warnings: list[str] = []
        surface = surface or {}
        if self.state == FUSING:
            # Frame to fused surface: the sensor moves rigidly over a still organ, so the frames
            # agree with one another better than each agrees with the preop model (deformation).
            T = self._track(preop_mm, points_mm)
            tracked = self._score(preop_mm, points_mm, T, fid)
            problem = self._tracking_problem(tracked)
            if not problem:
                result = self._fuse(preop_mm, points_mm, tracked, fid, surface)
                return SurveyStep(result, self._values(), warnings)
            self.state, self.reason = STOPPED, f"tracking failed at frame {self.frames + 1} of the survey: {problem}"
        if self.state == STOPPED:
            # frame by frame, as continuous mode
            result = self.registrar.register(preop_mm, points_mm, **fid, **surface)
            warnings.append(f"survey stopped ({self.reason}); ~/reset_survey starts over")
            return SurveyStep(result, self._values(), warnings)
        result = self.registrar.register(preop_mm, points_mm, **fid, **surface)  # the first frame: a global one
        if self._warnings(result):  # fusing from a doubtful pose would spread its error over the whole survey
            warnings.append("survey waits for a first frame that registers without warnings")
            return SurveyStep(result, self._values(), warnings)
        self.state, self.reason = FUSING, ""
        self.registrations = 1
        result = self._fuse(preop_mm, points_mm, result, fid, surface, first=True)
        return SurveyStep(result, self._values(), warnings)

    def fused_view_mm(self) -> np.ndarray | None:
        """The fused surface in the last accepted frame's sensor frame (mm), while fusing; else None."""
        if self.state != FUSING or self.T_mm is None or not len(self.fused):
            return None
        return transform_points(self.T_mm, self.fused.points)

    # ---------------------------------------------------------------- internals
    def _track(self, preop_mm: np.ndarray, points_mm: np.ndarray) -> np.ndarray:
        """T_sensor_ct of a new frame: trimmed ICP of the frame onto the fused surface, from the last pose."""
        cfg = self.config
        scale_mm = self._meter_for(preop_mm).norm.scale_mm  # ICP's gates in the pipeline's normalized units
        if self._index is None:
            self._index = source_search_index(self.fused.points, cfg.normal_radius_norm * scale_mm)
        return trimmed_icp(
            self.T_mm,
            self.fused.points,
            points_mm,
            max_iterations=cfg.icp_max_iterations,
            max_corr=cfg.icp_max_corr_norm * scale_mm,
            trim_ratio=cfg.icp_trim_ratio,
            max_target_points=cfg.icp_max_points,
            tol=1e-3 * scale_mm,
            source_index=self._index,
        )

    def _fuse(
        self,
        preop_mm: np.ndarray,
        points_mm: np.ndarray,
        result: RegistrationResult,
        fid: dict,
        surface: dict[str, np.ndarray],
        first: bool = False,
    ) -> RegistrationResult:
        """Merge an accepted frame; re-register the fused surface (on the preop `surface`, the judge's) when its
        visibility has grown enough."""
        self.T_mm = np.asarray(result.T_target_source, dtype=np.float64)
        cfg = self.config
        if cfg.outlier_std_ratio > 0:  # flying pixels would pile up in the fused surface frame after frame
            points_mm = points_mm[statistical_inliers(points_mm, cfg.outlier_neighbors, cfg.outlier_std_ratio)]
        self.fused.add(transform_points(np.linalg.inv(self.T_mm), points_mm))
        self._index = None
        self.frames += 1
        self.visibility = float(self._meter_for(preop_mm)(self.fused.points))
        if first:
            self.registered_visibility = self.visibility
            return result
        if self.visibility < self.registered_visibility + self.config.survey_step:
            return result
        # The fused surface sits in the preop frame as the current pose sees it: registering the
        # preop model to it gives the correction C (preop -> fused frame) of that pose.
        fused = self.fused.points
        correction = self.registrar.register(preop_mm, fused, method="track", initial_T_mm=np.eye(4))
        try:
            fresh = self.registrar.register(preop_mm, fused, **surface)
            if not self._warnings(fresh) and fresh.residual_mm <= correction.residual_mm:
                correction = fresh
        except LiverP2PError:  # the global step is an improvement, never a requirement
            pass
        C = np.asarray(correction.T_target_source, dtype=np.float64)
        self.fused.transform(np.linalg.inv(C))
        self.registrations += 1
        self.registered_visibility = self.visibility
        corrected = self._score(preop_mm, points_mm, self.T_mm @ C, fid)
        self.T_mm = np.asarray(corrected.T_target_source, dtype=np.float64)
        return corrected

    def _score(self, preop_mm: np.ndarray, points_mm: np.ndarray, T_mm: np.ndarray, fid: dict) -> RegistrationResult:
        """The frame's result at a pose found on the fused surface, its bound of survey mode's calibration."""
        result = self.registrar.register(preop_mm, points_mm, method=SURVEY_TRACKED_METHOD, initial_T_mm=T_mm, **fid)
        use_survey_calibration(result, self.config)
        return result

    def _tracking_problem(self, tracked: RegistrationResult) -> str:
        """Why a tracked frame cannot be fused ("" when it can)."""
        if not np.isfinite(tracked.T_target_source).all():
            return "non-finite pose"
        # The node's WARN limit, not continuous mode's ratio to one frame's residual: a sweep brings
        # other parts of the organ, deformed differently, into view, and their residual differs.
        limit = self.config.residual_warn_mm
        # Not the free-space WARN either: it is calibrated on single frontal views, and a sweep's oblique
        # views of the flanks exceed it at good poses; the frame's own diagnostic still warns.
        if not tracked.residual_mm <= limit:
            return f"residual {tracked.residual_mm:.2f} mm above residual_warn_mm {limit:.2f} mm"
        return ""

    def _warnings(self, result: RegistrationResult) -> dict[str, str]:
        # The pose's warnings and its interior's error bound at depth, as the node's verdict has them: a pose the node
        # marks WARN for its bound must not start a survey, however well it fits the view. Not a method's own notes
        # (prepared weights of another liver): they would hold a survey forever.
        return pose_bound_warnings(result, self.config)

    def _meter_for(self, preop_mm: np.ndarray) -> VisibilityMeter:
        """M/N against this preop model, measured as the pipeline measures a target's visibility (one per model)."""
        if self._meter is None or self._meter[0] is not preop_mm:
            self._meter = (preop_mm, VisibilityMeter(preop_mm, self.config.voxel_size_norm))
        return self._meter[1]

    def _values(self) -> dict[str, str]:
        return {
            "survey_state": self.state if not self.reason else f"{self.state}: {self.reason}",
            "survey_visibility": f"{self.visibility:.3f}",
            "survey_frames": str(self.frames),
            "survey_points": str(len(self.fused)),
            "survey_registrations": str(self.registrations),
        }


def stage_view_mm(survey: Survey | None, config: Config, reason: str) -> np.ndarray | None:
    """What the non-rigid stage fits instead of the frame (`survey_deform_fused`): the fused surface while a survey
    fuses (not on a ~/reregister, which registers the frame alone), else None."""
    if survey is None or config.mode != "survey" or reason == "reregister" or not config.survey_deform_fused:
        return None
    return survey.fused_view_mm()
