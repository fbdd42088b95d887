"""Structure clouds (label_id uint32, error_bound float32) and the label JSON, on rosbags objects: every layout round-trips."""

import json

import numpy as np
import pytest

from liver_p2p_reg.bags.io import rosbags_types, typestore
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.ros.messages import (
    parse_structure_labels,
    preop_structures_cloud,
    registered_structures_cloud,
    structure_labels_json,
)
from liver_p2p_reg.ros.pointcloud2 import (
    FLOAT32,
    UINT32,
    cloud_fields,
    cloud_to_points_m,
    cloud_to_structures,
    points_to_cloud,
    structures_to_cloud,
)
from liver_p2p_reg.structures_io import PlacedStructure, Structure

TYPES = rosbags_types()


def roundtrip(msg):
    """Through CDR bytes, as a bag or a subscriber gets it."""
    return typestore().deserialize_cdr(
        typestore().serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"), "sensor_msgs/msg/PointCloud2"
    )


def test_structures_cloud_fields_and_round_trip(rng: np.random.Generator) -> None:
    points_m = rng.uniform(-0.2, 0.2, (30, 3))
    ids = np.repeat([0, 1, 4], 10)
    bounds_m = rng.uniform(0.001, 0.02, 30)
    msg = roundtrip(structures_to_cloud(points_m, ids, TYPES, frame_id="camera", stamp_ns=9, error_bound_m=bounds_m))
    assert [(f.name, f.datatype, f.offset) for f in msg.fields] == [
        ("x", FLOAT32, 0), ("y", FLOAT32, 4), ("z", FLOAT32, 8), ("label_id", UINT32, 12), ("error_bound", FLOAT32, 16)
    ]  # fmt: skip
    assert msg.point_step == 20 and msg.header.frame_id == "camera"
    points, got_ids, got_bounds = cloud_to_structures(msg)
    np.testing.assert_allclose(points, points_m, atol=1e-7)  # float32 metres: < 1e-4 mm
    np.testing.assert_array_equal(got_ids, ids)
    np.testing.assert_allclose(got_bounds, bounds_m, rtol=1e-6)
    assert cloud_fields(msg, ["label_id"])["label_id"].dtype == np.uint32
    np.testing.assert_allclose(cloud_to_points_m(msg), points_m, atol=1e-7)  # a plain x/y/z reader ignores the rest
    preop = roundtrip(structures_to_cloud(points_m, ids, TYPES, frame_id="ct"))  # /preop/structures: no bounds
    assert [f.name for f in preop.fields] == ["x", "y", "z", "label_id"] and cloud_to_structures(preop)[2] is None


@pytest.mark.parametrize(
    "layout", [{"big_endian": True}, {"height": 5}, {"pad_bytes": 3}, {"dtype": np.float64}, {"field_order": "zyx"}]
)
def test_other_publishers_layouts_decode_alike(layout: dict, rng: np.random.Generator) -> None:
    points_m = rng.uniform(-0.2, 0.2, (20, 3))
    extra = {"label_id": np.repeat(np.array([2, 7], np.uint32), 10), "error_bound": np.full(20, 0.005, np.float32)}
    msg = points_to_cloud(points_m, TYPES, frame_id="camera", extra_fields=extra, **layout)
    points, ids, bounds = cloud_to_structures(roundtrip(msg))
    np.testing.assert_allclose(points, points_m, atol=1e-7)
    np.testing.assert_array_equal(ids, extra["label_id"])
    np.testing.assert_allclose(bounds, 0.005, rtol=1e-6)


def test_non_finite_points_go_with_their_label_and_bad_ids_are_refused(rng: np.random.Generator) -> None:
    points_m = rng.uniform(-0.2, 0.2, (6, 3))
    points_m[2] = np.nan
    points, ids, _ = cloud_to_structures(structures_to_cloud(points_m, np.arange(6), TYPES, frame_id="ct"))
    np.testing.assert_array_equal(ids, [0, 1, 3, 4, 5])
    np.testing.assert_allclose(points[2], points_m[3], atol=1e-7)
    float_ids = points_to_cloud(points_m[:2], TYPES, frame_id="ct", extra_fields={"label_id": np.array([0.5, 1.0])})
    with pytest.raises(InputError, match="label_id"):
        cloud_to_structures(float_ids)
    huge_ids = points_to_cloud(points_m[:2], TYPES, frame_id="ct", extra_fields={"label_id": np.array([1e300, 1.0])})
    with pytest.raises(InputError, match="below 2\\*\\*31"):  # whole, and garbage once cast to an integer
        cloud_to_structures(huge_ids)
    with pytest.raises(InputError, match="lacks field.*label_id"):
        cloud_to_structures(points_to_cloud(points_m[:2], TYPES, frame_id="ct"))
    assert [
        len(a) for a in cloud_to_structures(structures_to_cloud(np.zeros((0, 3)), [], TYPES, frame_id="ct"))[:2]
    ] == [0, 0]


def test_node_messages_carry_structures_in_metres_with_their_ids_and_names(rng: np.random.Generator) -> None:
    tumour, vessel = rng.uniform(90, 110, (5, 3)), rng.uniform(-40, 40, (8, 3))
    structures = [Structure("tumour", tumour, 0), Structure("vessel", vessel, 1)]
    points, ids, bounds = cloud_to_structures(preop_structures_cloud(structures, TYPES, "ct", 42))
    np.testing.assert_allclose(points * 1e3, np.concatenate([tumour, vessel]), atol=1e-4)
    assert bounds is None and ids.tolist() == [0] * 5 + [1] * 8
    placed = [PlacedStructure("vessel", 1, vessel + 5.0, np.linspace(1, 9, 8), 0.9)]
    msg = registered_structures_cloud(placed, TYPES, "camera", 7)
    points, ids, bounds = cloud_to_structures(msg)
    np.testing.assert_allclose(points * 1e3, vessel + 5.0, atol=1e-4)
    np.testing.assert_allclose(bounds * 1e3, np.linspace(1, 9, 8), rtol=1e-6)
    assert ids.tolist() == [1] * 8 and msg.header.frame_id == "camera"
    text = structure_labels_json(structures, 42)
    assert json.loads(text) == {"labels": ["tumour", "vessel"], "stamp_ns": 42}
    assert parse_structure_labels(text) == (["tumour", "vessel"], 42)
    assert parse_structure_labels('{"labels": []}') == ([], None)
    for bad in ("nope", '{"labels": "tumour"}', '["tumour"]', '{"labels": ["a"], "stamp_ns": "1"}'):
        with pytest.raises(InputError):
            parse_structure_labels(bad)


def test_structure_labels_nested_beyond_the_parser_are_refused_not_fatal() -> None:
    from liver_p2p_reg.errors import InputError
    from liver_p2p_reg.ros.messages import parse_structure_labels

    with pytest.raises(InputError, match="not JSON"):  # RecursionError ended register_node and the Slicer bridge
        parse_structure_labels("[" * 200_000)


def test_a_cloud_naming_a_coordinate_twice_is_refused() -> None:
    from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_m

    msg = points_to_cloud(np.random.default_rng(0).uniform(-0.1, 0.1, (5, 3)), TYPES, frame_id="camera")
    msg.fields[1].name = "x"  # two x fields (offsets 0 and 4): one of them is y
    with pytest.raises(InputError, match="field.s. x twice"):
        cloud_to_points_m(msg)
