"""Bag making/import, reading back with rosbags (dirs and bare .mcap), replay output bags and CLI errors."""

import os
import re
import shutil
import signal

import numpy as np
import pytest
import yaml

from liver_p2p_reg.bags.io import bag_custom_data, bag_topics, read_messages
from liver_p2p_reg.bags.make import CASE_KEY, make_case_bag
from liver_p2p_reg.bags.replay import format_table, replay_bag
from liver_p2p_reg.bags.replay_outputs import OUTPUT_TOPICS
from liver_p2p_reg.cli import main
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.registrar import available_methods
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm

PC2 = "sensor_msgs/msg/PointCloud2"


def synthetic_case(seed=0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(3000, 3))
    source = d / np.linalg.norm(d, axis=1, keepdims=True) * [80.0, 55.0, 40.0]
    fid = rng.uniform(-20, 20, size=(6, 3))
    c, s = np.cos(0.4), np.sin(0.4)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    t = np.array([15.0, -10.0, 280.0])
    target = source[source[:, 2] > 0] @ R.T + t
    return source, target, fid, fid @ R.T + t


@pytest.fixture
def case_bag(tmp_path):
    source, target, fs, ft = synthetic_case()
    return make_case_bag(
        tmp_path / "case_bag", source, target, source_fiducials_mm=fs, target_fiducials_mm=ft, info={"visibility": 0.5}
    )


