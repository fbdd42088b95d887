"""`liver-p2p calibrate-bound` end to end on a few written cases: it calibrates, reproduces itself, refuses to overwrite."""

from __future__ import annotations

import json

import numpy as np
import pytest
from synthetic_cases import partial_case

from liver_p2p_reg.cli import main
from liver_p2p_reg.config import Config
from liver_p2p_reg.phantom.casefile import write_case
from liver_p2p_reg.registration.error_calibration import pose_settings, read_calibration


@pytest.fixture(scope="module")
def case_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cases")
    for i in range(6):
        rng = np.random.default_rng(100 + i)
        share = (0.2, 0.3, 0.45)[i % 3]
        source, target, T, fid_s, fid_t = partial_case(rng, share=share)
        write_case(
            folder / f"case_L{900 + i % 2}_D00_T{i:03d}.npz",
            {
                "src_pcd": source,
                "tgt_pcd": target,
                "src_marker": fid_s,
                "tgt_marker": fid_t,
                "R_gt": T[:3, :3],
                "t_gt": T[:3, 3],
                "visibility": share,
                "liver_id": 900 + i % 2,
                "seed": i,
                "crop_mode": "random",
            },
        )
    config = folder.parent / "fast.yaml"
    # two torch threads, as a node runs: Open3D's RANSAC draws from one generator across its OpenMP threads, so on
    # two of them the same seed gave another pose about one run in seven; `open3d_threads: 1` keeps it reproducible
    config.write_text("method: fpfh-ransac-icp\nnum_threads: 2\n")
    return folder, config


def _calibrate(case_dir, out, *extra):
    folder, config = case_dir
    argv = ["calibrate-bound", "--val", str(folder), "--out", str(out), "--config", str(config), "--workers", "1"]
    return main([*argv, "--cache", str(out.parent / "cache"), *extra])


def test_the_command_calibrates_and_reproduces_its_calibration_bitwise(case_dir, tmp_path, capsys):
    out = tmp_path / "cal.json"
    assert _calibrate(case_dir, out) == 0
    cal = read_calibration(out)
    assert cal.method == "fpfh-ransac-icp" and cal.weights_sha256 == ""
    assert cal.pose == pose_settings(Config.from_yaml(case_dir[1]))  # what a pose is checked against
    raw = json.loads(out.read_text())
    assert raw["provenance"]["seed"] == 0 and raw["provenance"]["sets"][0]["cases"] == 6
    assert sorted(raw["fit_livers"] + raw["calibration_livers"]) == [900, 901]
    first = out.read_bytes()
    for cache in (tmp_path / "cache").iterdir():
        cache.unlink()  # register everything again: the whole command, not only the fit, is reproduced
    assert _calibrate(case_dir, out) == 0
    assert "unchanged (the calibration was reproduced bitwise)" in capsys.readouterr().out
    assert out.read_bytes() == first


def test_a_different_calibration_is_not_written_over_without_force(case_dir, tmp_path, capsys):
    out = tmp_path / "cal.json"
    out.write_text("{}")
    assert _calibrate(case_dir, out) == 2
    err = capsys.readouterr().err
    assert "exists and differs" in err and len(err.strip().splitlines()) == 1
    assert out.read_text() == "{}"
    assert _calibrate(case_dir, out, "--force") == 0
    read_calibration(out)


def test_a_missing_set_is_a_one_line_error(tmp_path, capsys):
    assert main(["calibrate-bound", "--val", str(tmp_path / "nope"), "--out", str(tmp_path / "c.json")]) == 2
    assert "is not a folder of cases" in capsys.readouterr().err


def _write_small_set(folder, seeds=(200, 201, 202, 203)):
    """Four cases of two livers: enough for a calibration, quick to register with `icp`."""
    for i, seed in enumerate(seeds):
        rng = np.random.default_rng(seed)
        share = (0.3, 0.45)[i % 2]
        source, target, T, fid_s, fid_t = partial_case(rng, share=share)
        liver = 900 + i % 2
        case = {"src_pcd": source, "tgt_pcd": target, "src_marker": fid_s, "tgt_marker": fid_t, "R_gt": T[:3, :3]}
        case.update(t_gt=T[:3, 3], visibility=share, liver_id=liver, seed=i, crop_mode="random")
        write_case(folder / f"case_L{liver}_D00_T{i:03d}.npz", case)


@pytest.fixture
def small_set(tmp_path):
    """A fresh small set (its own folder, cache and quick config) per test: the tests change them."""
    folder = tmp_path / "small"
    _write_small_set(folder)
    config = tmp_path / "icp.yaml"
    config.write_text("method: icp\nnum_threads: 2\n")
    return folder, config


def _quick(small_set, out, *extra):
    folder, config = small_set
    argv = ["calibrate-bound", "--out", str(out), "--config", str(config), "--workers", "1"]
    return main(
        [*argv, "--cache", str(out.parent / "cache"), *extra] + ([] if "--val" in extra else ["--val", str(folder)])
    )


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("liver-p2p: error: "), err
    return err


