"""The feature-agreement rule: the cue, the keyed choice, the composed poses and the verdict; the kept set runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from synthetic_cases import write_cases

from liver_p2p_reg.bench.agreement_rule import (
    SETTINGS,
    agreement,
    collect_case,
    composed_tre,
    keyed_choice,
    reproduction_mismatches,
    verdict,
)
from liver_p2p_reg.bench.case_runs import set_rows
from liver_p2p_reg.bench.cases import case_info
from liver_p2p_reg.bench.failure_sources import run_case
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError


def test_agreement_weighs_the_matches_a_pose_brings_close() -> None:
    source = np.array([[0.0, 0, 0], [100, 0, 0], [0, 100, 0]])
    T = np.eye(4)
    T[:3, 3] = [5.0, 0, 0]
    target = source + [5.0, 0, 0]
    target[2] += [0, 30, 0]  # the third match is 30 mm off under T
    assert agreement(T, source, target, np.array([1.0, 1.0, 2.0])) == pytest.approx(0.5)
    assert agreement(np.eye(4), source, target, np.array([1.0, 1.0, 2.0])) == pytest.approx(0.5)  # 5 mm: within 10
    assert agreement(T, source, target, np.zeros(3)) == 0.0


def _candidate(residual: float, agree: float, tre: float, chosen: bool = False) -> dict:
    return {"short_residual_mm": residual, "agreement": agree, "rms_tre_mm": tre, "chosen": chosen}


def test_the_key_lets_agreement_overrule_a_slightly_lower_residual() -> None:
    flip = _candidate(2.0, 0.05, 90.0, chosen=True)
    truth = _candidate(2.1, 0.20, 6.0)
    assert keyed_choice([flip, truth], 0.0) == 0  # the residual alone: the flip
    assert keyed_choice([flip, truth], 0.1) == 1  # 2.0 x (1 + 0.1 x 0.75) = 2.15 > 2.1
    assert keyed_choice([_candidate(2.0, 0.0, 9.0), _candidate(2.0, 0.0, 5.0)], 1.0) == 0  # no agreement: first
    row = {"case_id": "c", "visibility": 0.12, "rms_tre_mm": 90.0, "screened": [flip, truth]}
    assert composed_tre([row], 0.1).tolist() == [6.0]
    assert reproduction_mismatches([row]) == []
    assert reproduction_mismatches([{**row, "rms_tre_mm": 6.0}]) == ["c"]


def _set(flip_residual: float) -> list[dict]:
    """20 small views; one flip that the agreement corrects, one good pose it spoils when lambda >= 0.5."""
    rows = [{"case_id": f"g{i}", "visibility": 0.1, "rms_tre_mm": 5.0, "screened": []} for i in range(18)]
    flip = [_candidate(flip_residual, 0.05, 90.0, chosen=True), _candidate(2.1, 0.20, 6.0)]
    spoil = [_candidate(2.0, 0.10, 5.0, chosen=True), _candidate(2.5, 0.30, 80.0)]
    rows.append({"case_id": "f", "visibility": 0.1, "rms_tre_mm": 90.0, "screened": flip})
    rows.append({"case_id": "s", "visibility": 0.15, "rms_tre_mm": 5.0, "screened": spoil})
    return rows


def _spoiled_by_any_lambda(good_mm: float = 5.0, bad_mm: float = 150.0) -> list[dict]:
    """The residual's choice is right; any lambda > 0 turns to a pose that agrees more and is wrong."""
    return [_candidate(2.0, 0.05, good_mm, chosen=True), _candidate(2.0001, 0.30, bad_mm)]


def _mended_by_any_lambda(bad_mm: float) -> list[dict]:
    """The residual's choice is `bad_mm` off; any lambda > 0 turns to the right pose (5 mm)."""
    return [_candidate(2.0, 0.05, bad_mm, chosen=True), _candidate(2.0001, 0.30, 5.0)]


def test_the_verdict_takes_the_lowest_pooled_mean_among_the_lambdas_without_harm() -> None:
    table, line, chosen = verdict({"a": _set(2.0), "b": _set(2.0), "c": _set(2.0)})
    assert chosen == 0.1 and line.startswith("Lambda 0.1 passes rules 1 and 2")
    assert table[2] == "| a (20) | 9.25 / 1 | 5.05 / 0 | 5.05 / 0 | 8.80 / 1 | 8.80 / 1 |"  # lambda 0, 0.1, ... 1
    assert table[-1] == "| pooled mean | 9.25 | 5.05 | 5.05 | 8.80 | 8.80 |"
    # a lambda that lowers the pooled mean but raises one set's is not chosen (rule 1 holds on every set)
    worse = _set(2.0) + [{"case_id": "x", "visibility": 0.1, "rms_tre_mm": 5.0, "screened": _spoiled_by_any_lambda()}]
    table, line, chosen = verdict({"a": _set(2.0), "b": _set(2.0), "c": worse})
    assert chosen is None and line.startswith("No lambda passes rule 1"), table
    # ... nor one that lowers every mean but adds a pose off by 20 mm or more on one set
    gross = _set(1.0) + [  # _set(1.0): its flip stays at every lambda below 0.5
        {"case_id": "y", "visibility": 0.1, "rms_tre_mm": 19.0, "screened": _spoiled_by_any_lambda(19.0, 21.0)},
        {"case_id": "z", "visibility": 0.1, "rms_tre_mm": 19.5, "screened": _mended_by_any_lambda(19.5)},
    ]
    assert verdict({"a": _set(2.0), "b": _set(2.0), "c": gross})[2] is None
    # a flip whose residual is far lower than the truth's is not overruled by any lambda: nothing gains
    assert verdict({"a": _set(1.0), "b": _set(1.0), "c": _set(1.0)})[2] is None


