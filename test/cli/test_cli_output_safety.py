"""--force replaces what a command wrote before, never its inputs nor what merely stands at an output path."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from synthetic_cases import partial_case

from liver_p2p_reg.bags.io import bag_topics
from liver_p2p_reg.cli import main
from liver_p2p_reg.cloud_io import save_points

METHOD = ["--method", "fpfh-p2p-icp"]  # deterministic and fast on these clean crops


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A source and one view of it as point files, and a case NPZ of the same pair."""
    tmp = tmp_path_factory.mktemp("outputs")
    source, view, _, _, _ = partial_case(np.random.default_rng(5))
    paths = {"source": tmp / "source.ply", "view": tmp / "view.xyz", "npz": tmp / "case.npz"}
    save_points(paths["source"], source)
    save_points(paths["view"], view)
    np.savez(paths["npz"], src_pcd=source, tgt_pcd=view)
    return paths


def _run(argv: list, capsys: pytest.CaptureFixture) -> tuple[int, str]:
    rc = main([str(a) for a in argv])
    return rc, capsys.readouterr().err


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_bag_force_never_deletes_a_folder_that_is_not_a_bag(files, tmp_path, capsys, monkeypatch) -> None:
    work = tmp_path / "work"
    (work / "sub").mkdir(parents=True)
    (work / "notes.txt").write_text("keep")
    (work / "sub" / "z.txt").write_text("keep too")
    before = _snapshot(work)
    make = ["bag", "make", "--source", files["source"], "--target", files["view"], "--frames", 2, "--force"]
    rc, err = _run([*make[:2], work, *make[2:]], capsys)
    assert rc == 2 and "'notes.txt', which is not a bag's file" in err and len(err.splitlines()) == 1
    monkeypatch.chdir(work)
    rc, err = _run([*make[:2], ".", *make[2:]], capsys)  # the current folder: refused, not emptied
    assert rc == 2 and "current folder" in err
    assert _snapshot(work) == before
    # an input as OUT, even with --force: refused and intact
    data = files["view"].read_bytes()
    rc, err = _run([*make[:2], files["view"], *make[2:]], capsys)
    assert rc == 2 and "is an input" in err and files["view"].read_bytes() == data
    npz = files["npz"].read_bytes()
    rc, err = _run(["bag", "import", files["npz"], files["npz"], "--force"], capsys)
    assert rc == 2 and "is an input" in err and files["npz"].read_bytes() == npz
    # a folder of bare .mcap files (flight recordings, several bags) is no one bag; nor is a pipe
    recordings = tmp_path / "recordings"
    recordings.mkdir()
    for name in ("flight_a.mcap", "flight_b.mcap"):
        (recordings / name).write_bytes(b"evidence")
    rc, err = _run([*make[:2], recordings, *make[2:]], capsys)
    assert rc == 2 and "no metadata.yaml" in err and len(list(recordings.iterdir())) == 2
    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)
    rc, err = _run([*make[:2], pipe, *make[2:]], capsys)
    assert rc == 2 and "is not a bag" in err and len(err.splitlines()) == 1
    # a bag is still replaced with --force
    bag = tmp_path / "bag"
    assert _run([*make[:2], bag, *make[2:]], capsys)[0] == 0
    make[make.index("--frames") + 1] = 3
    assert _run([*make[:2], bag, *make[2:]], capsys)[0] == 0
    assert bag_topics(bag)["/intraop/points"][1] == 3


def test_replay_outputs_never_replace_the_bag_being_replayed(files, tmp_path, capsys) -> None:
    bag = tmp_path / "case_bag"
    assert _run(["bag", "import", files["npz"], bag, "--frames", 1], capsys)[0] == 0
    before = _snapshot(bag)
    replay = ["replay", bag, *METHOD, "--force"]
    rc, err = _run([*replay, "--out", tmp_path], capsys)  # OUT/<bag name> is the bag itself
    assert rc == 2 and "is an input" in err
    mcap = next(bag.glob("*.mcap"))
    rc, err = _run([*replay, "--json", mcap], capsys)
    assert rc == 2 and "inside" in err and "a bag this command reads" in err
    assert _snapshot(bag) == before
    # --json: an existing file only with --force; a folder is refused before any work
    rows = tmp_path / "rows.json"
    rows.write_text("{}")
    rc, err = _run(["replay", bag, *METHOD, "--json", rows], capsys)
    assert rc == 2 and "--force" in err and rows.read_text() == "{}"
    rc, err = _run(["replay", bag, *METHOD, "--json", tmp_path], capsys)
    assert rc == 2 and "is a folder" in err
    rc, err = _run(["replay", bag, *METHOD, "--plots", rows], capsys)
    assert rc == 2 and "is a file" in err
    rc, err = _run(["replay", bag, *METHOD, "--max-frames", -1], capsys)
    assert rc == 2 and "--max-frames" in err
    assert _run([*replay, "--json", rows], capsys)[0] == 0
    assert json.loads(rows.read_text())[0]["bag"] == "case_bag"
    # two bags, the second's output bag exists: refused before the first is replayed, not after
    second = tmp_path / "second_bag"
    assert _run(["bag", "import", files["npz"], second, "--frames", 1], capsys)[0] == 0
    out = tmp_path / "out"
    (out / "second_bag").mkdir(parents=True)
    rc, err = _run(["replay", bag, second, *METHOD, "--out", out], capsys)
    assert rc == 2 and "exists; pass --force" in err and not (out / "case_bag").exists()


