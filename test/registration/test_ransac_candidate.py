"""learned-p2p-ransac-icp: FPFH + RANSAC's pose screened beside P2P's candidates, and the rule that judges it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from synthetic_cases import partial_case

from liver_p2p_reg import Config, InputError, Registrar
from liver_p2p_reg.bench.cases_csv import write_rows
from liver_p2p_reg.bench.ransac_candidate_rule import CANDIDATE, REFERENCE, RUN, SETS, median_ms, verdict
from liver_p2p_reg.errors import RegistrationError

METHOD = "learned-p2p-ransac-icp"


@pytest.fixture(scope="module")
def case():
    return partial_case(np.random.default_rng(7))


def _register(case, config: Config, method: str = METHOD):
    source, target, _, fid_s, fid_t = case
    return Registrar(config).register(
        source, target, method=method, source_fiducials_mm=fid_s, target_fiducials_mm=fid_t
    )


def test_ransac_pose_is_screened_beside_p2p_candidates(case) -> None:
    result = _register(case, Config(k=2, ransac_candidate_visibility=1.0))
    names = [c.name for c in result.candidates]
    assert names[-1] == "fpfh-ransac" and names.count("fpfh-ransac") == 1
    assert names[:-1] == [c.name for c in _register(case, Config(k=2), "learned-p2p-icp").candidates]
    # screened second, after P2P's choice, unless it is a near-duplicate of that choice (then ICP would end alike)
    screened = [c.name for c in result.screened]
    gap_mm = np.abs(result.candidates[-1].T_target_source[:3, 3] - result.screened[0].T_target_source[:3, 3]).max()
    assert screened[1] == "fpfh-ransac" if "fpfh-ransac" in screened else gap_mm < 10.0
    assert result.runtime_ms["ransac"] > 0 and result.rms_tre_mm < 3.0
    ransac = result.candidates[-1]
    assert ransac.n_matches == 0 and np.isfinite(ransac.residual_mm) and ransac.ok


def test_above_the_visibility_threshold_it_is_the_default_bit_for_bit(case) -> None:
    config = Config(k=2, ransac_candidate_visibility=0.0)
    hybrid, default = _register(case, config), _register(case, config, "learned-p2p-icp")
    assert "ransac" not in hybrid.runtime_ms
    assert hybrid.T_target_source.tobytes() == default.T_target_source.tobytes()
    assert [c.name for c in hybrid.screened] == [c.name for c in default.screened]


def test_ransac_pose_answers_when_p2p_has_no_candidate(case) -> None:
    # No dual-softmax confidence reaches 1: every P2P candidate fails; the default raises, the hybrid has RANSAC
    config = Config(k=2, confidence_threshold=1.0, ransac_candidate_visibility=1.0)
    with pytest.raises(RegistrationError, match="no candidate"):
        _register(case, config, "learned-p2p-icp")
    result = _register(case, config)
    assert result.candidates[result.chosen].name == "fpfh-ransac" and result.rms_tre_mm < 3.0


@pytest.mark.parametrize("value", [-0.1, 1.5, float("nan")])
def test_ransac_candidate_visibility_out_of_range_is_refused(value: float) -> None:
    with pytest.raises(InputError, match="ransac_candidate_visibility must be in"):
        Config(ransac_candidate_visibility=value).validate()


def _rows(method: str, tre_small: list[float], tre_above: list[float]) -> list[dict]:
    rows = []
    for i, tre in enumerate(tre_small + tre_above):
        visibility = 0.1 if i < len(tre_small) else 0.25
        rows.append(
            {"case_id": f"c{i}", "method": method, "visibility": visibility, "rms_tre_mm": tre, "failed": False}
        )
    return rows


def _write_runs(root: Path, candidate_small: list[float]) -> None:
    for dataset in SETS:
        rows = _rows(REFERENCE, [4.0, 30.0, 6.0], [5.0, 5.0]) + _rows(CANDIDATE, candidate_small, [5.05, 5.0])
        (root / RUN / dataset).mkdir(parents=True)
        write_rows(root / RUN / dataset / "cases.csv", rows)


def test_rule_passes_a_candidate_better_below_0_2_within_time(tmp_path: Path) -> None:
    _write_runs(tmp_path, [4.0, 8.0, 6.0])  # the gross pose fixed, nothing worse above
    _, line = verdict(str(tmp_path), 140.0)
    assert "passes every rule" in line
    _, slow = verdict(str(tmp_path), 151.0)
    assert "fails rule 3" in slow and "stays the default" in slow


def test_rule_refuses_a_candidate_that_loses_successes(tmp_path: Path) -> None:
    _write_runs(tmp_path, [4.0, 12.0, 11.0])  # lower mean, but one success fewer below 0.2
    table, line = verdict(str(tmp_path), float("nan"))  # and no time measured
    assert "fails rule 1 on real-val-v2" in line and "3 (nan ms" in line
    assert any(f"| {CANDIDATE} | [0.05, 0.2) | 3 | 9.00 | 33.3 % | 0 |" in row for row in table)


def test_median_time_is_read_from_its_own_block_only(tmp_path: Path) -> None:
    speed = tmp_path / "speed.md"
    speed.write_text(
        f"<!-- SPEED:START -->\n| {CANDIDATE} | 99.0 | 1 |\n<!-- SPEED:END -->\n"
        f"<!-- SPEED-RANSAC:START -->\n| learned-p2p-icp | 80.0 | 1 |\n| {CANDIDATE} | 131.5 | 170.2 |\n"
        "<!-- SPEED-RANSAC:END -->\n"
    )
    assert median_ms(speed) == 131.5
    assert np.isnan(median_ms(tmp_path / "missing.md"))
