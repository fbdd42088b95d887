"""A re-run compares each registration's verdict as well as its pose: a recalibrated bound changes the verdict only."""

import json
import os
import subprocess
import sys

import numpy as np
from ros_support import BAG_A, bag_frames_m

from liver_p2p_reg.bags.flight_replay import _Rerunner, read_recording, rerun_recording
from liver_p2p_reg.bags.recorder import TOPIC_REGISTRATION
from liver_p2p_reg.bags.replay import replay_bag
from liver_p2p_reg.bags.rerun_report import Rerun
from liver_p2p_reg.config import Config
from liver_p2p_reg.registration.error_calibration import BUNDLED_CALIBRATION
from liver_p2p_reg.stream.outputs import ERROR, OK, WARN


def recorded(path):
    """topic -> the JSON records of a recording."""
    out = {}
    for item in read_recording(path):
        if item.msgtype == "std_msgs/msg/String":
            out.setdefault(item.topic, []).append(item.values)
    return out


def widened(path, factor):
    """Rewrite the calibration at `path` with every quantile `factor` times wider (a later mtime, so it is re-read)."""
    calibration = json.loads(path.read_text())
    for key in ("point_quantiles", "pose_quantiles"):
        calibration[key] = [[q * factor for q in row] for row in calibration[key]]
    stat = path.stat()
    path.write_text(json.dumps(calibration))
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))


def test_a_verdict_changed_behind_the_same_pose_is_a_difference(tmp_path):
    calibration = tmp_path / "bound.json"
    calibration.write_text(BUNDLED_CALIBRATION.read_text())
    config = Config(sensor_at_frame_origin=False, error_calibration_path=str(calibration))
    recording = tmp_path / "replay.mcap"
    replay_bag(BAG_A, config, record_path=recording)
    before = rerun_recording(recording)
    assert before.ok and (before.verdicts, before.verdicts_same) == (5, 5), before
    assert "5 of 5 verdicts (OK/WARN/ERROR) as recorded" in before.summary()
    # the recorded verdicts are OK (BAG_A's bounds lie well below 10 mm); 1000x wider quantiles put them above it
    widened(calibration, 1000.0)
    after = rerun_recording(recording)
    assert after.identical + after.roundoff == after.poses == 5  # the poses do not depend on the bound ...
    assert (after.verdicts, after.verdicts_same) == (5, 0) and not after.ok  # ... the verdicts do
    assert after.registrations_differing == len(after.differences) == 5  # one line each here
    assert all("verdict differs (recorded OK, re-run WARN" in line for line in after.differences), after.differences


def test_the_register_command_s_verdict_is_re_computed_as_the_command_gave_it(tmp_path):
    preop_m, frames_m = bag_frames_m(BAG_A)
    np.save(tmp_path / "source.npy", preop_m * 1e3)
    np.save(tmp_path / "view.npy", frames_m[0] * 1e3)
    calibration = tmp_path / "bound.json"
    calibration.write_text(BUNDLED_CALIBRATION.read_text())
    (tmp_path / "config.yaml").write_text(f"error_calibration_path: {calibration}\n")
    recording = tmp_path / "register.mcap"
    proc = subprocess.run(
        [sys.executable, "-m", "liver_p2p_reg", "register", tmp_path / "source.npy", tmp_path / "view.npy",
         "--config", tmp_path / "config.yaml", "--record", recording, "-q"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["status"] == "OK"
    before = rerun_recording(recording)
    assert before.ok and (before.verdicts, before.verdicts_same) == (1, 1), before
    widened(calibration, 1000.0)
    after = rerun_recording(recording)
    assert (after.verdicts, after.verdicts_same) == (1, 0) and after.identical + after.roundoff == 1, after
    assert "verdict differs (recorded OK, re-run WARN" in after.differences[0]


def test_a_failed_registration_and_an_ignored_origin_keep_their_verdicts(tmp_path):
    preop_m, frames_m = bag_frames_m(BAG_A)
    np.save(tmp_path / "source.npy", preop_m * 1e3)
    np.save(tmp_path / "view.npy", frames_m[0] * 1e3)
    np.save(tmp_path / "tiny.npy", frames_m[0][:4] * 1e3)  # 4 points: the registration fails (ERROR, no pose)
    inside = ",".join(f"{v:.3f}" for v in (frames_m[0] * 1e3).mean(axis=0))  # an origin amid the view: refused
    recording = tmp_path / "register.mcap"
    proc = subprocess.run(
        [sys.executable, "-m", "liver_p2p_reg", "register", tmp_path / "source.npy", tmp_path / "view.npy",
         tmp_path / "tiny.npy", "--sensor-origin", inside, "--record", recording, "-q"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2 and "only 4 valid points" in proc.stderr, proc.stderr
    status = json.loads(proc.stdout.splitlines()[0])
    assert status["status"] == "WARN" and status["warnings"][0].startswith("--sensor-origin ignored")
    levels = [r["level"] for r in recorded(recording)[TOPIC_REGISTRATION]]
    assert levels == [WARN, ERROR]  # the recording's verdicts are the command's (the JSON's status, the error)
    report = rerun_recording(recording)
    assert report.ok and (report.verdicts, report.verdicts_same, report.no_pose) == (2, 2, 1), report


def test_only_recordings_that_kept_structures_compare_verdicts():
    rerun = _Rerunner(None, False)
    rerun._compare_verdict({"level": OK}, WARN, "registration 0")  # before structures were kept: not compared
    assert (rerun.report.verdicts, rerun.report.differences) == (0, [])
    rerun._compare_verdict({"level": OK, "structures_sha256": None}, WARN, "registration 1")
    assert rerun.report.verdicts == 1 and rerun.report.differences[0].startswith(
        "registration 1: verdict differs (recorded OK, re-run WARN"
    )
    report = Rerun(["a.mcap"], registrations=2, poses=2, identical=2)
    assert report.ok and "verdicts" not in report.summary()  # nothing compared, nothing said
