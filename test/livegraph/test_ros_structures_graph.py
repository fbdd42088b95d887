"""Structures through the real graph: preop_loader_node -> register_node -> /registration/structures, real rclpy processes.

One loader is given two good structure files and four bad ones (missing, empty, NaN, metres): it
reports each bad one in an ERROR diagnostic and still publishes the model and the good structures;
register_node moves those with the pose it publishes, a bound per point, and its verdict follows them.
"""

import numpy as np
from conftest import require_rclpy

rclpy = require_rclpy()

from ros_support import BAG_A, bag_raw, clean_stderr, wait_for_fiducial_paths  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from liver_p2p_reg.bags.io import read_messages  # noqa: E402
from liver_p2p_reg.cloud_io import save_points  # noqa: E402
from liver_p2p_reg.livegraph.graph import (  # noqa: E402
    GraphProbe,
    NodeProcess,
    level_of,
    set_isolated_environment,
    stamp_ns,
    values_of,
)
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm, cloud_to_structures  # noqa: E402
from liver_p2p_reg.ros.topics import (  # noqa: E402
    TOPIC_INTRAOP,
    TOPIC_INTRAOP_FIDUCIALS,
    TOPIC_POSE,
    TOPIC_PREOP,
    TOPIC_PREOP_FIDUCIALS,
    TOPIC_STRUCTURES,
)
from liver_p2p_reg.stream.outputs import DIAG_NAME, ERROR, LOADER_DIAG_NAME, OK, PREOP_DIAG_NAME  # noqa: E402

BAD = {"missing.ply": "file not found", "empty.xyz": "no points", "nan.npy": "NaN or infinite", "metres.npy": "metres"}


def files(tmp):
    """The bag's model and fiducials as files (mm), a tumour and a vessel inside the liver, and the bad files."""
    preop = next(cloud_to_points_mm(m.msg) for m in read_messages(BAG_A, [TOPIC_PREOP]))
    fiducials = next(cloud_to_points_mm(m.msg) for m in read_messages(BAG_A, [TOPIC_PREOP_FIDUCIALS]))
    inside = preop.mean(axis=0)
    d = np.random.default_rng(3).normal(size=(30, 3))
    tumour = inside + 4.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    vessel = inside + np.linspace(-35, 35, 20)[:, None] * [1.0, 0.4, -0.2]
    for name, points in {"model.npy": preop, "fid.npy": fiducials, "tumour.xyz": tumour, "vessel.npy": vessel}.items():
        save_points(tmp / name, points)
    (tmp / "empty.xyz").write_text("")
    np.save(tmp / "nan.npy", np.vstack([tumour[:5], [np.nan, 0.0, 0.0]]))
    np.save(tmp / "metres.npy", tumour / 1000.0)
    return tumour, vessel


def test_structures_from_the_loader_move_with_the_published_pose(tmp_path):
    tumour, vessel = files(tmp_path)
    env = set_isolated_environment()
    probe = GraphProbe()
    register = NodeProcess("register_node", {"method": "procrustes"}, env=env, log_dir=tmp_path)
    specs = [f"{tmp_path / 'tumour.xyz'}:tumour", str(tmp_path / "vessel.npy"), *(str(tmp_path / n) for n in BAD)]
    params = {"model_path": tmp_path / "model.npy", "fiducials_path": tmp_path / "fid.npy", "structures_paths": specs}
    loader = None
    try:
        assert probe.wait_for(lambda: "loaded in" in register.stderr() or not register.alive(), 120), register.stderr()
        # matched both ways (its 1 Hz status arrives) before the loader's one-shot messages make it talk
        assert probe.wait_for(lambda: probe.diagnostics(0, DIAG_NAME), 60), register.stderr()
        assert probe.wait_for_subscriber(TOPIC_INTRAOP, 60)
        loader = NodeProcess("preop_loader_node", params, env=env, log_dir=tmp_path)
        # the loader: one ERROR naming every bad file with its reason, and the model and good structures published
        status = probe.wait_for(lambda: [s for s, _ in probe.diagnostics(0, LOADER_DIAG_NAME)], 60)
        assert status, loader.stderr()
        assert level_of(status[0]) == ERROR and loader.alive()
        for name, reason in BAD.items():
            assert name in status[0].message and reason in status[0].message, status[0].message
            assert any(name in k for k in values_of(status[0])), values_of(status[0])
        assert values_of(status[0])["structures"] == "tumour,vessel"
        errors = [line for line in clean_stderr(loader.stderr()) if "[ERROR]" in line]
        assert len(errors) == len(BAD) and all("not published" in line for line in errors), errors
        # register_node got the model (warmed up: OK) and the two structures
        model = probe.wait_for(lambda: [s for s, _ in probe.diagnostics(0, PREOP_DIAG_NAME)], 120)
        assert model and level_of(model[-1]) == OK and "preop model received" in model[-1].message, register.stderr()
        assert probe.wait_for(lambda: "2 structures (50 points)" in register.stderr(), 30), register.stderr()
        # the oracle needs both fiducial sets in before the cloud (each its own topic, discovered on its own)
        assert wait_for_fiducial_paths(probe, len(np.load(tmp_path / "fid.npy"))), register.stderr()
        raw = bag_raw(BAG_A)
        probe.publish(TOPIC_INTRAOP_FIDUCIALS, raw[TOPIC_INTRAOP_FIDUCIALS][0])
        probe.publish(TOPIC_INTRAOP, raw[TOPIC_INTRAOP][0])
        assert probe.wait_for(lambda: probe.count(TOPIC_STRUCTURES) and probe.count(TOPIC_POSE), 60), register.stderr()
        pose = probe.since(TOPIC_POSE)[0].msg
        cloud = probe.since(TOPIC_STRUCTURES)[0].msg
        assert stamp_ns(cloud) == stamp_ns(pose) and cloud.header.frame_id == pose.header.frame_id
        q, t = pose.pose.orientation, pose.pose.position
        R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        points_m, ids, bounds_m = cloud_to_structures(cloud)
        for label_id, points in enumerate((tumour, vessel)):
            moved_mm = points @ R.T + np.array([t.x, t.y, t.z]) * 1e3
            np.testing.assert_allclose(points_m[ids == label_id] * 1e3, moved_mm, rtol=0, atol=1e-3)
        assert len(ids) == 50 and np.isfinite(bounds_m).all() and (bounds_m > 0).all()

        # the verdict follows the structures' bounds: the widest named when above the 10 mm margin
        # (its own topic: it may arrive after the pose and the structures, so it is waited for too)
        def verdicts():
            statuses = [s for s, _ in probe.diagnostics(0, DIAG_NAME) if "received_clouds" not in values_of(s)]
            return [s for s in statuses if "structures" in values_of(s)]  # (the periodic status has received_clouds)

        assert probe.wait_for(verdicts, 30), register.stderr()
        (verdict,) = verdicts()
        assert values_of(verdict)["structures"] == "2"
        widest_mm = {"tumour": bounds_m[ids == 0].max() * 1e3, "vessel": bounds_m[ids == 1].max() * 1e3}
        worst = max(widest_mm, key=widest_mm.get)
        assert abs(float(values_of(verdict)["structure_error_bound_max_mm"]) - widest_mm[worst]) < 2e-3  # float32 m
        assert (worst in verdict.message) == (widest_mm[worst] > 10.0), verdict.message
    finally:
        if loader is not None:
            loader.stop()
        register.stop()
        probe.close()
