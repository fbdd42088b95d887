"""The node core's structures: which set it keeps and how it names them, moved with every pose, in the verdict, in replay."""

from pathlib import Path

import numpy as np
import pytest
from synthetic_cases import partial_case

from liver_p2p_reg.bags.io import read_messages, rosbags_types
from liver_p2p_reg.bags.replay import replay_bag
from liver_p2p_reg.config import Config
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.ros.messages import (
    feed_structure_labels_msg,
    feed_structures_msg,
    preop_structures_cloud,
    structure_labels_json,
)
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm, cloud_to_structures, stamp_to_ns
from liver_p2p_reg.ros.topics import TOPIC_POSE, TOPIC_PREOP, TOPIC_STRUCTURES
from liver_p2p_reg.stream.core import NodeCore
from liver_p2p_reg.stream.outputs import OK, WARN
from liver_p2p_reg.stream.structures import StructureStore
from liver_p2p_reg.structures_io import Structure

TYPES = rosbags_types()
BAG_A = Path(__file__).resolve().parents[2] / "bags" / "insilico_L9000001_D00_T007_random"


def test_the_store_keeps_the_latest_set_and_names_it_only_with_its_own_names() -> None:
    store = StructureStore()
    assert store.current() == []
    points = np.arange(15.0).reshape(5, 3) + 100
    assert store.set_points(points, [1, 1, 0, 0, 0], stamp_ns=10) == 2
    assert [(s.label, s.label_id, len(s.points_mm)) for s in store.current()] == [("label_0", 0, 3), ("label_1", 1, 2)]
    store.set_names(["tumour", "vessel"], stamp_ns=99)  # another set's names: not used
    assert [s.label for s in store.current()] == ["label_0", "label_1"]
    store.set_names(["tumour", "vessel"], stamp_ns=10)
    assert [s.label for s in store.current()] == ["tumour", "vessel"]
    store.set_points(points[:2], [0, 0], stamp_ns=11)  # a new set: its names have not come yet
    assert [s.label for s in store.current()] == ["label_0"]
    store.set_names(["plan"])  # names without a stamp fit any set
    assert [s.label for s in store.current()] == ["plan"]
    store.set_points(np.zeros((0, 3)), [], stamp_ns=12)  # an empty cloud clears the set
    assert store.current() == []
    store.set_structures([Structure("a", points, 3)])
    assert [(s.label, s.label_id) for s in store.current()] == [("a", 3)]


@pytest.fixture(scope="module")
def case():
    source, target, _, fid_s, fid_t = partial_case(np.random.default_rng(7))
    inside = source.mean(axis=0)
    d = np.random.default_rng(8).normal(size=(30, 3))
    tumour = inside + 4.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    vessel = inside + np.linspace(-40, 40, 25)[:, None] * [1.0, 0.3, 0.1]
    return source, target, fid_s, fid_t, [Structure("tumour", tumour, 0), Structure("vessel", vessel, 1)]


def registered(case, **cfg):
    """One registration of the case by a core that got the structures as register_node gets them."""
    source, target, fid_s, fid_t, structures = case
    core = NodeCore(Config(method="procrustes", **cfg))
    assert core.set_preop(source, stamp_ns=5).level == OK
    core.set_preop_fiducials(fid_s, 5)
    assert feed_structures_msg(core, preop_structures_cloud(structures, TYPES, "ct", 5)) is None
    assert feed_structure_labels_msg(core, structure_labels_json(structures, 5)) is None
    core.set_intraop_fiducials(fid_t, 6)
    core.on_intraop_points(target, "camera", 6)
    return core.reregister()


def test_structures_move_with_the_published_pose_and_carry_the_results_bounds(case) -> None:
    output = registered(case)
    assert output.pose is not None
    T = output.pose.T_sensor_ct_mm
    placed = output.structures
    assert [(p.label, p.label_id) for p in placed] == [("tumour", 0), ("vessel", 1)]
    for p, s in zip(placed, case[4], strict=True):
        # through the message: float32 metres, so within 1e-3 mm of the exact positions
        np.testing.assert_allclose(p.position_mm, transform_points(T, s.points_mm), atol=1e-3)
        np.testing.assert_allclose(p.error_bound_mm, output.result.error_bound_at(s.points_mm), rtol=1e-5)
        assert np.isfinite(p.error_bound_mm).all() and (p.error_bound_mm > 0).all()
    values = output.diagnostics[0].values
    worst = max(float(p.error_bound_mm.max()) for p in placed)
    assert values["structures"] == "2" and float(values["structure_error_bound_max_mm"]) == pytest.approx(
        worst, abs=1e-3
    )


