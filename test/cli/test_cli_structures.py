"""`liver-p2p register|replay --structures FILE[:LABEL]`: positions and bounds in the JSON, the verdict, bad files in one line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from synthetic_cases import partial_case

from liver_p2p_reg.cli import main
from liver_p2p_reg.cloud_io import save_points
from liver_p2p_reg.metrics import transform_points

BAG_A = Path(__file__).resolve().parents[2] / "bags" / "insilico_L9000001_D00_T007_random"


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> dict:
    tmp = tmp_path_factory.mktemp("structures")
    rng = np.random.default_rng(11)
    source, target, T, fid_s, fid_t = partial_case(rng)
    inside = source.mean(axis=0)
    d = rng.normal(size=(25, 3))
    tumour = inside + 3.0 * d / np.linalg.norm(d, axis=1, keepdims=True)  # a 6 mm tumour ~200 mm from the origin
    vessel = inside + np.linspace(-30, 30, 15)[:, None] * [0.2, 1.0, 0.1]
    files = {"source.ply": source, "target.xyz": target, "fs.npy": fid_s, "ft.npy": fid_t}
    files |= {"tumour.xyz": tumour, "vessel.npy": vessel}
    for name, points in files.items():
        save_points(tmp / name, points)
    (tmp / "empty.xyz").write_text("")
    with_nan = tumour.copy()
    with_nan[0, 2] = np.inf
    np.save(tmp / "nan.npy", with_nan)
    np.save(tmp / "metres.npy", tumour / 1000.0)
    return {"dir": tmp, "T": T, "tumour": tumour, "vessel": vessel, **{k: str(tmp / k) for k in files}}


def register(case: dict, *extra: str) -> list[str]:
    return ["register", case["source.ply"], case["target.xyz"], "--method", "procrustes",
            "--source-fiducials", case["fs.npy"], "--target-fiducials", case["ft.npy"], *extra]  # fmt: skip


def test_each_structure_moved_by_the_pose_with_a_bound_per_point(case: dict, tmp_path: Path, capsys) -> None:
    out = tmp_path / "r.json"
    argv = register(case, "--structures", f"{case['tumour.xyz']}:Tumour 1", case["vessel.npy"], "-o", str(out))
    assert main(argv) == 0
    result = json.loads(out.read_text())
    T = np.array(result["transform"])
    structures = result["structures"]
    assert [s["label"] for s in structures] == ["Tumour 1", "vessel"]
    for entry, points in zip(structures, (case["tumour"], case["vessel"]), strict=True):
        np.testing.assert_allclose(entry["position_mm"], transform_points(T, points), atol=1e-5)
        bounds = np.array(entry["error_bound_mm"], dtype=float)
        assert len(bounds) == len(points) == entry["n_points"] and np.isfinite(bounds).all() and (bounds > 0).all()
        assert entry["max_error_bound_mm"] == pytest.approx(bounds.max()) and entry["error_coverage"] == 0.9
    # the verdict follows the structures' bounds (config structure_error_warn_mm, 10 mm by default)
    widest = max(structures, key=lambda s: s["max_error_bound_mm"])
    assert (widest["label"] in " ".join(result["warnings"])) == (widest["max_error_bound_mm"] > 10.0)
    assert "structures" in capsys.readouterr().out  # the summary line says so


def test_the_verdict_moves_with_the_structure_limit(case: dict, tmp_path: Path, capsys) -> None:
    results = []
    for limit in (0.0, 1e6):
        config = tmp_path / f"c{limit:g}.yaml"
        config.write_text(f"structure_error_warn_mm: {limit}\n")
        assert main(register(case, "--structures", case["tumour.xyz"], "--config", str(config), "-q")) == 0
        results.append(json.loads(capsys.readouterr().out))
    strict, lenient = results
    assert strict["status"] == "WARN" and any("tumour" in w for w in strict["warnings"])
    assert not any("tumour" in w for w in lenient["warnings"])


@pytest.mark.parametrize(
    ("spec", "words"),
    [
        ("missing.ply", "file not found"),
        ("empty.xyz", "no points"),
        ("nan.npy", "NaN or infinite"),
        ("metres.npy", "metres"),
    ],
)
def test_a_bad_structure_file_is_one_line_and_exit_2(case: dict, spec: str, words: str, capsys) -> None:
    bad = str(case["dir"] / spec)
    assert main(register(case, "--structures", case["tumour.xyz"], bad)) == 2
    out = capsys.readouterr()
    assert out.out == ""  # nothing registered, nothing half-printed
    (line,) = out.err.strip().splitlines()
    assert line.startswith("liver-p2p: error: structure '") and words in line and spec in line


def test_duplicate_labels_and_the_replay_option(case: dict, capsys) -> None:
    assert main(register(case, "--structures", f"{case['tumour.xyz']}:t", f"{case['vessel.npy']}:t")) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "given twice" in line
    assert main(["replay", str(BAG_A), "--structures", str(case["dir"] / "metres.npy")]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("liver-p2p: error: structure 'metres'")


def test_a_structure_far_from_the_model_is_refused(case: dict, capsys) -> None:
    # 5 m off: another frame or unit; it used to be moved with the pose and given a sub-millimetre bound
    far = Path(case["dir"]) / "far.xyz"
    save_points(far, case["tumour"] + 5000.0)
    assert main(register(case, "--structures", str(far))) == 2
    err = capsys.readouterr().err.strip()
    assert "structure 'far': a point lies" in err and "outside the preop model's bounding box" in err
    assert "\n" not in err