def test_a_rerun_never_records_over_the_recording_it_reads(files, tmp_path, capsys) -> None:
    recording = tmp_path / "flight.mcap"
    assert _run(["register", files["source"], files["view"], *METHOD, "--record", recording], capsys)[0] == 0
    data = recording.read_bytes()
    for extra in (["--record", recording, "--force"], ["--json", recording, "--force"]):
        rc, err = _run(["replay", recording, *extra], capsys)
        assert rc == 2 and "is an input" in err, extra
    assert recording.read_bytes() == data
    rc, err = _run(["replay", recording, "--record", tmp_path / "again.mcap"], capsys)
    assert rc == 0 and (tmp_path / "again.mcap").is_file()


def test_register_outputs_never_collide_with_each_other_or_an_input(files, tmp_path, capsys, monkeypatch) -> None:
    register = ["register", files["source"], files["view"], *METHOD]
    same = tmp_path / "same.ply"
    rc, err = _run([*register, "-o", same, "--moved", same], capsys)
    assert rc == 2 and "would both write" in err and not same.exists()
    inputs = {name: files[name].read_bytes() for name in ("source", "view")}
    for option, path in (("-o", files["view"]), ("--moved", files["source"]), ("--moved", files["view"])):
        rc, err = _run([*register, option, path, "--force"], capsys)
        assert rc == 2 and "is an input" in err, (option, path)
    assert {name: files[name].read_bytes() for name in inputs} == inputs
    # several targets, --moved their own folder: FOLDER/<target name>.ply would be the input views themselves
    views = [tmp_path / "t1.ply", tmp_path / "t2.ply"]
    for view in views:
        save_points(view, np.loadtxt(files["view"]))
    data = [v.read_bytes() for v in views]
    rc, err = _run(["register", files["source"], *views, *METHOD, "--moved", tmp_path, "--force"], capsys)
    assert rc == 2 and "is an input" in err and [v.read_bytes() for v in views] == data
    rc, err = _run([*register, "-o", tmp_path, "--force"], capsys)
    assert rc == 2 and "is a folder" in err
    # an empty option is no input (Path("") would be the current folder, and every output in it refused)
    monkeypatch.chdir(tmp_path)
    rc, err = _run([*register, "-o", "result.json", "--config", "", "--weights", ""], capsys)
    assert rc == 0 and json.loads((tmp_path / "result.json").read_text())["status"] in ("OK", "WARN")


def test_a_prior_pose_is_scored_as_is_by_evaluate(files, tmp_path, capsys) -> None:
    _, _, T_true, _, _ = partial_case(np.random.default_rng(5))  # the fixture's view and its true pose
    pose = tmp_path / "pose.txt"
    np.savetxt(pose, T_true)
    rc = main(["register", str(files["source"]), str(files["view"]), "--method", "evaluate",
               "--initial-transform", str(pose)])  # fmt: skip
    result = json.loads(capsys.readouterr().out)
    # as given (up to the round trip through the normalized frame), and its fit measured
    assert rc == 0 and np.abs(np.array(result["transform"]) - T_true).max() < 1e-9
    assert result["residual_mm"] < 2.0  # the view's own noise; the identity pose leaves ~300 mm
    rc, err = _run(["register", files["source"], files["view"], "--method", "evaluate"], capsys)
    assert rc == 2 and "--initial-transform" in err


