"""Survey mode on a bundled sweep bag: the fused surface grows, resets on request, and stops when tracking fails."""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from liver_p2p_reg.bags.io import read_messages
from liver_p2p_reg.config import Config
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm
from liver_p2p_reg.stream.core import NodeCore
from liver_p2p_reg.stream.outputs import OK, WARN
from liver_p2p_reg.stream.survey import FusedSurface

SWEEP = Path(__file__).resolve().parents[2] / "bags" / "sweep_insilico_9000002"


@pytest.fixture(scope="module")
def sweep() -> dict:
    """The sweep bag's preop model and fiducials, and every frame with its ground-truth fiducials (mm)."""
    out: dict = {"frames": [], "fiducials": []}
    for item in read_messages(SWEEP):
        if item.topic == "/preop/mesh":  # a Marker: the non-rigid stage's surface, not used here
            continue
        points = cloud_to_points_mm(item.msg)
        if item.topic == "/preop/points":
            out["preop"] = points
        elif item.topic == "/preop/fiducials":
            out["preop_fiducials"] = points
        elif item.topic == "/intraop/fiducials":
            out["fiducials"].append(points)
        elif item.topic == "/intraop/points":
            out["frames"].append(points)
    return out


def survey_core(sweep: dict) -> NodeCore:
    core = NodeCore(Config(mode="survey"))
    assert core.set_preop(sweep["preop"]).level == OK
    core.set_preop_fiducials(sweep["preop_fiducials"])
    return core


def feed(core: NodeCore, sweep: dict, k: int, now_s: float, points: np.ndarray | None = None):
    stamp = 1_000_000 + k
    core.set_intraop_fiducials(sweep["fiducials"][k], stamp)
    core.on_intraop_points(sweep["frames"][k] if points is None else points, "camera", stamp)
    output = core.process_pending(now_s)
    assert output is not None and output.pose is not None
    return output, output.diagnostics[0]


def test_survey_fusion_grows_visibility_on_a_sweep_bag_and_resets(sweep) -> None:
    core = survey_core(sweep)
    visibility, tre = [], []
    for i, k in enumerate(range(0, 40, 4)):  # ~1.25 frames/s of the 5 Hz sweep: 8 s of scope motion
        output, diag = feed(core, sweep, k, float(i))
        assert diag.values["survey_state"] == "fusing", diag.message
        visibility.append(float(diag.values["survey_visibility"]))
        tre.append(output.result.rms_tre_mm)
    assert visibility[-1] > visibility[0] + 0.15  # the fused surface sees much more than one frame
    assert int(diag.values["survey_registrations"]) >= 2  # ... and was registered again as it grew
    assert int(diag.values["survey_frames"]) == 10
    assert max(tre) < 10.0  # no accepted frame is off by more than 10 mm
    message = core.reset_survey()
    assert "dropped 10 fused frames" in message
    output, diag = feed(core, sweep, 40, 20.0)
    assert diag.values["survey_state"] == "fusing" and diag.values["survey_frames"] == "1"
    assert output.result.method != "evaluate"  # the first frame of a new survey: a global registration
    assert float(diag.values["survey_visibility"]) < visibility[-1] - 0.15


def test_frames_tracked_on_the_survey_get_the_survey_calibrations_bound(sweep) -> None:
    """The global first frame keeps the single-view bound; tracked frames get survey mode's own, with no note; a
    user's calibration applies to every frame as it is (and says it was made for another method)."""
    from liver_p2p_reg.registration.error_calibration import BUNDLED_CALIBRATION

    runs = {}
    for path in ("", str(BUNDLED_CALIBRATION)):
        core = NodeCore(Config(mode="survey", error_calibration_path=path))
        assert core.set_preop(sweep["preop"]).level == OK
        core.set_preop_fiducials(sweep["preop_fiducials"])
        runs[path] = [feed(core, sweep, k, float(i)) for i, k in enumerate(range(0, 12, 4))]
    first, *tracked = runs[""]
    assert first[0].result.method != "evaluate" and first[0].result.error_model.calibration.view == "frame"
    for output, diag in tracked:
        result = output.result
        assert result.method == "evaluate" and result.error_model.calibration.view == "survey"
        assert result.error_calibration_note == "" and "error_calibration_note" not in diag.values
        assert float(diag.values["error_bound_mm"]) == pytest.approx(result.error_bound_mm, rel=1e-3)
    for (output, _), (theirs, diag) in zip(tracked, runs[str(BUNDLED_CALIBRATION)][1:], strict=True):
        assert np.array_equal(output.pose.T_sensor_ct_mm, theirs.pose.T_sensor_ct_mm)  # the bound only
        assert theirs.result.error_model.calibration.view == "frame"
        assert "not evaluate" in diag.values["error_calibration_note"]
        # the survey's calibration is tighter on these frames (its judged coverage: docs/results/survey_deform.md)
        assert output.result.error_bound_mm < theirs.result.error_bound_mm
    # a survey run under another method: its frames' survey bound says it was calibrated for the default's survey
    from liver_p2p_reg.registration.error_calibration import BUNDLED_SURVEY_RIGID_CALIBRATION as SURVEY_FILE
    from liver_p2p_reg.registration.error_calibration import calibration_note, read_calibration

    survey = read_calibration("", SURVEY_FILE)
    assert calibration_note(survey, "evaluate", Config(mode="survey")) == ""
    note = calibration_note(survey, "evaluate", Config(mode="survey", method="fpfh-ransac-icp"))
    assert "calibrated for learned-p2p-icp, not fpfh-ransac-icp" in note