def test_a_case_changed_under_its_name_is_registered_again(small_set, tmp_path, capsys):
    out, cache = tmp_path / "cal.json", tmp_path / "cache"
    assert _quick(small_set, out) == 0 and len(list(cache.iterdir())) == 1
    folder = small_set[0]
    case = next(folder.iterdir())
    case.touch()  # a new time, the same bytes: still the cached set
    assert _quick(small_set, out) == 0 and len(list(cache.iterdir())) == 1
    assert "unchanged" in capsys.readouterr().out
    _write_small_set(folder, seeds=(300, 201, 202, 203))  # the set regenerated: one case differs, same names
    assert _quick(small_set, out, "--force") == 0
    assert len(list(cache.iterdir())) == 2  # collected again, not served from the first set's cache
    assert "wrote" in capsys.readouterr().out


def test_a_damaged_cache_entry_is_collected_again(small_set, tmp_path, capsys, caplog):
    out, cache = tmp_path / "cal.json", tmp_path / "cache"
    assert _quick(small_set, out) == 0
    (entry,) = cache.iterdir()  # written whole: no temporary file left beside it
    first = out.read_bytes()
    for damage in (entry.read_bytes()[:300], b""):  # cut short, then empty
        entry.write_bytes(damage)
        assert _quick(small_set, out) == 0
        assert "unchanged" in capsys.readouterr().out and out.read_bytes() == first
        assert "unreadable cache" in caplog.text and entry.stat().st_size > 300
        caplog.clear()


def test_a_collection_made_before_a_feature_was_added_is_collected_again(small_set, tmp_path, capsys, caplog):
    from liver_p2p_reg.bench import bound_data

    out, cache = tmp_path / "cal.json", tmp_path / "cache"
    assert _quick(small_set, out) == 0
    (entry,) = cache.iterdir()
    first, data = out.read_bytes(), bound_data.load(entry)
    for key in ("features", "interior_features"):  # as a collection of the seven features before log_halves
        data[key] = data[key][:, :7]
    bound_data.save(entry, data)
    assert _quick(small_set, out) == 0
    assert "holds other features" in caplog.text and "unchanged" in capsys.readouterr().out
    assert out.read_bytes() == first and bound_data.load(entry)["features"].shape[1] == 8


def test_the_evidence_settings_are_the_values_the_features_are_computed_with():
    from liver_p2p_reg.registration import confidence, error_bound

    settings = error_bound.EVIDENCE_SETTINGS
    assert settings["normal_neighbors"] == confidence.NORMAL_NEIGHBORS and settings["version"] >= 1
    for name in ("max_source", "max_view", "min_pairs", "max_pairs", "interior_shrink", "interior_points"):
        assert settings[name] == getattr(error_bound, name.upper()), name
    for name in ("rival_gap_mm", "rival_ratio_cap", "half_points", "half_min_points", "half_iterations"):
        assert settings[name] == getattr(error_bound, name.upper()), name


def test_another_interior_stand_in_keys_another_collection(small_set, tmp_path):
    import argparse

    from liver_p2p_reg.cli.calibrate_cmd import collection_cache
    from liver_p2p_reg.config import Config
    from liver_p2p_reg.registration.error_bound import EVIDENCE_SETTINGS

    args, config = argparse.Namespace(cache=str(tmp_path), noise_mm=2.0), Config(method="icp")
    ours = collection_cache(small_set[0], args, config, "")
    assert ours == collection_cache(small_set[0], args, config, "", dict(EVIDENCE_SETTINGS))
    for name in ("interior_shrink", "interior_points", "half_points", "normal_neighbors", "version"):
        other = {**EVIDENCE_SETTINGS, name: EVIDENCE_SETTINGS[name] * 2}
        assert collection_cache(small_set[0], args, config, "", other) != ours, name


def test_outputs_are_checked_before_any_registration(small_set, tmp_path, capsys):
    folder = small_set[0]
    report, readme = tmp_path / "mine.md", tmp_path / "README.md"
    report.write_text("my notes\n")
    readme.write_text("# no markers\n")
    manifest = folder / "manifest.csv"
    manifest.write_text("file\n")
    judge = ["--judge", str(folder)]
    for extra, expected in (
        ([*judge, "--report", str(manifest), "--force"], "is inside"),  # a set's own file
        ([*judge, "--report", str(report)], "exists; pass --force"),
        ([*judge, "--readme", str(tmp_path / "none.md")], "does not exist"),
        ([*judge, "--readme", str(readme)], "lacks the <!-- ERROR_BOUND:START -->"),
        (["--readme", str(readme)], "give --judge"),  # it would be ignored
    ):
        assert _quick(small_set, tmp_path / "cal.json", *extra) == 2
        assert expected in _one_line_error(capsys)
    assert main(["calibrate-bound", "--val", str(folder), "--cache", str(folder / "cache")]) == 2
    assert "--cache" in _one_line_error(capsys)
    assert (
        not (tmp_path / "cache").exists() and not (folder / "cache").exists() and not (tmp_path / "cal.json").exists()
    )
    assert report.read_text() == "my notes\n" and manifest.read_text() == "file\n"


def test_a_set_given_twice_is_refused(small_set, tmp_path, capsys):
    folder = small_set[0]
    twin = tmp_path / "elsewhere" / folder.name  # another folder of the same name: the same key in the results
    twin.mkdir(parents=True)
    for val in ([folder, folder], [folder, tmp_path / "." / folder.name], [folder, twin]):
        assert _quick(small_set, tmp_path / "cal.json", "--val", *map(str, val)) == 2
        assert "give each set once" in _one_line_error(capsys)
    assert not (tmp_path / "cache").exists()
