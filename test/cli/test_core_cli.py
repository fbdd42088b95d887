"""`liver-p2p register` end to end on generated files, including every bad-input case."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from synthetic_cases import partial_case

from liver_p2p_reg.cli import main
from liver_p2p_reg.cloud_io import load_points, save_points
from liver_p2p_reg.metrics import rms_tre_mm


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A complete blob as PLY, its moved partial crop as XYZ, fiducials as NPY."""
    tmp = tmp_path_factory.mktemp("clouds")
    source, target, T, fid_s, fid_t = partial_case(np.random.default_rng(11))
    paths = {name: tmp / name for name in ("source.ply", "target.xyz", "fid_s.npy", "fid_t.npy")}
    save_points(paths["source.ply"], source)
    save_points(paths["target.xyz"], target)
    np.save(paths["fid_s.npy"], fid_s)
    np.save(paths["fid_t.npy"], fid_t)
    return {"T": T, "fid_s": fid_s, "fid_t": fid_t, "target": target, **{k: str(v) for k, v in paths.items()}}


def test_register_prints_and_writes_json(files: dict, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "result.json"
    argv = ["register", files["source.ply"], files["target.xyz"], "--method", "fpfh-ransac-icp", "--seed", "1"]
    argv += ["--source-fiducials", files["fid_s.npy"], "--target-fiducials", files["fid_t.npy"], "--output", str(out)]
    assert main(argv) == 0
    summary = capsys.readouterr().out  # with --output, stdout gets a line for a person, not the JSON
    written = json.loads(out.read_text())
    assert summary.count("\n") == 1 and summary.startswith("target.xyz: OK fpfh-ransac-icp: residual")
    assert f"JSON -> {out}" in summary and "RMS-TRE" in summary
    assert written["status"] == "OK" and written["warnings"] == [] and written["target"] == files["target.xyz"]
    T = np.array(written["transform"])
    assert T.shape == (4, 4)
    assert rms_tre_mm(T, files["fid_s"], files["fid_t"]) < 2.0
    assert written["rms_tre_mm"] < 2.0
    assert written["method"] == "fpfh-ransac-icp"
    assert written["residual_mm"] < 2.0 and "total" in written["runtime_ms"]
    # An existing output is not overwritten without --force.
    assert main(argv) == 2
    assert "exists; pass --force" in capsys.readouterr().err
    assert main([*argv, "--force", "--json"]) == 0  # --json: the JSON on stdout too
    assert json.loads(capsys.readouterr().out) == json.loads(out.read_text())


def test_p2p_output_lists_candidates(files: dict, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    config = tmp_path / "c.yaml"
    config.write_text("temperature: 0.1\nvoxel_size_norm: 0.05\n")
    assert main(["register", files["source.ply"], files["target.xyz"], "--method", "fpfh-p2p", "--k", "3"]) == 0
    result = json.loads(capsys.readouterr().out)
    # 1 + K plain candidates and as many consensus-started twins
    assert len(result["candidates"]) == 8 and result["chosen_candidate"] in range(8)
    assert all(np.array(c["transform"]).shape == (4, 4) for c in result["candidates"])
    argv = ["register", files["source.ply"], files["target.xyz"], "--method", "fpfh", "--config", str(config)]
    assert main(argv) == 0
    coarse = json.loads(capsys.readouterr().out)
    # no patches: the complete-to-partial candidate and its consensus-started twin
    assert [c["name"] for c in coarse["candidates"]] == ["complete-to-partial", "complete-to-partial-consensus"]
    assert coarse["n_source"] < result["n_source"]


def _error(argv: list[str], capsys: pytest.CaptureFixture) -> str:
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert captured.out == ""  # no JSON, in particular no identity transform
    lines = captured.err.splitlines()
    # Exactly one line: no traceback, no library warning with a source line before it.
    assert len(lines) == 1 and lines[0].startswith("liver-p2p: error:"), captured.err
    return lines[0]


def test_bad_inputs_give_one_line_errors(files: dict, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    src, tgt = files["source.ply"], files["target.xyz"]
    assert "file not found" in _error(["register", str(tmp_path / "nope.ply"), tgt], capsys)
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"\x00\x01 not a ply file")
    assert "garbage.ply" in _error(["register", str(garbage), tgt], capsys)
    empty = tmp_path / "empty.npy"
    np.save(empty, np.zeros((0, 3)))
    assert "empty" in _error(["register", src, str(empty)], capsys)
    nan = tmp_path / "nan.npy"
    np.save(nan, np.full((500, 3), np.nan))
    assert "NaN" in _error(["register", src, str(nan)], capsys)
    empty_text = tmp_path / "empty.xyz"
    empty_text.write_text("")
    assert "no points in the file" in _error(["register", src, str(empty_text)], capsys)
    metres = tmp_path / "metres.npy"  # a depth sensor's cloud saved in metres
    np.save(metres, files["target"] / 1000.0)
    assert "target extent" in _error(["register", src, str(metres)], capsys)
    few = tmp_path / "few.npy"
    np.save(few, files["target"][:20])
    assert "only 20 valid points" in _error(["register", src, str(few)], capsys)
    assert "more than 1.25x the source" in _error(["register", tgt, src, "--method", "fpfh-p2p"], capsys)
    assert "unknown method" in _error(["register", src, tgt, "--method", "magic"], capsys)
    assert "k must be in [1, 64]" in _error(["register", src, tgt, "--k", "0"], capsys)
    assert "needs source and target fiducials" in _error(["register", src, tgt, "--method", "procrustes"], capsys)
    assert "give both" in _error(["register", src, tgt, "--source-fiducials", files["fid_s.npy"]], capsys)
    missing_dir = tmp_path / "no" / "out.json"
    assert "does not exist" in _error(["register", src, tgt, "--output", str(missing_dir)], capsys)


def test_register_writes_the_moved_source_and_an_overlay_plot(
    files: dict, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    import matplotlib.image

    moved, plot = tmp_path / "moved.npy", tmp_path / "check.png"
    argv = ["register", files["source.ply"], files["target.xyz"], "--method", "procrustes"]
    argv += ["--source-fiducials", files["fid_s.npy"], "--target-fiducials", files["fid_t.npy"]]
    assert main([*argv, "--moved", str(moved), "--plot", str(plot)]) == 0
    T = np.array(json.loads(capsys.readouterr().out)["transform"])
    source = load_points(files["source.ply"])
    assert np.allclose(np.load(moved), source @ T[:3, :3].T + T[:3, 3], atol=1e-9)
    # The moved preop lies on the intraop view (the oracle pose of a mildly deformed crop).
    dist, _ = cKDTree(np.load(moved)).query(files["target"], k=1)
    assert np.median(dist) < 1.0
    image = matplotlib.image.imread(plot)
    assert image.shape[1] > 1500 and image.shape[0] > 400 and image[..., :3].std() > 0.05
    # Outputs are checked before any work: a wrong suffix or an existing file is a one-line error.
    assert "--plot" in _error([*argv, "--plot", str(tmp_path / "check.jpg")], capsys)
    assert "exists; pass --force" in _error([*argv, "--moved", str(moved)], capsys)
    assert not (tmp_path / "check.jpg").exists()
    before = plot.stat().st_mtime_ns
    assert main([*argv, "--plot", str(plot), "--force"]) == 0
    assert plot.stat().st_mtime_ns != before


def test_nan_points_are_dropped_with_a_warning(
    files: dict, tmp_path: Path, capsys: pytest.CaptureFixture, caplog: pytest.LogCaptureFixture
) -> None:
    target = files["target"].copy()
    target[::50] = np.nan
    path = tmp_path / "holey.npy"
    np.save(path, target)
    argv = ["register", files["source.ply"], str(path), "--method", "procrustes"]
    argv += ["--source-fiducials", files["fid_s.npy"], "--target-fiducials", files["fid_t.npy"]]
    assert main(argv) == 0
    assert "dropped 105 of 5250 points with NaN/inf" in caplog.text
    assert json.loads(capsys.readouterr().out)["rms_tre_mm"] < 1e-6


def test_the_nodes_warnings_go_to_stderr(
    files: dict, tmp_path: Path, capsys: pytest.CaptureFixture, caplog: pytest.LogCaptureFixture
) -> None:
    argv = ["register", files["source.ply"], files["target.xyz"], "--method", "procrustes"]
    argv += ["--source-fiducials", files["fid_s.npy"], "--target-fiducials", files["fid_t.npy"]]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out)
    assert "poorly constrained" not in caplog.text and result["uncertainty_mm"] < 15.0
    strict = tmp_path / "strict.yaml"
    strict.write_text(f"uncertainty_warn_mm: {result['uncertainty_mm'] / 2}\nresidual_warn_mm: 0.0\n")
    assert main([*argv, "--config", str(strict)]) == 0  # still a pose, now flagged
    assert "poorly constrained by the visible surface" in caplog.text and "residual" in caplog.text
    assert json.loads(capsys.readouterr().out)["transform"]


def test_console_entry_point_exit_status(files: dict, tmp_path: Path) -> None:
    """The real process: non-zero exit and a single error line, no traceback."""
    proc = subprocess.run(
        [sys.executable, "-m", "liver_p2p_reg", "register", files["source.ply"], str(tmp_path / "missing.pcd")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert proc.stderr.strip().startswith("liver-p2p: error: file not found")
    assert "Traceback" not in proc.stderr


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="checks the no-CUDA message")
def test_cuda_without_a_gpu_is_a_clear_error(files: dict, capsys: pytest.CaptureFixture) -> None:
    argv = ["register", files["source.ply"], files["target.xyz"], "--method", "fpfh-p2p", "--device", "cuda"]
    assert "no CUDA device" in _error(argv, capsys)