def test_a_first_frame_warned_for_its_error_bound_alone_does_not_start_a_survey(sweep) -> None:
    # the same frame starts a survey under the default limit (the test above); at 0.5 mm its bound at depth warns
    core = NodeCore(Config(mode="survey", structure_error_warn_mm=0.5))
    assert core.set_preop(sweep["preop"]).level == OK
    core.set_preop_fiducials(sweep["preop_fiducials"])
    output, diag = feed(core, sweep, 0, 0.0)
    assert diag.level == WARN and "error bound at depth" in diag.message
    assert diag.values["warn_reasons"] == "input,error_bound"  # the bound alone (input: the survey's own line)
    assert diag.values["survey_state"] == "idle" and "waits for a first frame" in diag.message
    assert output.result.residual_mm <= core.config.residual_warn_mm and not output.result.ambiguous


def test_a_tracking_failure_stops_fusion_with_a_diagnostic(sweep) -> None:
    core = survey_core(sweep)
    for i, k in enumerate((0, 3, 6)):
        _, diag = feed(core, sweep, k, float(i))
        assert diag.values["survey_state"] == "fusing"
    # The scope jumps: the next frame is the sweep's frame 9 seen from 40 degrees and 60 mm away.
    jump = np.eye(4)
    jump[:3, :3] = Rotation.from_euler("y", 40, degrees=True).as_matrix()
    jump[:3, 3] = [60.0, 0.0, 0.0]
    output, diag = feed(core, sweep, 9, 3.0, transform_points(jump, sweep["frames"][9]))
    assert diag.level == WARN
    assert diag.values["survey_state"].startswith("stopped: tracking failed at frame 4 of the survey")
    assert "survey stopped (tracking failed" in diag.message and "~/reset_survey" in diag.message
    assert diag.values["survey_frames"] == "3"  # the jumped frame was not fused
    # Later frames are registered one by one and say so, until the survey is reset.
    _, diag = feed(core, sweep, 12, 4.0)
    assert diag.values["survey_state"].startswith("stopped") and diag.values["survey_frames"] == "3"
    core.reset_survey()
    _, diag = feed(core, sweep, 15, 5.0)
    assert diag.values["survey_state"] == "fusing" and diag.values["survey_frames"] == "1"


def test_fused_surface_is_voxel_merged_and_bounded() -> None:
    rng = np.random.default_rng(0)
    fused = FusedSurface(voxel_mm=2.0, max_points=500)
    patch = rng.uniform(0, 20, size=(3000, 3)) * [1, 1, 0]  # a 20 x 20 mm square: 100 voxels of 2 mm
    fused.add(patch)
    fused.add(patch + [0.0, 0.0, 0.0])  # the same surface again adds no point
    assert len(fused) == 100 and fused.counts.sum() == 6000
    fused.add(rng.uniform(0, 100, size=(20000, 3)) * [1, 1, 0])  # a 100 x 100 mm square: 2500 voxels of 2 mm
    assert len(fused) <= 500 and fused.voxel_mm > 2.0  # the grid coarsened to stay bounded
    assert fused.counts.sum() == 26000


def test_with_deform_the_stage_fits_the_fused_surface_while_fusing(sweep) -> None:
    """survey_deform_fused: the stage's view is the fused sweep (more points than the frame), else the frame."""
    cores = {fused: NodeCore(Config(mode="survey", deform=True, survey_deform_fused=fused)) for fused in (True, False)}
    diags = {}
    for fused, core in cores.items():
        assert core.set_preop(sweep["preop"]).level == OK
        core.set_preop_fiducials(sweep["preop_fiducials"])
        for i, k in enumerate(range(0, 24, 4)):
            output, diag = feed(core, sweep, k, float(i))
        diags[fused] = (output, diag.values)
    (out_f, fused), (out_1, frame) = diags[True], diags[False]
    assert fused["survey_state"] == frame["survey_state"] == "fusing"
    # the stage never changes the pose: the same rigid pose either way
    assert np.array_equal(out_f.pose.T_sensor_ct_mm, out_1.pose.T_sensor_ct_mm)
    assert (fused["deform_view"], frame["deform_view"]) == ("survey", "frame")
    assert int(frame["deform_view_points"]) <= len(sweep["frames"][20])  # the frame (its outliers dropped)
    assert int(fused["deform_view_points"]) == int(fused["survey_points"])  # the fused voxel means
    assert fused["deform_applied"] == "true", fused["deform_reason"]
    # each fit's deformed bound is its view's own calibration: the fused survey's has its own quantiles
    assert out_f.result.deformed_error_model.calibration.view == "survey"
    # its bundled file is calibrated where the bound is taken (the interior's stand-in): nothing to say
    assert out_f.result.deformed_error_calibration_note == ""
    assert float(fused["deformed_error_bound_mm"]) == pytest.approx(out_f.result.deformed_error_bound_mm, rel=1e-3)
    # more of the organ seen: the deformed interior is closer to the truth than the rigid pose's here
    assert float(fused["deformed_rms_tre_mm"]) < float(fused["rms_tre_mm"]) - 1.0, fused
    assert fused["deformed_rms_tre_mm"] != frame.get("deformed_rms_tre_mm")  # two fits of two views
