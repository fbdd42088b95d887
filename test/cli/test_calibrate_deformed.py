"""`liver-p2p calibrate-bound --deformed` on simulated deformed livers: a calibration of the deformed positions that
the non-rigid stage then uses for its bounds, refused where it is not one, noted where its settings differ."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from liver_p2p_reg.cli import main
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom.casefile import source_triangles, write_case
from liver_p2p_reg.phantom.dataset import make_case
from liver_p2p_reg.phantom.simulate import simulate_liver
from liver_p2p_reg.registration import error_calibration
from liver_p2p_reg.registration.error_calibration import BUNDLED_CALIBRATION, DEFORMED, read_calibration
from liver_p2p_reg.registration.registrar import Registrar
from liver_p2p_reg.structures_io import Structure, place_structures

# a small elastic model (fast); a small gain: these livers deform little, the stage is applied on most
SMALL = "method: fpfh-ransac-icp\ndeform_modes: 12\ndeform_target_tets: 1500\ndeform_min_gain: 0.01\n"


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> dict:
    tmp = tmp_path_factory.mktemp("deformed_bound")
    folder = tmp / "cases"
    folder.mkdir()
    cases = []
    for liver in (7, 8):
        sim = simulate_liver(liver, 1, target_tets=2000)
        for k, share in enumerate((0.25, 0.35, 0.45)):
            case = make_case(sim, 0, share, seed=k)
            write_case(folder / f"case_L{liver}_D00_T{k:03d}.npz", {**case, "crop_mode": "random"})
            cases.append(case)
    config = tmp / "small.yaml"
    config.write_text(SMALL)
    out = tmp / "deformed.json"
    argv = ["calibrate-bound", "--deformed", "--val", str(folder), "--out", str(out), "--config", str(config)]
    assert main([*argv, "--workers", "1", "--noise-mm", "0", "--cache", str(tmp / "cache")]) == 0
    return {"tmp": tmp, "out": out, "cases": cases, "config": config}


def _registered(calibrated: dict, extra: str) -> tuple:
    path = calibrated["tmp"] / "run.yaml"
    path.write_text(SMALL + f"deform: true\ndeform_error_calibration_path: {extra}\n")
    case = calibrated["cases"][1]
    registrar = Registrar(Config.from_yaml(path).validate())
    result = registrar.register(
        case["src_pcd"],
        case["tgt_pcd"],
        source_triangles=source_triangles(case),
        source_fiducials_mm=case["src_marker"],
        target_fiducials_mm=case["tgt_marker"],
    )
    return result, case


def test_the_calibration_is_of_deformed_positions_with_the_stage_settings(calibrated: dict) -> None:
    raw = json.loads(calibrated["out"].read_text())
    cal = read_calibration(calibrated["out"])
    assert cal.positions == DEFORMED and raw["positions"] == DEFORMED
    assert cal.deform["deform_modes"] == 12 and cal.deform["deform_target_tets"] == 1500
    assert raw["provenance"]["command"].startswith("liver-p2p calibrate-bound --deformed")
    assert sorted(raw["fit_livers"] + raw["calibration_livers"]) == [7, 8]
    # only the poses the stage was applied on are calibrated on: of the calibrating liver's 3, at least one
    assert 1 <= sum(raw["calibration_poses_per_group"]) <= 3


def test_an_applied_stage_bounds_its_deformed_positions(calibrated: dict) -> None:
    result, case = _registered(calibrated, str(calibrated["out"]))
    assert result.deformation.applied, result.deformation.reason
    assert np.isfinite(result.deformed_error_bound_mm) and result.deformed_error_bound_mm > 0
    assert result.deformed_error_calibration_note == ""
    structure = Structure("tumour", case["src_marker"][:20])
    (placed,) = place_structures(result, [structure])
    assert placed.deformed_error_bound_mm is not None and np.all(placed.deformed_error_bound_mm > 0)
    assert placed.current_error_bound_mm is placed.deformed_error_bound_mm
    # the rigid bound is another calibration's: the two differ
    assert not np.allclose(placed.deformed_error_bound_mm, placed.error_bound_mm)
    payload = result.to_json_dict()
    assert payload["deformed_error_bound_mm"] == pytest.approx(result.deformed_error_bound_mm)
    assert placed.to_json_dict()["deformed_error_bound_mm"][0] == pytest.approx(placed.deformed_error_bound_mm[0])


def test_a_rigid_calibration_is_refused_and_other_settings_are_noted(
    calibrated: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # a rigid file as the user's deformed one: refused in one line before the stage, as the reverse is below
    with pytest.raises(InputError, match="deform_error_calibration_path: .* is not a calibration of deformed"):
        _registered(calibrated, str(BUNDLED_CALIBRATION))
    # a bundled file that cannot be read: the deformation stands, its positions have no bound and say why
    with monkeypatch.context() as patch:
        patch.setattr(error_calibration, "BUNDLED_DEFORMED_CALIBRATION", tmp_path / "absent.json")
        result, case = _registered(calibrated, "''")
    assert result.deformation.applied and result.deformed_error_model is None
    assert "the deformed positions have no bound: error-bound calibration" in result.deformed_error_calibration_note
    (placed,) = place_structures(result, [Structure("tumour", case["src_marker"][:5])])
    assert np.all(np.isnan(placed.current_error_bound_mm))  # no bound rather than the rigid pose's
    # and the reverse: the deformed file as the pose's calibration is refused in one line
    config = Config.from_yaml(calibrated["config"]).replace(error_calibration_path=str(calibrated["out"]))
    with pytest.raises(InputError, match="a calibration of deformed positions, not of the pose's"):
        Registrar(config).register(case["src_pcd"], case["tgt_pcd"])
    raw = json.loads(calibrated["out"].read_text())
    raw["deform"]["deform_regularization"] = 0.5
    other = tmp_path / "other.json"
    other.write_text(json.dumps(raw))
    result, _ = _registered(calibrated, str(other))
    assert "deform_regularization" in result.deformed_error_calibration_note


def test_a_fused_survey_fit_is_told_when_its_calibration_saw_single_views(calibrated: dict) -> None:
    # the file given is a calibration of single-view fits: on a survey's fused surface its coverage is not known
    result, case = _registered(calibrated, str(calibrated["out"]))
    registrar = Registrar(Config.from_yaml(calibrated["tmp"] / "run.yaml").validate())
    registrar.deform(result, case["src_pcd"], case["tgt_pcd"], source_triangles(case), view="survey")
    assert result.deformation.applied and np.isfinite(result.deformed_error_bound_mm)
    assert result.deformed_error_calibration_note == "calibrated on single views; this fit used a fused survey"
    registrar.deform(result, case["src_pcd"], case["tgt_pcd"], source_triangles(case))  # one view: no note
    assert result.deformed_error_calibration_note == ""
