"""Large /intraop/points clouds between two processes over Fast DDS, with the bundled profile for large clouds."""

from conftest import require_rclpy

require_rclpy()

from liver_p2p_reg.livegraph.cloud_delivery import BUNDLED_PROFILE, delivery  # noqa: E402
from liver_p2p_reg.livegraph.graph import isolated_env  # noqa: E402


def test_the_large_clouds_profile_delivers_1m_point_clouds_through_a_64_mb_segment():
    assert BUNDLED_PROFILE.is_file()
    run = delivery(1_000_000, 10, 10.0, BUNDLED_PROFILE, isolated_env())
    # the profile, given as the docs say (FASTRTPS_DEFAULT_PROFILES_FILE), took effect: the publisher's own segment
    # holds 64 MiB (Fast DDS's default: 0.5 MiB)
    assert run.shm_segment_mb >= 64.0, run
    assert run.published == 10 and run.complete >= 9, run  # 12 MB clouds at 10 Hz, best effort


def test_without_its_segment_size_the_profile_leaves_fast_dds_s_default_segment(tmp_path):
    # the probe tells a profile whose segment took effect from one whose did not (Fast DDS says nothing of either)
    broken = tmp_path / "broken.xml"
    broken.write_text(BUNDLED_PROFILE.read_text().replace("<segment_size>67108864</segment_size>", ""))
    run = delivery(10_000, 3, 10.0, broken, isolated_env())
    assert run.shm_segment_mb < 1.0 and run.complete >= 2, run  # the default 512 KB segment; small clouds still go
