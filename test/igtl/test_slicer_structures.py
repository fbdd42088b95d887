"""Structures to 3D Slicer: one POLYDATA per structure, named by its label, in the sensor frame (node outputs and topics)."""

from __future__ import annotations

import numpy as np
import pytest
from igtl_support import Recorder

from liver_p2p_reg.bags.io import rosbags_types, typestore
from liver_p2p_reg.igtl.bridge import SlicerBridge, open_endpoint
from liver_p2p_reg.igtl.link import SlicerLink
from liver_p2p_reg.ros.messages import registered_structures_cloud, structure_labels_json
from liver_p2p_reg.slicer_config import SlicerConfig
from liver_p2p_reg.stream.outputs import OK, CoreOutput, Diagnostic, PoseOutput
from liver_p2p_reg.structures_io import PlacedStructure, Structure


@pytest.fixture
def link():
    config = SlicerConfig(host="127.0.0.1", port=0, point_size_mm=1.0)
    endpoint = open_endpoint(config)
    yield SlicerLink(SlicerBridge(config, endpoint))
    endpoint.close()


def placed(rng: np.random.Generator) -> list[PlacedStructure]:
    tumour, vessel = rng.uniform(90, 110, (6, 3)), rng.uniform(-40, 40, (9, 3))
    return [
        PlacedStructure("tumour", 0, tumour, np.full(6, 4.0), 0.9),
        PlacedStructure("vessel", 1, vessel, np.full(9, 7.0), 0.9),
    ]


def assert_points_drawn(received, points_mm: np.ndarray, atol_mm: float = 0.0) -> None:
    """The structure's points first (float32, sensor frame), each drawn as one triangle, as the cloud is."""
    n = len(points_mm)
    assert received.type_name == "POLYDATA" and len(received.value.points) == 3 * n
    np.testing.assert_allclose(received.value.points[:n], points_mm.astype(np.float32), rtol=0, atol=atol_mm)
    assert len(received.value.polygons) == n


def test_a_registration_sends_each_structure_under_its_label(link: SlicerLink, rng: np.random.Generator) -> None:
    slicer = Recorder.connect(link.bridge.endpoint.port)
    assert link.bridge.endpoint.wait_for_peers(1, 10.0)
    try:
        structures = placed(rng)
        T = np.eye(4)
        T[:3, 3] = [5.0, 0.0, 250.0]
        verdict = Diagnostic(OK, "liver_p2p_reg: registration", "registered: residual 1.00 mm")
        output = CoreOutput(
            [verdict], PoseOutput(1_700_000_000_500_000_000, "camera", "ct", T), np.zeros((3, 3)), structures=structures
        )
        link.on_output(output)
        for s in structures:
            (received,) = slicer.wait_for(s.label)
            assert_points_drawn(received, s.position_mm)
            assert received.timestamp_s == pytest.approx(1_700_000_000.5, abs=1e-6)  # the pose's stamp
        assert link.counters["structures_sent"] == 2
    finally:
        slicer.close()


def test_the_topics_name_each_structure_by_the_labels_message(link: SlicerLink, rng: np.random.Generator) -> None:
    """slicer_bridge_node's path: /registration/structures (label ids) named by /preop/structure_labels."""
    slicer = Recorder.connect(link.bridge.endpoint.port)
    assert link.bridge.endpoint.wait_for_peers(1, 10.0)
    try:
        structures = placed(rng)
        msg = registered_structures_cloud(structures, rosbags_types(), "camera", 5)
        link.on_structures_msg(msg)  # before any names: label_<id>
        assert_points_drawn(slicer.wait_for("label_1")[0], structures[1].position_mm, 1e-4)  # via float32 metres
        names = [Structure(s.label, s.position_mm, s.label_id) for s in structures]
        String = typestore().types["std_msgs/msg/String"]
        link.on_structure_labels_msg(String(data=structure_labels_json(names, 0)))
        link.on_structures_msg(msg)
        for s in structures:
            assert_points_drawn(slicer.wait_for(s.label)[0], s.position_mm, 1e-4)
        link.on_structure_labels_msg(String(data="not json"))  # counted, never raised
        assert link.counters["bad_messages"] == 1
    finally:
        slicer.close()


def test_device_names_are_valid_and_never_the_bridges_own(link: SlicerLink) -> None:
    labels = ["tumour", "PreopModel", "Lebermetastase Segment VIII", "tumour", "Gefäß", "DeformedModel"]
    devices = link.bridge.structure_devices(labels)
    assert devices[0] == "tumour" and devices[1] == "PreopModel~2" and devices[2] == "Lebermetastase Segme"
    assert devices[3] == "tumour~2" and devices[4] == "Gef__"  # non-ASCII letters as '_'
    assert devices[5] == "DeformedModel~2"  # nor the deformed model's
    assert len(set(devices)) == len(devices) and all(d.isascii() and d.isprintable() and len(d) <= 20 for d in devices)