def test_made_bag_is_jazzy_rosbag2_mcap(case_bag):
    meta = yaml.safe_load((case_bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap" and meta["ros_distro"] == "jazzy"
    assert meta["relative_file_paths"] == ["case_bag.mcap"]
    assert CASE_KEY in meta["custom_data"]
    latched = {
        t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"][0]["durability"]
        for t in meta["topics_with_message_count"]
    }
    assert latched["/preop/points"] == "transient_local" and latched["/intraop/points"] == "volatile"
    assert bag_topics(case_bag) == {
        "/preop/points": (PC2, 1),
        "/preop/fiducials": (PC2, 1),
        "/intraop/points": (PC2, 5),
        "/intraop/fiducials": (PC2, 5),
    }


def test_bag_contents_round_trip_in_metres_and_order(case_bag):
    source, target, fs, ft = synthetic_case()
    msgs = list(read_messages(case_bag))
    assert [m.timestamp_ns for m in msgs] == sorted(m.timestamp_ns for m in msgs)
    preop = next(m.msg for m in msgs if m.topic == "/preop/fiducials")
    assert preop.header.frame_id == "ct"
    np.testing.assert_allclose(cloud_to_points_mm(preop), fs, atol=1e-3)  # float32 metres
    frames = [m.msg for m in msgs if m.topic == "/intraop/points"]
    fids = [m.msg for m in msgs if m.topic == "/intraop/fiducials"]
    assert all(f.header.frame_id == "camera" for f in frames)
    assert [f.header.stamp for f in frames] == [f.header.stamp for f in fids]  # paired by stamp
    np.testing.assert_allclose(cloud_to_points_mm(fids[0]), ft, atol=1e-3)  # frame 0: no sensor motion
    moved = np.linalg.norm(cloud_to_points_mm(fids[-1]) - ft, axis=1)
    assert 0.05 < moved.max() < 10  # later frames: small sensor motion


def test_bare_mcap_file_is_readable(case_bag):
    mcap = case_bag / "case_bag.mcap"
    assert sum(1 for m in read_messages(mcap) if m.topic == "/intraop/points") == 5


def test_bag_import_cli_and_overwrite_refusal(tmp_path, capsys):
    source, target, fs, ft = synthetic_case(1)
    npz = tmp_path / "case_0001.npz"
    np.savez(npz, src_pcd=source, tgt_pcd=target, src_marker=fs, tgt_marker=ft, visibility=np.float64(0.5))
    out = tmp_path / "imported"
    assert main(["bag", "import", str(npz), str(out), "--frames", "3"]) == 0
    assert bag_topics(out)["/intraop/points"] == (PC2, 3)
    assert main(["bag", "import", str(npz), str(out)]) == 2
    assert "exists" in capsys.readouterr().err
    assert main(["bag", "import", str(npz), str(out), "--force", "--frames", "2"]) == 0
    assert bag_topics(out)["/intraop/points"] == (PC2, 2)


def test_bag_import_public_layout_with_src_vol(tmp_path):
    source, target, fs, ft = synthetic_case(3)
    npz = tmp_path / "public.npz"
    np.savez(npz, src_pcd=source, tgt_pcd=target, src_vol=fs, tgt_vol=ft, t_gt=np.zeros((3, 1)))
    assert main(["bag", "import", str(npz), str(tmp_path / "pub")]) == 0
    fids = [m.msg for m in read_messages(tmp_path / "pub", ["/intraop/fiducials"])]
    np.testing.assert_allclose(cloud_to_points_mm(fids[0]), ft, atol=1e-3)


def test_bag_make_from_plain_files(tmp_path):
    source, target, fs, ft = synthetic_case(2)
    np.savetxt(tmp_path / "src.xyz", source)
    np.save(tmp_path / "tgt.npy", target)
    np.savetxt(tmp_path / "pairs.txt", np.hstack([fs, ft]))
    out = tmp_path / "plain"
    args = ["bag", "make", str(out), "--source", str(tmp_path / "src.xyz"), "--target", str(tmp_path / "tgt.npy")]
    assert main([*args, "--fiducials", str(tmp_path / "pairs.txt")]) == 0
    assert bag_topics(out)["/preop/fiducials"] == (PC2, 1)


def test_bag_make_bad_inputs(tmp_path, capsys):
    assert main(["bag", "make", str(tmp_path / "x")]) == 2
    assert main(["bag", "import", str(tmp_path / "missing.npz"), str(tmp_path / "y")]) == 2
    assert "not found" in capsys.readouterr().err
    with pytest.raises(InputError):
        make_case_bag(tmp_path / "z", np.zeros((0, 3)), np.ones((5, 3)))
    source, target, fs, ft = synthetic_case(4)
    # Each of these used to write a bag (a NaN model, a cloud in metres, NaN ground truth,
    # all frames at one stamp, an empty preop message) or, for a .npy, crash.
    bad_fid = ft.copy()
    bad_fid[2] = np.nan
    for kwargs, message in [
        (dict(source_mm=np.full((500, 3), np.nan)), "source: all 500 points are NaN"),
        (dict(target_mm=target / 1000.0), "target extent .* wrong units"),
        (dict(source_fiducials_mm=fs, target_fiducials_mm=bad_fid), "target fiducials contain NaN"),
        (dict(frame_period_s=0.0), "frame period must be > 0"),
        (dict(max_preop_points=0), "point limits must be >= 1"),
        (dict(motion_mm=float("inf")), "sensor motion must be finite"),
    ]:
        with pytest.raises(InputError, match=message):
            make_case_bag(tmp_path / "z", **{"source_mm": source, "target_mm": target, **kwargs})
    assert not (tmp_path / "z").exists()  # nothing half-written
    np.save(tmp_path / "array.npy", source)
    assert main(["bag", "import", str(tmp_path / "array.npy"), str(tmp_path / "w")]) == 2
    assert "not an NPZ archive" in capsys.readouterr().err


def test_replay_refuses_missing_bag_and_unknown_method(tmp_path, case_bag, capsys):
    assert main(["replay", str(tmp_path / "nope")]) == 2
    assert main(["replay", str(case_bag), "--method", "no-such-method"]) == 2
    assert "unknown method" in capsys.readouterr().err


@pytest.mark.skipif("procrustes" not in available_methods(), reason="procrustes method not implemented yet")
def test_replay_writes_output_bag_with_registration_topics(tmp_path, case_bag):
    out = tmp_path / "out_bag"
    row = replay_bag(case_bag, Config(method="procrustes"), out_path=out)
    assert row.frames == 5 and row.registered == 5 and row.status in ("OK", "WARN")
    assert row.rms_tre_mm < 0.01  # oracle on exact fiducials (float32 metres in the bag)
    assert 0 < row.uncertainty_mm < Config().uncertainty_warn_mm
    topics = bag_topics(out)
    for topic, msgtype in OUTPUT_TOPICS.items():
        assert topics[topic][0] == msgtype
    assert topics["/registration/pose"][1] == 5 and topics["/intraop/points"][1] == 5
    poses = [m.msg for m in read_messages(out, ["/registration/pose"])]
    _, _, _, ft = synthetic_case()
    assert poses[0].header.frame_id == "camera"
    assert abs(poses[0].pose.position.z - 0.280) < 1e-4  # ct origin in the sensor frame, metres
    diags = [m.msg for m in read_messages(out, ["/diagnostics"])]
    keys = {kv.key for d in diags for s in d.status for kv in s.values}
    assert {"residual_mm", "rms_tre_mm", "max_tre_mm", "visibility", "matches", "runtime_ms.total"} <= keys
    assert "uncertainty_mm" in keys
    with pytest.raises(InputError, match="exists"):
        replay_bag(case_bag, Config(method="procrustes"), out_path=out)
    assert "case_bag" in format_table([row]) and "uncertainty mm" in format_table([row])


def test_replay_plots_the_last_registered_frame_and_keeps_existing_plots(tmp_path, case_bag, capsys):
    import matplotlib.image

    plots = tmp_path / "plots"
    argv = ["replay", str(case_bag), "--method", "procrustes", "--plots", str(plots)]
    assert main(argv) == 0
    png = plots / "case_bag.png"
    image = matplotlib.image.imread(png)
    assert image.shape[1] > 1500 and image[..., :3].std() > 0.05
    capsys.readouterr()
    before = png.read_bytes()
    assert main(argv) == 2  # an existing plot is not overwritten without --force
    assert "exists; pass --force" in capsys.readouterr().err and png.read_bytes() == before
    assert main([*argv, "--force"]) == 0
    # Every frame failing (the oracle without ground truth) gives no pose, so no picture either.
    source, target, _, _ = synthetic_case()
    bare = make_case_bag(tmp_path / "bare_bag", source, target)
    capsys.readouterr()
    assert main(["replay", str(bare), "--method", "procrustes", "--plots", str(tmp_path / "none")]) == 1
    assert not (tmp_path / "none" / "bare_bag.png").exists()
    # Which frame the message (and its RMS-TRE) is: the first at the bag's worst status.
    assert "bare_bag: ERROR (frame 1 of 5, the first at ERROR): " in capsys.readouterr().out


def _broken_bag(tmp_path, case_bag, kind):
    """A path that is no readable bag, made from a real one."""
    mcap = (case_bag / "case_bag.mcap").read_bytes()
    path = tmp_path / {"garbage": "x.mcap", "truncated": "cut.mcap", "ply": "cloud.ply", "pipe": "pipe.mcap"}.get(
        kind, kind
    )
    if kind == "garbage":
        path.write_bytes(bytes(range(256)) * 20)
    elif kind == "truncated":
        path.write_bytes(mcap[: len(mcap) // 2])
    elif kind == "ply":
        path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    elif kind == "pipe":
        os.mkfifo(path)
    elif kind == "empty-folder":
        path.mkdir()
    else:
        shutil.copytree(case_bag, path)
        if kind == "bad-metadata":
            (path / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  version: 9\n  files: [a\n  : : {\n")
        elif kind == "metadata-not-a-mapping":
            (path / "metadata.yaml").write_text("rosbag2_bagfile_information: 5\n")
        elif kind == "missing-mcap":
            (path / "case_bag.mcap").unlink()
    return path


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        ("garbage", "cannot read bag .*x.mcap: File magic is invalid"),
        ("truncated", "cannot read bag .*cut.mcap: it ends without its footer"),
        ("ply", "not a rosbag2 directory or .mcap file: .*cloud.ply"),
        ("pipe", "not a rosbag2 directory or .mcap file: .*pipe.mcap"),
        ("empty-folder", r"empty-folder is not a rosbag2 directory \(no metadata.yaml\)"),
        ("bad-metadata", r"bag metadata .*metadata.yaml is not valid YAML: .* \(line 4\)"),
        ("metadata-not-a-mapping", "metadata.yaml holds no rosbag2_bagfile_information mapping"),
        ("missing-mcap", "cannot read bag .*missing-mcap: Some database files are missing"),
    ],
)
def test_unreadable_bags_are_one_line_input_errors(tmp_path, case_bag, capsys, kind, message):
    """`bag info` on these was an internal error (AnyReaderError, FileNotFoundError) or a 5-line YAML excerpt."""
    path = _broken_bag(tmp_path, case_bag, kind)

    def hang(*_):
        raise TimeoutError("blocked opening the bag")  # a pipe: open() waits for a writer

    previous = signal.signal(signal.SIGALRM, hang)
    signal.alarm(10)
    try:
        for read in (bag_topics, lambda p: list(read_messages(p))):
            with pytest.raises(InputError, match=message) as info:
                read(path)
            assert "\n" not in str(info.value)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    capsys.readouterr()
    assert main(["bag", "info", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("liver-p2p: error: ") and err.count("\n") == 1 and re.search(message, err)


def test_replay_of_a_bag_with_malformed_metadata_is_one_line(tmp_path, case_bag, capsys):
    path = _broken_bag(tmp_path, case_bag, "bad-metadata")
    with pytest.raises(InputError, match=r"is not valid YAML: .* \(line 4\)"):
        bag_custom_data(path)
    assert main(["-q", "replay", str(path), "--method", "procrustes"]) == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("liver-p2p: error: bag metadata") and last.endswith("(line 4)")