def test_the_verdict_follows_the_structures_bounds(case) -> None:
    output = registered(case)
    widest = max(output.structures, key=lambda p: p.error_bound_mm.max())
    worst = float(widest.error_bound_mm.max())
    # a limit below the widest bound: WARN naming that structure; above every bound: no word about structures
    strict, lenient = (
        registered(case, structure_error_warn_mm=worst / 2),
        registered(case, structure_error_warn_mm=worst * 2),
    )
    assert strict.level == WARN and widest.label in strict.summary
    assert "tumour" not in lenient.summary and "vessel" not in lenient.summary
    assert strict.pose is not None and lenient.pose is not None  # a WARN still gives the pose


def test_replay_moves_command_line_structures_and_writes_them_to_the_output_bag(tmp_path: Path) -> None:
    preop = next(cloud_to_points_mm(m.msg) for m in read_messages(BAG_A, [TOPIC_PREOP]))
    tumour = Structure("tumour", preop.mean(axis=0) + np.random.default_rng(1).normal(size=(12, 3)), 0)
    out = tmp_path / "out"
    row = replay_bag(BAG_A, Config(method="procrustes"), out_path=out, max_frames=1, structures=[tumour])
    assert row.registered == 1
    (pose,) = [m.msg for m in read_messages(out, [TOPIC_POSE])]
    (cloud,) = [m.msg for m in read_messages(out, [TOPIC_STRUCTURES])]
    assert (stamp_to_ns(cloud.header.stamp), cloud.header.frame_id) == (
        stamp_to_ns(pose.header.stamp),
        pose.header.frame_id,
    )
    points_m, ids, bounds_m = cloud_to_structures(cloud)
    from scipy.spatial.transform import Rotation

    q, t = pose.pose.orientation, pose.pose.position
    R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    np.testing.assert_allclose(points_m * 1e3, tumour.points_mm @ R.T + np.array([t.x, t.y, t.z]) * 1e3, atol=1e-3)
    assert ids.tolist() == [0] * 12 and np.isfinite(bounds_m).all() and (bounds_m > 0).all()


def test_replay_uses_the_structures_a_bag_carries_with_their_names(tmp_path: Path) -> None:
    from liver_p2p_reg.bags.io import POINTCLOUD2, BagWriter, typestore
    from liver_p2p_reg.bags.player import read_raw
    from liver_p2p_reg.ros.topics import TOPIC_PREOP_STRUCTURES, TOPIC_STRUCTURE_LABELS

    preop_msg = next(m.msg for m in read_messages(BAG_A, [TOPIC_PREOP]))
    stamp = stamp_to_ns(preop_msg.header.stamp)
    tumour = Structure("tumour", cloud_to_points_mm(preop_msg).mean(axis=0) + [[0, 0, 0], [2.0, 0, 0]], 0)
    bag = tmp_path / "with_structures"
    with BagWriter(bag) as writer:
        for i, (topic, msgtype, log_ns, raw) in enumerate(read_raw(BAG_A)):
            writer.write_raw(topic, msgtype, log_ns, raw)
            if i == 0:  # the loader's two latched messages, right after the first one
                writer.write(
                    TOPIC_PREOP_STRUCTURES, POINTCLOUD2, log_ns, preop_structures_cloud([tumour], TYPES, "ct", stamp)
                )
                labels = typestore().types["std_msgs/msg/String"](data=structure_labels_json([tumour], stamp))
                writer.write(TOPIC_STRUCTURE_LABELS, "std_msgs/msg/String", log_ns, labels)
    seen = []

    class Observer:
        def on_input(self, topic, msg):
            pass

        def on_output(self, output):
            seen.extend(output.structures)

    config = Config(method="procrustes", structure_error_warn_mm=0.0)  # every bound above it: the label is named
    row = replay_bag(bag, config, max_frames=1, observer=Observer())
    assert row.registered == 1 and [s.label for s in seen] == ["tumour"] and "tumour" in row.message
