"""The settings register_node refuses before any frame: at configure, and when a parameter is set."""

from __future__ import annotations

from liver_p2p_reg.bags.recorder import recording_path
from liver_p2p_reg.config import Config
from liver_p2p_reg.registration.error_calibration import check_calibrations
from liver_p2p_reg.registration.methods import check_method_name
from liver_p2p_reg.registration.pipeline import require_device


def refuse_unusable(config: Config, accepted: Config | None = None) -> None:
    """InputError for settings every registration would fail on (checked where they change from `accepted`):
    refused when set or at configure, not reported frame after frame."""
    check_method_name(config.method)
    if config.record_path and (accepted is None or config.record_path != accepted.record_path):
        recording_path(config.record_path, "new")  # a folder that does not exist: refused now, with why

    def calibrations(c: Config) -> tuple:
        return c.error_calibration_path, c.error_coverage, c.deform, c.deform_error_calibration_path

    # (a set deformed file only: the bundled one's absence costs the deformed positions their bound, said)
    if accepted is None or calibrations(config) != calibrations(accepted):
        check_calibrations(config)
    require_device(config.device)