def test_config_and_calibration_outputs_are_checked_before_any_work(tmp_path, capsys) -> None:
    rc, err = _run(["config", "--write", tmp_path / "missing" / "c.yaml"], capsys)
    assert rc == 2 and "does not exist" in err
    rc, err = _run(["config", "--write", tmp_path, "--force"], capsys)
    assert rc == 2 and "is a folder" in err
    mine = tmp_path / "mine.yaml"
    mine.write_text("k: 4\n")
    rc, err = _run(["config", "--config", mine, "--write", mine, "--force"], capsys)
    assert rc == 2 and "is an input" in err and mine.read_text() == "k: 4\n"
    val = tmp_path / "val"  # a set of one case (its name is all these checks read)
    val.mkdir()
    (val / "case.npz").write_bytes(b"")
    for extra, message in ((["--noise-mm", "nan"], "--noise-mm"), (["--noise-mm", "-1"], "--noise-mm"),
                           (["--seed", "-1"], "--seed"), (["--out", tmp_path], "is a folder"),
                           (["--cache", mine], "is a file")):  # fmt: skip
        rc, err = _run(["calibrate-bound", "--val", val, *extra], capsys)
        assert rc == 2 and message in err, extra


def test_dataset_commands_never_replace_what_they_did_not_write(tmp_path, capsys) -> None:
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "manifest.csv").write_text("my,csv\n")  # a folder of someone else's: no dataset.json
    rc, err = _run(["dataset", "generate", "--out", mine, "--livers", "1", "--deformations", "1", "--targets", "1",
                    "--tets", "500", "--no-progress"], capsys)  # fmt: skip
    assert rc == 2 and "holds no dataset.json" in err and (mine / "manifest.csv").read_text() == "my,csv\n"
    assert sorted(p.name for p in mine.iterdir()) == ["manifest.csv"]
    picture = tmp_path / "picture.png"
    picture.write_bytes(b"mine")
    for png, message in ((picture, "exists; pass --force"), (tmp_path / "stats.xyz", "use one of .png, .pdf, .svg")):
        rc, err = _run(["dataset", "stats", mine, "--png", png], capsys)
        assert rc == 2 and message in err, err
    assert picture.read_bytes() == b"mine"


def test_an_output_linked_into_a_missing_folder_is_refused_before_the_work(files, tmp_path, capsys) -> None:
    link = tmp_path / "result.json"
    link.symlink_to(tmp_path / "missing" / "x.json")
    rc, err = _run(["register", files["source"], files["view"], *METHOD, "-o", link], capsys)
    assert rc == 2 and "whose folder does not exist" in err


def test_a_prior_pose_or_sensor_far_beyond_any_scene_is_one_line(files, tmp_path, capsys) -> None:
    pose = tmp_path / "far.txt"
    T = np.eye(4)
    T[0, 3] = 1e300  # overflowed to inf further on, and the error bound indexed past its tree
    np.savetxt(pose, T)
    rc, err = _run(["register", files["source"], files["view"], "--method", "evaluate", "--initial-transform", pose],
                   capsys)  # fmt: skip
    assert rc == 2 and "initial_T_mm moves the organ inf mm" in err and err.count("\n") == 1, err
    rc, err = _run(["register", files["source"], files["view"], *METHOD, "--sensor-origin=1e308,1e308,1e308"], capsys)
    assert rc == 2 and "more than 1e+06 mm away" in err and err.count("\n") == 1, err


def test_a_configs_record_path_records_and_never_replaces_a_recording(files, tmp_path, capsys) -> None:
    recording = tmp_path / "flight.mcap"
    config = tmp_path / "record.yaml"
    config.write_text(f"method: fpfh-p2p-icp\nrecord_path: {recording}\n")
    register = ["register", files["source"], files["view"], "--config", config]
    assert _run(register, capsys)[0] == 0 and recording.is_file()  # it used to be ignored silently
    data = recording.read_bytes()
    assert _run(register, capsys)[0] == 0  # the second run takes a new name: a recording is evidence
    assert recording.read_bytes() == data and len(list(tmp_path.glob("flight*.mcap"))) == 2
    folder = tmp_path / "recordings"
    folder.mkdir()
    config.write_text(f"method: fpfh-p2p-icp\nrecord_path: {folder}\n")  # a folder, as for the node
    assert _run(register, capsys)[0] == 0 and len(list(folder.glob("flight_*.mcap"))) == 1
    rc, err = _run([*register, "--record", tmp_path / "own.mcap"], capsys)  # --record wins
    assert rc == 0 and (tmp_path / "own.mcap").is_file() and len(list(folder.glob("*.mcap"))) == 1