def test_set_runs_are_kept_by_settings_and_never_mixed(tmp_path: Path) -> None:
    folder = tmp_path / "cases"
    write_cases(folder, per_bin=1)
    settings = Config(method="fpfh-ransac-icp").to_dict()
    rows = set_rows(str(folder), run_case, settings, tmp_path / "out", below_visibility=0.35, workers=1)
    assert [r["case_id"] for r in rows] == ["case_0_0", "case_0_0+noise2mm", "case_1_0", "case_1_0+noise2mm"]
    saved = json.loads((tmp_path / "out" / "cases.json").read_text())
    assert json.dumps(saved["rows"]) == json.dumps(rows) and saved["settings"] == {
        **settings,
        "below_visibility": 0.35,
        "noise_mm": 2.0,
    }  # NaN != NaN: the rows as text
    for path in folder.iterdir():  # a second call reads the kept rows: it needs no case any more
        path.unlink()
    again = set_rows(str(folder), run_case, settings, tmp_path / "out", below_visibility=0.35, workers=1)
    assert json.dumps(again) == json.dumps(rows)
    with pytest.raises(InputError, match="made with other settings"):
        set_rows(str(folder), run_case, {**settings, "k": 7}, tmp_path / "out", below_visibility=0.35, workers=1)
    with pytest.raises(InputError, match="made with other settings"):  # so does the cut of the cases
        set_rows(str(folder), run_case, settings, tmp_path / "out", below_visibility=0.3, workers=1)
    with pytest.raises(InputError, match="made with other settings"):  # what else the run was told counts too
        set_rows(str(folder), run_case, settings, tmp_path / "out", below_visibility=0.35, workers=1, tag={"fs": True})


def test_set_runs_take_a_visibility_band_and_keep_it_in_the_stamp(tmp_path: Path) -> None:
    folder = tmp_path / "cases"
    write_cases(folder, per_bin=1)  # one case per bin [0.2, 0.3) ... [0.9, 1.0]
    settings = Config(method="fpfh-ransac-icp").to_dict()
    rows = set_rows(
        str(folder), run_case, settings, tmp_path / "out", from_visibility=0.3, below_visibility=0.5, workers=1
    )
    assert [r["case_id"] for r in rows] == ["case_1_0", "case_1_0+noise2mm", "case_2_0", "case_2_0+noise2mm"]
    assert all(0.3 <= r["visibility"] < 0.5 for r in rows)
    assert json.loads((tmp_path / "out" / "cases.json").read_text())["settings"]["from_visibility"] == 0.3
    with pytest.raises(InputError, match="made with other settings"):  # the band's lower end counts
        set_rows(str(folder), run_case, settings, tmp_path / "out", below_visibility=0.5, workers=1)


def test_damaged_kept_rows_and_no_workers_are_one_line_errors(tmp_path: Path) -> None:
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "cases.json").write_text('{"settings": {"method": "icp"}, "rows": [')  # cut short
    with pytest.raises(InputError, match=r"cannot read the kept rows .*cases.json \(JSONDecodeError\): remove it"):
        set_rows(str(tmp_path / "cases"), run_case, {}, tmp_path / "out", below_visibility=0.3, workers=1)
    with pytest.raises(InputError, match="workers must be >= 1, got 0"):
        set_rows(str(tmp_path / "cases"), run_case, {}, tmp_path / "elsewhere", below_visibility=0.3, workers=0)


def test_collected_rows_reproduce_the_methods_own_pose_at_lambda_0(tmp_path: Path) -> None:
    paths = write_cases(tmp_path / "cases", per_bin=1)[:3]  # ellipsoids at 20-50 %: the threshold is raised to reach
    config = Config.from_dict({**SETTINGS, "ransac_candidate_visibility": 1.0}).to_dict()
    rows = [collect_case(case_info(path), config) for path in paths]
    assert any(row["screened"] for row in rows)
    for row in rows:
        if row["screened"]:
            assert sum(c["chosen"] for c in row["screened"]) == 1
            assert all(0.0 <= c["agreement"] <= 1.0 for c in row["screened"])
            assert any(c["name"] == "fpfh-ransac" for c in row["screened"])  # RANSAC's pose is always screened
    assert reproduction_mismatches(rows) == []
