"""The checks an intraop cloud passes before the core registers it: frame, decoding, counts, voxelization, units."""

from __future__ import annotations

import numpy as np

from liver_p2p_reg.cloud_io import extent_mm
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.preprocess import voxel_downsample
from liver_p2p_reg.stream.intake import IntraopCloud
from liver_p2p_reg.stream.outputs import ERROR, WARN, units_warning


class Refused(Exception):
    """A frame not registered: the level and message of its diagnostic."""

    def __init__(self, level: int, message: str) -> None:
        super().__init__(message)
        self.level, self.message = level, message


def checked_points(
    cloud: IntraopCloud, config: Config, scale_mm: float | None, values: dict[str, str]
) -> tuple[np.ndarray, int, list[str]]:
    """The cloud's points as registered (voxelized when too many), its raw count and its warnings;
    Refused when it cannot be registered. Fills `values` with its counts and extent. Not
    cloud_io.clean_points: the node words its diagnostics itself, counts the point minimum after
    voxelizing, and drops NaN points silently (a depth camera's organized cloud has them in every frame)."""
    if not cloud.frame_id:
        raise Refused(ERROR, "intraop cloud has an empty header.frame_id (a pose needs its frame); not registered")
    try:
        points, n_raw = cloud.decode()
    except InputError as exc:
        raise Refused(ERROR, f"bad intraop cloud: {exc}") from None
    values["input_points"] = str(n_raw)
    if n_raw == 0:
        raise Refused(ERROR, "empty intraop cloud (0 points)")
    if len(points) == 0:
        raise Refused(ERROR, f"intraop cloud has no valid points (all {n_raw} are NaN/inf)")
    warnings: list[str] = []
    if len(points) >= config.max_input_points:
        voxel_mm = (scale_mm or extent_mm(points)) * config.voxel_size_norm / 2
        points = voxel_downsample(points, voxel_mm)
        warnings.append(f"{n_raw} input points voxelized to {len(points)} ({voxel_mm:.2f} mm voxels)")
    values["valid_points"] = str(len(points))
    if len(points) < config.min_points:
        raise Refused(ERROR, f"too few valid intraop points: {len(points)} < min_points {config.min_points}")
    extent = extent_mm(points)
    values["extent_mm"] = f"{extent:.1f}"
    unit_warning = units_warning(extent, "intraop cloud", config)
    if unit_warning:
        raise Refused(WARN, unit_warning + "; not registered")
    return points, n_raw, warnings


def same_model(current: tuple | None, points_mm: np.ndarray, frame_id: str, stamp_ns: int) -> bool:
    """Whether a model message repeats the current (or pending) one: the same points bit for bit, frame and
    stamp (a looped bag, a loader re-publishing); then nothing is reset and nothing recomputed.
    current: (points_mm, frame_id, stamp_ns, ...) or None."""
    if current is None or current[0] is None:
        return False
    old, old_frame, old_stamp = current[0], current[1], current[2]
    return (
        old_frame == frame_id
        and old_stamp == stamp_ns
        and old.shape == points_mm.shape
        and np.array_equal(old, points_mm)
    )
