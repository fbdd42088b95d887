"""Node core: bad inputs give the right diagnostic and no pose; modes, rate limit and latest-only."""

import threading

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from liver_p2p_reg.bags.io import rosbags_types
from liver_p2p_reg.config import Config
from liver_p2p_reg.registration.registrar import available_methods
from liver_p2p_reg.ros.messages import feed_intraop_msg
from liver_p2p_reg.ros.pointcloud2 import points_to_cloud
from liver_p2p_reg.stream.core import NodeCore
from liver_p2p_reg.stream.intake import FIDUCIAL_WAIT_S
from liver_p2p_reg.stream.outputs import ERROR, OK, STALE, WARN

TYPES = rosbags_types()


def liver_like(n=2000, seed=0):
    """An ellipsoid shell about 160 x 110 x 80 mm (liver-sized), in mm."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * [80.0, 55.0, 40.0]


def ground_truth():
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [20, -35, 60], degrees=True).as_matrix()
    T[:3, 3] = [30.0, -12.0, 250.0]
    return T


def moved(T, p):
    return p @ T[:3, :3].T + T[:3, 3]


def core_with_preop(**cfg):
    core = NodeCore(Config(method="procrustes", **cfg))
    diag = core.set_preop(liver_like())
    assert diag.level == OK
    return core


def only_diag(output):
    assert output is not None and output.pose is None and output.registered_preop_mm is None
    assert len(output.diagnostics) == 1
    return output.diagnostics[0]


def cloud_msg(points_mm, stamp_ns=1, **layout):
    return points_to_cloud(np.asarray(points_mm) * 1e-3, TYPES, frame_id="camera", stamp_ns=stamp_ns, **layout)


def test_cloud_before_preop_is_error_and_waits():
    core = NodeCore(Config(method="procrustes"))
    diags = core.on_intraop_points(liver_like(), "camera", 5)
    assert [d.level for d in diags] == [ERROR] and "before any preop" in diags[0].message
    assert not core.due(0.0) and core.process_pending(0.0) is None
    assert core.status().level == ERROR


def test_status_is_stale_before_anything():
    assert NodeCore(Config()).status().level == STALE


def test_status_counts_the_current_models_preop_fiducials():
    core = core_with_preop()
    assert core.status().values["preop_fiducials"] == "0"
    core.set_preop_fiducials(liver_like(6))
    assert core.status().values["preop_fiducials"] == "6"
    core.set_preop(liver_like(seed=1), stamp_ns=7)  # another model: the old one's markers are not its own
    assert core.status().values["preop_fiducials"] == "0"


@pytest.mark.parametrize(
    ("points", "level", "text"),
    [
        (np.zeros((0, 3)), ERROR, "empty intraop cloud"),
        (np.full((500, 3), np.nan), ERROR, "no valid points"),
        (liver_like(50), ERROR, "too few valid intraop points"),
        (liver_like() * 1000.0, WARN, "wrong units"),  # mm values published as metres
        (liver_like() / 1000.0, WARN, "wrong units"),  # metres published as mm-scaled metres
    ],
    ids=["empty", "all-nan", "too-few", "1000x-large", "1000x-small"],
)
def test_bad_intraop_clouds(points, level, text):
    core = core_with_preop()
    assert feed_intraop_msg(core, cloud_msg(points)) == []
    diag = only_diag(core.process_pending(0.0))
    assert diag.level == level and text in diag.message
    assert core.last_output.pose is None


def test_missing_z_field_is_error():
    msg = cloud_msg(liver_like(), extra_fields={"intensity": np.ones(2000, np.float32)})
    msg.fields = [f for f in msg.fields if f.name != "z"]
    core = core_with_preop()
    feed_intraop_msg(core, msg)
    diag = only_diag(core.process_pending(0.0))
    assert diag.level == ERROR and "lacks field" in diag.message


def test_million_point_cloud_is_voxelized_first():
    rng = np.random.default_rng(1)
    tiny = rng.uniform(0, 3.0, size=(1_000_000, 3)) + 100.0  # a 3 mm cube: few voxels survive
    core = core_with_preop()
    feed_intraop_msg(core, cloud_msg(tiny))
    diag = only_diag(core.process_pending(0.0))
    assert diag.level == ERROR and "too few" in diag.message
    assert diag.values["input_points"] == "1000000"
    assert int(diag.values["valid_points"]) < 100


def test_bad_preop_is_rejected():
    core = NodeCore(Config())
    assert core.set_preop(np.full((10, 3), np.nan)).level == ERROR
    assert core.preop_mm is None
    assert core.set_preop(liver_like() * 1000).level == WARN  # accepted, but flagged


def test_preop_in_wrong_units_never_gives_a_pose():
    core = NodeCore(Config(method="icp"))
    assert core.set_preop(liver_like() * 1000).level == WARN  # kept, flagged
    feed_intraop_msg(core, cloud_msg(liver_like()))
    diag = only_diag(core.process_pending(0.0))
    assert diag.level == ERROR and diag.message.startswith("preop model extent") and "wrong units" in diag.message
    assert core.set_preop(liver_like()).level == OK  # a model in mm (as metres) clears it
    feed_intraop_msg(core, cloud_msg(liver_like(), stamp_ns=2))
    assert core.process_pending(10.0).pose is not None


def test_cloud_without_frame_id_gets_no_pose():
    core = core_with_preop()
    msg = cloud_msg(liver_like())
    msg.header.frame_id = ""
    feed_intraop_msg(core, msg)
    diag = only_diag(core.process_pending(0.0))
    assert diag.level == ERROR and "empty header.frame_id" in diag.message


def test_continuous_rate_limit_keeps_latest_only():
    core = core_with_preop(max_rate_hz=2.0)
    core.on_intraop_points(liver_like(50), "camera", 1)
    assert core.due(10.0)
    first = core.process_pending(10.0)
    assert first.diagnostics[0].values["stamp_ns"] == "1"
    core.on_intraop_points(liver_like(50), "camera", 2)
    core.on_intraop_points(liver_like(50), "camera", 3)
    assert not core.due(10.2) and core.process_pending(10.2) is None  # rate limited
    second = core.process_pending(10.5)
    assert second.diagnostics[0].values["stamp_ns"] == "3"  # the stale cloud 2 was dropped
    assert core.dropped == 1 and core.received == 3 and core.processed == 2
    assert core.process_pending(20.0) is None  # nothing pending: no unbounded queue


def test_on_demand_mode_only_registers_on_service():
    core = core_with_preop(mode="on_demand")
    core.on_intraop_points(liver_like(50), "camera", 7)
    assert not core.due(100.0)
    out = core.reregister(100.0)
    assert out.reason == "reregister" and out.diagnostics[0].values["stamp_ns"] == "7"


def test_reregister_without_cloud_is_error():
    core = core_with_preop()
    diag = only_diag(core.reregister(0.0))
    assert diag.level == ERROR and "no intraop cloud" in diag.message


needs_procrustes = pytest.mark.skipif(
    "procrustes" not in available_methods(), reason="procrustes method not implemented yet"
)


@needs_procrustes
def test_registration_outputs_pose_cloud_and_tre():
    T = ground_truth()
    preop = liver_like()
    fid_ct = np.array([[10.0, 5, 0], [-20, 10, 5], [0, -15, -10], [30, 0, 8], [-5, 20, -12]])
    core = NodeCore(Config(method="procrustes", mode="once"))
    core.set_preop(preop)
    core.set_preop_fiducials(fid_ct)
    core.set_intraop_fiducials(moved(T, fid_ct), 42)
    core.on_intraop_points(moved(T, preop[preop[:, 0] > 0]), "camera", 42)
    out = core.process_pending(0.0)
    assert out.pose is not None and out.level in (OK, WARN)
    np.testing.assert_allclose(out.pose.T_sensor_ct_mm, T, atol=1e-6)
    np.testing.assert_allclose(out.pose.translation_m, T[:3, 3] / 1000)
    q = out.pose.quaternion_xyzw
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), T[:3, :3], atol=1e-9)
    assert out.pose.frame_id == "camera" and out.pose.child_frame_id == "ct"
    np.testing.assert_allclose(out.registered_preop_mm, moved(T, preop), atol=1e-6)
    values = out.diagnostics[0].values
    assert float(values["rms_tre_mm"]) < 1e-3 and "runtime_ms.total" in values and "residual_mm" in values
    # once mode: holds after the first pose until re-registered
    core.set_intraop_fiducials(moved(T, fid_ct), 43)  # the oracle needs this frame's own fiducials
    core.on_intraop_points(moved(T, preop[preop[:, 1] > 0]), "camera", 43)
    assert not core.due(100.0)
    assert core.reregister(100.0).pose is not None


def tracking_core(**cfg):
    """A core registering an asymmetric cap with the oracle, frames of it moving slightly."""
    rng = np.random.default_rng(3)
    d = rng.normal(size=(6000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    bumps = 1 + 0.25 * np.sin(3 * d[:, 0] + 1) * np.cos(2 * d[:, 1]) + 0.2 * d[:, 2] ** 3
    preop = d * bumps[:, None] * [80.0, 55.0, 40.0]  # lumpy: ICP has one clear optimum
    fid_ct = np.array([[10.0, 5, 0], [-20, 10, 5], [0, -15, -10], [30, 0, 8], [-5, 20, -12]])
    core = NodeCore(Config(method="procrustes", max_rate_hz=100.0, **cfg))
    core.set_preop(preop)
    core.set_preop_fiducials(fid_ct)
    return core, preop, fid_ct


def send_frame(core, preop, fid_ct, T, stamp, now_s):
    core.set_intraop_fiducials(moved(T, fid_ct), stamp)
    core.on_intraop_points(moved(T, preop[preop[:, 0] > 10]), "camera", stamp)
    return core.process_pending(now_s)


def nudged(T, degrees=1.0, mm=2.0):
    step = np.eye(4)
    step[:3, :3] = Rotation.from_euler("z", degrees, degrees=True).as_matrix()
    step[:3, 3] = [mm, -mm, 0.5 * mm]
    return step @ T


@needs_procrustes
def test_continuous_mode_tracks_from_the_previous_pose():
    core, preop, fid_ct = tracking_core()
    T = ground_truth()
    first = send_frame(core, preop, fid_ct, T, 1, 0.0)
    assert first.result.method == "procrustes" and first.diagnostics[0].values["tracked"] == "false"
    T2 = nudged(T)  # small sensor motion: ICP from the previous pose converges
    second = send_frame(core, preop, fid_ct, T2, 2, 1.0)
    assert second.result.method == "track" and second.diagnostics[0].values["tracked"] == "true"
    assert second.level == OK and "tracked from the previous pose" in second.summary
    assert float(second.diagnostics[0].values["rms_tre_mm"]) < 0.5
    np.testing.assert_allclose(second.pose.T_sensor_ct_mm[:3, 3], T2[:3, 3], atol=0.5)
    # the service always runs the full method, whatever the prior
    assert core.reregister(2.0).result.method == "procrustes"


@needs_procrustes
def test_tracking_falls_back_to_the_full_method_after_a_jump():
    core, preop, fid_ct = tracking_core()
    send_frame(core, preop, fid_ct, ground_truth(), 1, 0.0)
    jumped = nudged(ground_truth(), degrees=90.0, mm=60.0)  # ICP from the old pose cannot fit this
    out = send_frame(core, preop, fid_ct, jumped, 2, 1.0)
    assert out.result.method == "procrustes" and out.diagnostics[0].values["tracked"] == "false"
    assert "track_rejected" in out.result.runtime_ms  # the failed attempt counts in the latency
    np.testing.assert_allclose(out.pose.T_sensor_ct_mm, jumped, atol=1e-6)


@needs_procrustes
@pytest.mark.parametrize("cfg", [{"track_previous_pose": False}, {"track_max_frames": 1}, {"mode": "once"}])
def test_no_tracking_when_disabled_due_or_not_continuous(cfg):
    core, preop, fid_ct = tracking_core(**cfg)
    T = ground_truth()
    send_frame(core, preop, fid_ct, T, 1, 0.0)
    send_frame(core, preop, fid_ct, nudged(T), 2, 1.0)  # tracked only with track_max_frames=1 (then due)
    out = core.reregister(2.0) if cfg.get("mode") == "once" else send_frame(core, preop, fid_ct, nudged(T, 2), 3, 2.0)
    assert out.result.method == "procrustes"


@needs_procrustes
def test_a_new_preop_model_clears_the_prior_pose():
    core, preop, fid_ct = tracking_core()
    send_frame(core, preop, fid_ct, ground_truth(), 1, 0.0)
    # the same message again (a looped bag, a loader re-publishing): unchanged, the prior stays
    assert core.set_preop(preop).values.get("unchanged") == "true"
    assert send_frame(core, preop, fid_ct, nudged(ground_truth()), 2, 1.0).result.method == "track"
    core.set_preop(preop, stamp_ns=7)  # a new model message, if of the same shape
    core.set_preop_fiducials(fid_ct)  # markers belong to their model: a new model needs its own
    out = send_frame(core, preop, fid_ct, nudged(ground_truth()), 3, 2.0)
    assert out.result.method == "procrustes"


@pytest.mark.parametrize("limit_mm, level", [(15.0, OK), (0.05, WARN)])
def test_a_poorly_constrained_pose_is_published_with_a_warning(limit_mm, level):
    T = ground_truth()
    preop = liver_like(6000)
    fid_ct = np.array([[10.0, 5, 0], [-20, 10, 5], [0, -15, -10], [30, 0, 8], [-5, 20, -12]])
    core = NodeCore(Config(method="procrustes", mode="once", uncertainty_warn_mm=limit_mm))
    core.set_preop(preop)
    core.set_preop_fiducials(fid_ct)
    core.set_intraop_fiducials(moved(T, fid_ct), 7)
    view = preop[preop[:, 0] > 30]
    noisy = view + np.random.default_rng(6).normal(scale=0.5, size=view.shape)  # 0.5 mm sensor noise
    core.on_intraop_points(moved(T, noisy), "camera", 7)
    out = core.process_pending(0.0)
    uncertainty = float(out.diagnostics[0].values["uncertainty_mm"])
    assert out.pose is not None and out.level == level and 0.05 < uncertainty < 15.0
    assert ("poorly constrained" in out.summary) == (level == WARN)


@needs_procrustes
def test_rate_limit_counts_from_arrivals_so_waits_never_creep():
    """Clouds at exactly max_rate_hz, each registered a little late: every next one is due on arrival."""
    core = core_with_preop(max_rate_hz=2.0)
    fid_ct = liver_like(6, seed=5) * 0.3
    core.set_preop_fiducials(fid_ct)
    for k in range(20):
        arrival = 100.0 + 0.5 * k
        core.set_intraop_fiducials(fid_ct, k)
        core.on_intraop_points(liver_like()[:900], "camera", k, now_s=arrival)
        assert core.due(arrival + 0.001), f"cloud {k} waited"  # counting from late starts, waits crept up
        assert core.process_pending(arrival + 0.04).pose is not None  # started 40 ms after arrival
    assert core.dropped == 0


@needs_procrustes
def test_tre_needs_the_frames_own_fiducials_and_the_current_models():
    T = ground_truth()
    preop = liver_like()
    fid_ct = np.array([[10.0, 5, 0], [-20, 10, 5], [0, -15, -10], [30, 0, 8], [-5, 20, -12]])
    core = NodeCore(Config(method="icp", mode="on_demand"))
    core.set_preop(preop, stamp_ns=7)
    core.set_preop_fiducials(fid_ct, stamp_ns=7)
    core.set_intraop_fiducials(moved(T, fid_ct), 1)
    core.on_intraop_points(moved(T, preop[preop[:, 0] > 0]), "camera", 1)
    assert "rms_tre_mm" in core.reregister(0.0).diagnostics[0].values
    core.on_intraop_points(moved(T, preop[preop[:, 0] > 5]), "camera", 2)  # no fiducials of its own
    assert "rms_tre_mm" not in core.reregister(1.0).diagnostics[0].values
    core.set_preop(preop * 1.1, stamp_ns=7)  # another model with the same stamp (bags share a clock)
    core.on_intraop_points(moved(T, preop[preop[:, 0] > 0]), "camera", 1)  # frame 1's stamp again
    assert core.preop_fiducials_mm is None
    assert "rms_tre_mm" not in core.reregister(2.0).diagnostics[0].values


def test_a_cloud_waits_briefly_for_its_own_fiducials_while_ground_truth_streams():
    core = core_with_preop()
    core.set_preop_fiducials(liver_like(5))
    core.set_intraop_fiducials(liver_like(5), 1)
    core.on_intraop_points(liver_like(), "camera", 2, now_s=10.0)  # stamp 2's fiducials not here yet
    assert not core.due(10.0) and core.due(10.0 + FIDUCIAL_WAIT_S)
    core.set_intraop_fiducials(liver_like(5), 2)
    assert core.due(10.0)


def test_a_stream_faster_than_the_fiducial_wait_is_still_registered():
    """A newer cloud replaces a waiting one without restarting the wait: at 10 Hz without fiducials
    (a model with markers, no cloud of it paired yet) every cloud used to push the wait 0.3 s on."""
    core = core_with_preop()
    core.set_preop_fiducials(liver_like(5))
    registered = []
    for k in range(20):  # 10 Hz for 2 s, the worker looking every 30 ms
        now_s = 10.0 + 0.1 * k
        core.on_intraop_points(liver_like(), "camera", k, now_s=now_s)
        for t in (now_s, now_s + 0.03, now_s + 0.06, now_s + 0.09):
            output = core.process_pending(t)
            if output is not None:
                registered.append((t, int(output.diagnostics[0].values["stamp_ns"])))
    assert registered, "no cloud of a 10 Hz stream registered in 2 s"
    first_s, first_stamp = registered[0]
    assert first_s <= 10.0 + FIDUCIAL_WAIT_S + 0.03 and first_stamp == 3  # the latest cloud, after one wait
    assert len(registered) >= 3  # then at the rate limit (2 Hz)


def test_reconfigure_validates_the_method_and_keeps_the_cache():
    from liver_p2p_reg.errors import InputError

    with pytest.raises(InputError, match="unknown method 'nope'"):
        NodeCore(Config(method="nope"))
    core = NodeCore(Config(method="icp"))
    core.registrar.cache["prepared-source:abc:()"] = object()
    cache = dict(core.registrar.cache)
    with pytest.raises(InputError, match="unknown method"):
        core.reconfigure({"method": "nope", "residual_warn_mm": 9.0})
    assert core.config.residual_warn_mm == 4.0 and core.config.method == "icp"  # all or nothing
    core.reconfigure({"residual_warn_mm": 9.0})
    assert core.config.residual_warn_mm == 9.0 and core.registrar.config.residual_warn_mm == 9.0
    assert core.registrar.cache == cache


def test_a_model_arriving_during_a_registration_becomes_current_after_it():
    """Was: the model swapped mid-registration, and the old model's pose became the new model's tracking prior."""
    from liver_p2p_reg.registration.methods import Method, add_method, remove_method, run_method

    entered, release = threading.Event(), threading.Event()

    def slow_procrustes(source, target, config, ctx):
        entered.set()
        assert release.wait(10)
        return run_method("procrustes", source, target, config, ctx)

    add_method("slow-procrustes", Method(doc="procrustes after a signal (test)", run=slow_procrustes))
    try:
        core, preop, fid_ct = tracking_core()
        core.reconfigure({"method": "slow-procrustes"})
        worker = threading.Thread(target=send_frame, args=(core, preop, fid_ct, ground_truth(), 1, 0.0))
        worker.start()
        assert entered.wait(10)
        other = preop[::-1] * 1.05  # another model, while the registration runs
        assert core.set_preop(other, stamp_ns=9, warm_up=False).level == OK
        assert core.preop_mm is not other and np.array_equal(core.preop_mm, preop)  # not swapped under it
        release.set()
        worker.join(10)
        assert np.array_equal(core.preop_mm, other) and core.preop_stamp_ns == 9  # current once it ended
        core.reconfigure({"method": "procrustes"})
        core.set_preop_fiducials(fid_ct)
        out = send_frame(core, other, fid_ct, nudged(ground_truth()), 2, 1.0)
        assert out.result.method == "procrustes"  # a full registration: the old model's pose is no prior
    finally:
        release.set()
        remove_method("slow-procrustes")


@needs_procrustes
@pytest.mark.parametrize(
    "limits, tracked", [({"structure_error_warn_mm": 1e-6}, True), ({"uncertainty_warn_mm": 1e-6}, False)]
)
def test_a_pose_only_its_error_bound_warns_is_still_tracked_from(limits, tracked):
    # A bound above the margin says the view cannot certify the pose, not that it is wrong: the next
    # frame starts ICP from it; any other reason (here the uncertainty) forces the full method.
    core, preop, fid_ct = tracking_core(**limits)
    first = send_frame(core, preop, fid_ct, ground_truth(), 1, 0.0)
    assert first.level == WARN
    assert first.diagnostics[0].values["warn_reasons"] == ("error_bound" if tracked else "uncertainty")
    second = send_frame(core, preop, fid_ct, nudged(ground_truth()), 2, 1.0)
    assert (second.result.method == "track") == tracked
