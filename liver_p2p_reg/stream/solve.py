"""One frame's rigid result for the node core: a survey step, a tracked pose, or else the full method (Refused when it raises)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import LiverP2PError
from liver_p2p_reg.registration.registrar import Registrar
from liver_p2p_reg.result import RegistrationResult
from liver_p2p_reg.stream.checks import Refused
from liver_p2p_reg.stream.outputs import ERROR
from liver_p2p_reg.stream.survey import Survey
from liver_p2p_reg.stream.tracking import Tracker

LOG = logging.getLogger("liver_p2p_reg.node")


@dataclass(frozen=True)
class Frame:
    """What one registration works on: the model and the frame's points (mm), fiducials, where the sensor stood."""

    preop_mm: np.ndarray
    points_mm: np.ndarray
    fid_s: np.ndarray | None
    fid_t: np.ndarray | None
    frame_id: str
    reason: str
    origin_mm: np.ndarray | None
    # the preop mesh's Registrar arguments when the contenders' judge needs the elastic model (else empty)
    surface: dict[str, np.ndarray] = field(default_factory=dict)


def guarded(what: str, call: Callable[[], Any]) -> Any:
    """call(), or Refused with the frame's ERROR: the node must survive anything a method raises."""
    try:
        return call()
    except LiverP2PError as exc:
        raise Refused(ERROR, f"registration failed: {exc}") from None
    except Exception as exc:
        LOG.exception("%s raised", what)
        raise Refused(ERROR, f"registration crashed: {type(exc).__name__}: {exc}") from None


def solve_frame(
    frame: Frame,
    registrar: Registrar,
    config: Config,
    tracker: Tracker,
    survey: Callable[[], Survey],
    values: dict[str, str],
    warnings: list[str],
) -> RegistrationResult:
    """The frame's rigid result; `values` and `warnings` gain what a survey step or tracking says."""
    f = frame
    if config.mode == "survey" and f.reason != "reregister":  # ---- survey mode (survey.py)
        step = guarded(
            "survey registration",
            lambda: survey().step(
                f.preop_mm,
                f.points_mm,
                source_fiducials_mm=f.fid_s,
                target_fiducials_mm=f.fid_t,
                sensor_origin_mm=f.origin_mm,
                surface=f.surface,
            ),
        )
        result, track_ms = step.result, None
        values.update(step.values)
        warnings += step.warnings
    else:
        result, track_ms = tracker.attempt(
            registrar, config, f.preop_mm, f.points_mm, f.fid_s, f.fid_t, f.frame_id, f.reason, f.origin_mm
        )
    values["tracked"] = str(result is not None and result.method == "track").lower()
    if result is None:
        result = guarded(
            "registration",
            lambda: registrar.register(
                f.preop_mm,
                f.points_mm,
                source_fiducials_mm=f.fid_s,
                target_fiducials_mm=f.fid_t,
                sensor_origin_mm=f.origin_mm,
                **f.surface,
            ),
        )
        if track_ms is not None:  # a rejected tracking attempt is part of this frame's latency
            result.runtime_ms["track_rejected"] = track_ms
            result.runtime_ms["total"] = result.runtime_ms.get("total", 0.0) + track_ms
    return result
