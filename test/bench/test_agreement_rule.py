"""The feature-agreement rule: the cue, the keyed choice, the composed poses and the verdict; the kept set runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from synthetic_cases import write_cases

from liver_p2p_reg.bench.agreement_rule import (
    agreement,
    composed_tre,
    keyed_choice,
    reproduction_mismatches,
    verdict,
)
from liver_p2p_reg.bench.case_runs import set_rows
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


def test_the_verdict_takes_the_lowest_pooled_mean_among_the_lambdas_without_harm() -> None:
    table, line, chosen = verdict({"a": _set(2.0), "b": _set(2.0), "c": _set(2.0)})
    assert chosen == 0.1 and line.startswith("Lambda 0.1 passes rules 1 and 2")
    assert table[2] == "| a (20) | 9.25 / 1 | 5.05 / 0 | 5.05 / 0 | 8.80 / 1 | 8.80 / 1 |"  # lambda 0, 0.1, ... 1
    assert table[-1] == "| pooled mean | 9.25 | 5.05 | 5.05 | 8.80 | 8.80 |"
    # a flip whose residual is far lower than the truth's is not overruled by any lambda: nothing gains
    assert verdict({"a": _set(1.0), "b": _set(1.0), "c": _set(1.0)})[2] is None


def test_set_runs_are_kept_by_settings_and_never_mixed(tmp_path: Path) -> None:
    folder = tmp_path / "cases"
    write_cases(folder, per_bin=1)
    settings = Config(method="fpfh-ransac-icp").to_dict()
    rows = set_rows(str(folder), run_case, settings, tmp_path / "out", below_visibility=0.35, workers=1)
    assert [r["case_id"] for r in rows] == ["case_0_0", "case_0_0+noise2mm", "case_1_0", "case_1_0+noise2mm"]
    saved = json.loads((tmp_path / "out" / "cases.json").read_text())
    assert json.dumps(saved["rows"]) == json.dumps(rows) and saved["settings"] == settings  # NaN != NaN: as text
    for path in folder.iterdir():  # a second call reads the kept rows: it needs no case any more
        path.unlink()
    again = set_rows(str(folder), run_case, settings, tmp_path / "out", below_visibility=0.35, workers=1)
    assert json.dumps(again) == json.dumps(rows)
    with pytest.raises(InputError, match="made with other settings"):
        set_rows(str(folder), run_case, {**settings, "k": 7}, tmp_path / "out", below_visibility=0.35, workers=1)
    with pytest.raises(InputError, match="made with other settings"):  # what else the run was told counts too
        set_rows(str(folder), run_case, settings, tmp_path / "out", below_visibility=0.35, workers=1, tag={"fs": True})
