"""demo, soak and replay refuse option values and output paths that cannot work, in one line, before any work."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from synthetic_cases import partial_case

from liver_p2p_reg.cli import main
from liver_p2p_reg.cli.demo_cmd import bundled_bags_dir

METHOD = ["--method", "fpfh-p2p-icp"]  # deterministic and fast on these clean crops
BAGS = Path(__file__).resolve().parents[2] / "bags"


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A one-frame bag of a synthetic case, with its fiducials."""
    tmp = tmp_path_factory.mktemp("flags")
    source, view, _, _, _ = partial_case(np.random.default_rng(5))
    np.savez(tmp / "case.npz", src_pcd=source, tgt_pcd=view)
    assert main(["bag", "import", str(tmp / "case.npz"), str(tmp / "case_bag"), "--frames", "1"]) == 0
    return tmp / "case_bag"


def _run(argv: list, capsys: pytest.CaptureFixture) -> tuple[int, str]:
    rc = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return rc, captured.err


def _one_line(rc: int, err: str, *words: str) -> None:
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "internal error" not in err, err
    for word in words:
        assert word in err, (word, err)


def test_demo_refuses_a_path_pattern_and_an_out_among_the_bags(tmp_path, capsys) -> None:
    _one_line(*_run(["demo", "--replay", "--bags", ""], capsys), "name pattern")
    _one_line(*_run(["demo", "--replay", "--bags", "/abs/*"], capsys), "name pattern")
    afile = tmp_path / "afile"
    afile.write_text("keep")
    _one_line(*_run(["demo", "--replay", "--bags", "phantom_sim_04*", "--out", afile], capsys), "is a file")
    assert afile.read_text() == "keep"
    bags = bundled_bags_dir()
    inside = bags / "phantom_sim_04_vis0.36" / "demo_out"
    _one_line(*_run(["demo", "--replay", "--bags", "phantom_sim_04*", "--out", inside], capsys), "bundled bags")
    assert not inside.exists()


def test_soak_refuses_endless_minutes_a_flood_rate_and_an_earlier_soaks_files(tmp_path, capsys) -> None:
    soak = ["soak", "--bags", BAGS / "phantom_sim_04_vis0.36", "--out", tmp_path / "o"]
    for minutes in ("nan", "inf"):
        _one_line(*_run([*soak, "--minutes", minutes], capsys), "--minutes")
    _one_line(*_run([*soak, "--minutes", 1, "--rate-hz", "1e6"], capsys), "--rate-hz")
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "soak.csv").write_text("minute\n1\n")
    _one_line(*_run([*soak, "--minutes", 1], capsys), "soak.csv exists", "--force")
    assert (tmp_path / "o" / "soak.csv").read_text() == "minute\n1\n"
    bag = BAGS / "phantom_sim_04_vis0.36"
    _one_line(*_run(["soak", "--bags", bag, "--out", bag / "soak", "--minutes", 1], capsys), "a bag this command reads")
    assert not (bag / "soak").exists()


def test_replay_outputs_never_share_a_path(bag, tmp_path, capsys) -> None:
    record = tmp_path / "same.mcap"
    _one_line(*_run(["replay", bag, *METHOD, "--record", record, "--json", record], capsys), "would both write")
    assert not record.exists()
    plots = tmp_path / "plots"
    plots.mkdir()  # an earlier run's plots
    _one_line(*_run(["replay", bag, *METHOD, "--plots", plots, "--json", plots / "case_bag.png"], capsys), "both write")
    out = tmp_path / "out"
    rc, err = _run(["replay", bag, *METHOD, "--out", out, "--json", out / "case_bag" / "metadata.yaml"], capsys)
    _one_line(rc, err, "inside", "an output bag")
    _one_line(*_run(["replay", bag, *METHOD, "--plots", bag / "plots"], capsys), "a bag this command reads")
    assert not (bag / "plots").exists()
    # the same bag twice (or two bags of one name) would write OUT/<name> twice: refused before the first
    _one_line(*_run(["replay", bag, bag, *METHOD, "--out", out], capsys), "two bags are named case_bag")
    assert not out.exists()
    _one_line(*_run(["replay", bag, *METHOD, "--slicer", 0, "--slicer-wait", "nan"], capsys), "--slicer-wait")


def test_a_dangling_link_as_record_is_refused_without_force_and_replaced_with_it(bag, tmp_path, capsys) -> None:
    link = tmp_path / "rec.mcap"
    link.symlink_to(tmp_path / "nowhere.mcap")
    _one_line(*_run(["replay", bag, *METHOD, "--record", link], capsys), "exists", "--force")
    assert _run(["replay", bag, *METHOD, "--record", link, "--force"], capsys)[0] == 0
    assert link.is_file() and not link.is_symlink() and not (tmp_path / "nowhere.mcap").exists()


