"""msg_docs/ documents every topic, the service and every register_node parameter with its default."""

import dataclasses
from pathlib import Path

from liver_p2p_reg.bags.replay import OUTPUT_TOPICS
from liver_p2p_reg.config import Config
from liver_p2p_reg.ros.topics import TOPIC_INTRAOP, TOPIC_INTRAOP_FIDUCIALS, TOPIC_PREOP, TOPIC_PREOP_FIDUCIALS

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
    topics = [TOPIC_PREOP, TOPIC_PREOP_FIDUCIALS, TOPIC_INTRAOP, TOPIC_INTRAOP_FIDUCIALS, *OUTPUT_TOPICS]
    for topic in topics:
        assert f"`{topic}" in index, topic
        pages = [p for p in DOCS.glob("*.md") if p.name != "README.md" and p.read_text().startswith(f"# `{topic}")]
        assert len(pages) == 1, topic
        text = pages[0].read_text()
        for word in ("type", "direction", "QoS", "frame", "units", "Example"):
            assert word in text, f"{pages[0].name} lacks {word}"
