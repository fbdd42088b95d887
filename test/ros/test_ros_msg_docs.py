"""msg_docs/ documents every topic, the service, every register_node parameter with its default and the diagnostic keys."""

import dataclasses
from pathlib import Path

import numpy as np

from liver_p2p_reg.bags.replay_outputs import OUTPUT_TOPICS
from liver_p2p_reg.config import Config
from liver_p2p_reg.registration.deform import Deformation
from liver_p2p_reg.ros.topics import (
    QOS_OF_TOPIC,
    TOPIC_DEFORMED_PREOP,
    TOPIC_INTRAOP,
    TOPIC_INTRAOP_FIDUCIALS,
    TOPIC_PREOP,
    TOPIC_PREOP_FIDUCIALS,
    TOPIC_PREOP_MESH,
)
from liver_p2p_reg.stream.deformation import PreopMesh, mesh_diagnostic, prepare_stage, stage_values

DOCS = Path(__file__).resolve().parents[2] / "msg_docs"


def test_every_parameter_documented_with_its_default():
    text = (DOCS / "parameters_registration.md").read_text() + (DOCS / "parameters_node.md").read_text()
    defaults = Config()
    for f in dataclasses.fields(Config):
        row = next((line for line in text.splitlines() if line.startswith(f"| `{f.name}` |")), None)
        assert row is not None, f"{f.name} missing from msg_docs"
        assert f"`{getattr(defaults, f.name)!r}`" in row, f"{f.name}: documented default differs from Config"


def test_every_topic_has_a_page_with_type_qos_frame_units_example():
    index = (DOCS / "README.md").read_text()
    topics = [TOPIC_PREOP, TOPIC_PREOP_FIDUCIALS, TOPIC_PREOP_MESH, TOPIC_INTRAOP, TOPIC_INTRAOP_FIDUCIALS]
    topics += [*OUTPUT_TOPICS, TOPIC_DEFORMED_PREOP]
    for topic in topics:
        assert f"`{topic}" in index, topic
        pages = [p for p in DOCS.glob("*.md") if p.name != "README.md" and p.read_text().startswith(f"# `{topic}")]
        assert len(pages) == 1, topic
        text = pages[0].read_text()
        for word in ("type", "direction", "QoS", "frame", "units", "Example"):
            assert word in text, f"{pages[0].name} lacks {word}"


def test_the_non_rigid_stages_topic_and_diagnostic_keys_are_documented():
    page = (DOCS / "registration_deformed_preop.md").read_text()
    assert "reliable, volatile, depth 1" in page and QOS_OF_TOPIC[TOPIC_DEFORMED_PREOP].depth == 1
    diagnostics = (DOCS / "diagnostics.md").read_text()
    registration = stage_values(Deformation(True, "", np.eye(4)), None, 1.0, 1.0, 1.0, "note")
    mesh = PreopMesh(np.zeros((4, 3)), np.array([[0, 1, 2]]), "ct", 0)
    preop = {**mesh_diagnostic(mesh, True).values, **prepare_stage_keys()}
    for key in [*registration, *preop]:
        assert f"`{key}`" in diagnostics, f"diagnostic key {key} missing from diagnostics.md"


def prepare_stage_keys() -> dict[str, str]:
    """The preop status's deform_* keys, as the warm-up makes them (here for a model too small to build)."""
    from liver_p2p_reg.registration.registrar import Registrar

    values = prepare_stage(Registrar(Config()), np.zeros((3, 3)), None)
    assert values["deform_model"].startswith("no elastic model")
    return values
