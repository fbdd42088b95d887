"""Tracking policy of continuous mode: ICP from the last good pose, kept only while it fits as well as a full registration."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import LiverP2PError
from liver_p2p_reg.registration.registrar import Registrar
from liver_p2p_reg.result import RegistrationResult
from liver_p2p_reg.stream.outputs import OK, WARN, CoreOutput

# Reasons of a WARN that do not say the pose is wrong, only that the view cannot certify it within the
# margin: re-registering the same view would not do better, so such a pose still starts the next ICP.
UNCERTIFIED_ONLY = {"error_bound", "structures"}


@dataclass
class TrackState:
    """The last good pose, to start the next frame's ICP from (continuous mode)."""

    T_mm: np.ndarray  # T_sensor_ct of the last accepted registration
    reference_residual_mm: float  # residual of the last full (global) registration
    frame_id: str
    frames: int = 0  # tracked frames since that full registration


class Tracker:
    """The prior pose of the next frame; not locked: the core uses it under its registration lock."""

    def __init__(self) -> None:
        self.state: TrackState | None = None

    def forget(self) -> None:
        """No prior (a pose of another model is none)."""
        self.state = None

    def attempt(
        self,
        registrar: Registrar,
        config: Config,
        preop: np.ndarray,
        points: np.ndarray,
        fid_s: np.ndarray | None,
        fid_t: np.ndarray | None,
        frame_id: str,
        reason: str,
        origin_mm: np.ndarray | None,
    ) -> tuple[RegistrationResult | None, float | None]:
        """ICP from the last good pose; (result, None) if it fits as well as the last full registration.

        Returns (None, ms spent) when the tracked pose is rejected and (None, None) when no
        tracking was attempted: outside continuous mode, on a re-register request, without a
        good previous pose, for another sensor frame, or when a full registration is due.
        """
        track = self.state
        if (
            not config.track_previous_pose
            or reason != "continuous"
            or track is None
            or track.frame_id != frame_id
            or track.frames >= config.track_max_frames
        ):
            return None, None
        start = time.perf_counter()
        try:
            result = registrar.register(
                preop,
                points,
                method="track",
                initial_T_mm=track.T_mm,
                source_fiducials_mm=fid_s,
                target_fiducials_mm=fid_t,
                sensor_origin_mm=origin_mm,
            )
        except LiverP2PError:
            return None, (time.perf_counter() - start) * 1e3
        limit_mm = min(config.track_residual_ratio * track.reference_residual_mm, config.residual_warn_mm)
        if not (result.residual_mm <= limit_mm and np.isfinite(result.T_target_source).all()):
            return None, (time.perf_counter() - start) * 1e3
        return result, None

    def remember(self, output: CoreOutput, frame_id: str) -> None:
        """Keep an OK pose (or one only its error bound warns) as the next frame's prior; anything else clears it."""
        result = output.result
        if output.pose is None or result is None or not _prior_worthy(output):
            self.state = None
        elif result.method == "track" and self.state is not None:
            self.state.T_mm = np.asarray(result.T_target_source, dtype=np.float64)
            self.state.frames += 1
        else:
            self.state = TrackState(np.asarray(result.T_target_source, float), result.residual_mm, frame_id)


def _prior_worthy(output: CoreOutput) -> bool:
    """OK, or WARN for UNCERTIFIED_ONLY reasons (the diagnostic's `warn_reasons`)."""
    if output.level == OK:
        return True
    reasons = {r for r in output.diagnostics[0].values.get("warn_reasons", "").split(",") if r}
    return output.level == WARN and bool(reasons) and reasons <= UNCERTIFIED_ONLY