def test_replay_on_demand_says_why_nothing_was_registered_and_writes_strict_json(bag, tmp_path, capsys) -> None:
    rows = tmp_path / "rows.json"
    rc = main(["replay", str(bag), *METHOD, "--mode", "on_demand", "--json", str(rows)])
    out = capsys.readouterr().out
    assert rc == 1 and "mode on_demand registers only when ~/reregister is called" in out
    text = rows.read_text()
    assert "NaN" not in text and json.loads(text)[0]["visibility"] is None  # null, not a bare NaN token


def test_bag_make_refuses_more_frames_than_a_bag_is_made_of(bag, tmp_path, capsys) -> None:
    npz = bag.parent / "case.npz"
    rc, err = _run(["bag", "import", npz, tmp_path / "huge", "--frames", 100_000_000], capsys)
    _one_line(rc, err, "fewer --frames")
    assert not (tmp_path / "huge").exists()


def test_register_outputs_refuse_a_pipe_and_keep_what_stands_beside_a_recording(bag, tmp_path, capsys) -> None:
    from liver_p2p_reg.cloud_io import save_points

    source, view, _, _, _ = partial_case(np.random.default_rng(5))
    save_points(tmp_path / "source.ply", source)
    save_points(tmp_path / "view.xyz", view)
    register = ["register", tmp_path / "source.ply", tmp_path / "view.xyz", *METHOD]
    pipe = tmp_path / "pipe.json"
    os.mkfifo(pipe)
    _one_line(*_run([*register, "-o", pipe, "--force"], capsys), "not a regular file")  # it blocked forever
    record = tmp_path / "rec.mcap"
    assert _run([*register, "--record", record], capsys)[0] == 0
    (tmp_path / "rec_001.mcap").mkdir()  # not a continuation: a folder of the user's
    (tmp_path / "rec_001.mcap" / "notes.txt").write_text("keep")
    _one_line(*_run([*register, "--record", record, "--force"], capsys), "rec_001.mcap", "no recording")
    assert (tmp_path / "rec_001.mcap" / "notes.txt").read_text() == "keep"
    (tmp_path / "rec_001.mcap" / "notes.txt").unlink()
    (tmp_path / "rec_001.mcap").rmdir()
    (tmp_path / "rec_001.mcap").write_bytes(record.read_bytes())  # a stale continuation: replaced with rec.mcap
    assert _run([*register, "--record", record, "--force"], capsys)[0] == 0
    assert record.is_file() and not (tmp_path / "rec_001.mcap").exists()


def test_register_refuses_an_unusable_calibration_before_any_work(tmp_path, capsys) -> None:
    from liver_p2p_reg.cloud_io import save_points

    source, view, _, _, _ = partial_case(np.random.default_rng(5))
    save_points(tmp_path / "source.ply", source)
    save_points(tmp_path / "view.xyz", view)
    register = ["register", tmp_path / "source.ply", tmp_path / "view.xyz", *METHOD, "-o", tmp_path / "r.json"]
    for key, flag in (("error_calibration_path", []), ("deform_error_calibration_path", ["--deform"])):
        (tmp_path / "c.yaml").write_text(f"{key}: {tmp_path / 'nowhere.json'}\n")
        rc, err = _run([*register, *flag, "--config", tmp_path / "c.yaml"], capsys)
        _one_line(rc, err, "nowhere.json not found")
        assert not (tmp_path / "r.json").exists()


def test_a_cut_npz_mesh_is_one_line_for_prepare_and_the_loader(tmp_path) -> None:
    from liver_p2p_reg.cloud_io import load_mesh
    from liver_p2p_reg.errors import InputError

    source, _, _, _, _ = partial_case(np.random.default_rng(5))
    np.savez(tmp_path / "mesh.npz", vertices=source, triangles=np.array([[0, 1, 2]]))
    (tmp_path / "cut.npz").write_bytes((tmp_path / "mesh.npz").read_bytes()[:3000])
    with pytest.raises(InputError, match="cannot read .*cut.npz"):
        load_mesh(tmp_path / "cut.npz")


def test_bag_make_refuses_an_out_named_like_a_file(bag, tmp_path, capsys) -> None:
    rc, err = _run(["bag", "import", bag.parent / "case.npz", tmp_path / "out.mcap"], capsys)
    _one_line(rc, err, "a bag is a folder")
    assert not (tmp_path / "out.mcap").exists()


def test_a_cut_mcap_alone_in_a_folder_is_checked_like_a_bare_one(bag, tmp_path, capsys) -> None:
    folder = tmp_path / "one"
    folder.mkdir()
    (folder / "x.mcap").write_bytes(next(bag.glob("*.mcap")).read_bytes()[:5000])
    _one_line(*_run(["bag", "info", folder], capsys), "ends without its footer")
