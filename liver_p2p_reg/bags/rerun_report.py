"""What re-running a flight recording gave, and where floating-point round-off ends and a real difference begins."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

# Why a round-off class beside bitwise equality: the same inputs, parameters and weights re-run in another
# process can now and then sum a reduction in another order (one CI run re-ran one `register` pose 1.83e-6 mm
# from its recording; ~50 in-process repeats and 8 test runs here were all bitwise equal), so "bit for bit" is
# what a re-run usually gives, and anything beyond these bounds is a real difference (model, parameter, code).
ROUNDOFF_TRANSLATION_MM = 1e-4
ROUNDOFF_ROTATION = 1e-6  # a rotation entry: at most 0.2 um at 200 mm from the origin
# A deformed preop surface is recorded as published, float32 metres (~3e-5 mm steps at 0.3 m), beside the
# digest of its exact millimetres: a re-run whose digest differs is compared with it point by point.
ROUNDOFF_DEFORMED_MM = 1e-3


def within_roundoff(T: np.ndarray, want: np.ndarray) -> bool:
    """Whether pose T (4x4, mm) equals the recorded `want` up to floating-point round-off."""
    return bool(
        np.all(np.abs(T[:3, :3] - want[:3, :3]) <= ROUNDOFF_ROTATION)
        and np.all(np.abs(T[:3, 3] - want[:3, 3]) <= ROUNDOFF_TRANSLATION_MM)
        and np.array_equal(T[3], want[3])
    )


def structures_within_roundoff(placed: Any, recorded_msg: Any) -> bool:
    """Whether a re-run's placed structures equal the recorded /registration/structures cloud (float32 metres)
    up to round-off: the same label ids, positions and bounds within ROUNDOFF_DEFORMED_MM (inf and NaN bounds:
    the same). InputError (or ValueError, ...) for a recorded cloud that does not decode."""
    from liver_p2p_reg.ros.pointcloud2 import MM_PER_M, cloud_to_structures
    from liver_p2p_reg.structures_io import stacked_placement

    points_m, ids, bounds_m = cloud_to_structures(recorded_msg)
    got_ids, got, got_bounds = stacked_placement(placed)
    if bounds_m is None or got.shape != points_m.shape or not np.array_equal(got_ids, ids):
        return False
    near = np.abs(got - points_m * MM_PER_M) <= ROUNDOFF_DEFORMED_MM
    bounds_mm = bounds_m * MM_PER_M
    same = (got_bounds == bounds_mm) | (np.isnan(got_bounds) & np.isnan(bounds_mm))  # inf: unbounded, NaN: no model
    with np.errstate(invalid="ignore"):
        return bool(near.all() and (same | (np.abs(got_bounds - bounds_mm) <= ROUNDOFF_DEFORMED_MM)).all())


def deformed_within_roundoff(got_mm: np.ndarray, recorded_mm: np.ndarray) -> bool:
    """Whether a re-run's deformed surface (mm) equals the recorded float32 one up to round-off."""
    got, recorded = np.asarray(got_mm, dtype=np.float64), np.asarray(recorded_mm, dtype=np.float64)
    return got.shape == recorded.shape and bool(np.all(np.abs(got - recorded) <= ROUNDOFF_DEFORMED_MM))


@dataclass
class Rerun:
    """What re-running a recording gave."""

    files: list[str]
    registrations: int = 0  # registrations recorded (completed ones) and re-run
    poses: int = 0  # of them, those that recorded a pose
    identical: int = 0  # of those, poses re-run bit for bit
    roundoff: int = 0  # ... and those within floating-point round-off of the recorded pose (ROUNDOFF_*)
    no_pose: int = 0  # recorded without a pose and re-run without one
    deformed: int = 0  # registrations with a recorded deformed surface (the non-rigid stage applied) ...
    deformed_identical: int = 0  # ... re-run to bitwise the same surface
    deformed_roundoff: int = 0  # ... and those within round-off of the recorded surface (ROUNDOFF_DEFORMED_MM)
    structures: int = 0  # registrations that placed subsurface structures ...
    structures_identical: int = 0  # ... re-run to bitwise the same positions and bounds
    structures_roundoff: int = 0  # ... and those within round-off of the recorded ones (ROUNDOFF_DEFORMED_MM)
    verdicts: int = 0  # registrations whose verdict (the diagnostic's level) was recorded and re-computed ...
    verdicts_same: int = 0  # ... and those whose verdict the re-run gave again
    registrations_differing: int = 0  # registrations with at least one line in `differences`
    differences: list[str] = field(default_factory=list)  # one line per thing that differs (a pose's first)
    truncated: bool = False  # the last file ends without its footer (its writer was killed)
    notes: list[str] = field(default_factory=list)  # how this run's environment differs from the recording's

    @property
    def ok(self) -> bool:
        return not self.differences

    def summary(self) -> str:
        line = (
            f"{self.registrations} registrations re-run from {len(self.files)} file(s): {self.identical} of "
            f"{self.poses} poses bitwise identical to the recorded ones, {self.no_pose} without a pose as recorded"
        )
        if self.roundoff:
            line += (
                f"; {self.roundoff} more within floating-point round-off ({ROUNDOFF_TRANSLATION_MM:g} mm, "
                f"{ROUNDOFF_ROTATION:g} in a rotation entry)"
            )
        if self.deformed:
            line += f"; {self.deformed_identical} of {self.deformed} deformed preop surfaces bitwise identical"
            if self.deformed_roundoff:
                line += f", {self.deformed_roundoff} more within round-off ({ROUNDOFF_DEFORMED_MM:g} mm)"
        if self.structures:
            line += f"; {self.structures_identical} of {self.structures} placements of structures bitwise identical"
            if self.structures_roundoff:
                line += f", {self.structures_roundoff} more within round-off ({ROUNDOFF_DEFORMED_MM:g} mm)"
        if self.verdicts:
            line += f"; {self.verdicts_same} of {self.verdicts} verdicts (OK/WARN/ERROR) as recorded"
        if self.truncated:
            line += "; the recording ends without its footer (writer killed): read up to its last complete registration"
        return line
