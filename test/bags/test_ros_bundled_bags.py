"""Replay of every bundled bag meets the per-bag error bound of bags/README.md; bag size limits."""

import re
from pathlib import Path

import pytest

from liver_p2p_reg.bags.io import bag_size_bytes, bag_topics
from liver_p2p_reg.bags.replay import replay_bags
from liver_p2p_reg.config import Config
from liver_p2p_reg.registration.registrar import available_methods

BAGS = Path(__file__).resolve().parents[2] / "bags"
README = BAGS / "README.md"


def bag_dirs():
    return sorted(p for p in BAGS.iterdir() if (p / "metadata.yaml").is_file()) if BAGS.is_dir() else []


def expected():
    """method, frames replayed by this test, {bag: (columns...)} from the README table."""
    text = README.read_text()
    method = re.search(r"## Expected results \(method `([^`]+)`", text).group(1)
    frames = int(re.search(r"replaying the first (\d+) frames", text).group(1))
    rows = {}
    header = None
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells and cells[0] == "bag":
            header = cells
        elif header and len(cells) == len(header) and (BAGS / cells[0]).is_dir():
            rows[cells[0]] = dict(zip(header, cells, strict=True))
    return method, frames, rows


def test_bundled_bags_exist_within_size_limits_and_are_documented():
    bags = bag_dirs()
    kinds = [b.name.split("_")[0] for b in bags]
    assert kinds.count("insilico") >= 6 and kinds.count("phantom") >= 2 and kinds.count("sweep") >= 2
    # a sweep is 10-20 s of a moving scope at 5 Hz; every other bag a few frames of one view
    assert all(bag_size_bytes(b) <= (6_000_000 if b.name.startswith("sweep_") else 3_000_000) for b in bags)
    assert sum(bag_size_bytes(b) for b in bags) <= 25_000_000
    _, _, rows = expected()
    assert sorted(rows) == [b.name for b in bags]
    for bag in bags:
        topics = bag_topics(bag)
        assert {"/preop/points", "/preop/fiducials", "/intraop/points", "/intraop/fiducials"} <= set(topics)
        assert topics["/intraop/points"][1] >= 5


def test_replay_of_bundled_bags_within_readme_bounds():
    method, frames, rows = expected()
    if method not in available_methods():
        pytest.skip(f"method {method} of the README is not available in this build")
    results = replay_bags(bag_dirs(), Config(method=method), progress=False, max_frames=frames)
    failures = []
    for row in results:
        bound = float(rows[row.bag]["bound mm"])
        if row.status == "ERROR" or row.registered != frames or not row.max_rms_tre_mm <= bound:
            failures.append(
                f"{row.bag}: {row.status} {row.registered}/{frames} worst RMS-TRE {row.max_rms_tre_mm:.2f} > {bound}"
            )
    assert not failures, "\n".join(failures)
