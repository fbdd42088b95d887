"""The deformed-screening rule: the keys, the judged choice, the composed poses, the verdict; real collected rows."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from synthetic_cases import write_cases

from liver_p2p_reg.bench.cases import case_info
from liver_p2p_reg.bench.deformed_screening import (
    SETTINGS,
    check_mismatches,
    collect_case,
    composed_tre,
    judged_case,
    judged_choice,
    judgement_table,
    key,
    margin_verdict,
    reproduction_mismatches,
    verdict,
)
from liver_p2p_reg.config import Config


def _contender(short: float, full: float, tre: float, deformed=None, gain=None, chosen=False) -> dict:
    return {
        "short_residual_mm": short,
        "full_residual_mm": full,
        "deformed_residual_mm": deformed,
        "holdout_gain": gain,
        "rms_tre_mm": tre,
        "chosen": chosen,
    }


def test_each_judge_keys_its_own_number_and_falls_back_where_the_stage_did_not_run() -> None:
    c = _contender(2.0, 1.9, 5.0, deformed=1.5, gain=0.2)
    assert key(c, "rigid") == 1.9
    assert key(c, "deformed") == 1.5
    assert key(c, "predictive") == pytest.approx(1.2)
    no_gain = _contender(2.0, 1.9, 5.0, deformed=1.5)
    assert key(no_gain, "predictive") == 1.5
    no_stage = _contender(2.0, 6.0, 5.0)  # a gross pose: the stage did not fit
    assert key(no_stage, "deformed") == key(no_stage, "predictive") == 6.0


def test_only_contenders_within_the_ratio_are_judged_and_the_first_of_equals_wins() -> None:
    flip = _contender(2.0, 2.1, 90.0, deformed=2.0, chosen=True)
    truth = _contender(2.3, 2.0, 6.0, deformed=1.6)  # 1.15 x the lowest short residual
    assert judged_choice([flip, truth], None, 1.0) == 0  # the screening's own: the lowest short residual
    assert judged_choice([flip, truth], "rigid", 1.1) == 0  # the truth is not a contender at 1.1
    assert judged_choice([flip, truth], "rigid", 1.25) == 1
    assert judged_choice([flip, truth], "deformed", 1.25) == 1
    twins = [_contender(2.0, 2.0, 9.0, chosen=True), _contender(2.0, 2.0, 5.0)]
    assert judged_choice(twins, "rigid", 1.5) == 0
    row = {"case_id": "c", "visibility": 0.12, "rms_tre_mm": 90.0, "screened": [flip, truth]}
    assert composed_tre([row], "rigid", 1.5).tolist() == [6.0]
    assert composed_tre([row], None).tolist() == [90.0]
    assert composed_tre([{**row, "screened": []}], "rigid", 1.5).tolist() == [90.0]  # nothing kept: the own pose
    assert reproduction_mismatches([row]) == []
    assert reproduction_mismatches([{**row, "rms_tre_mm": 6.0}]) == ["c"]


def _set(spoil: bool = False) -> list[dict]:
    """20 small views: one flip every judge from r 1.25 up mends; with `spoil`, a right pose the rigid judge loses."""
    rows = [{"case_id": f"g{i}", "visibility": 0.1, "rms_tre_mm": 5.0, "screened": []} for i in range(18)]
    flip = [_contender(2.0, 2.1, 90.0, deformed=2.0, chosen=True), _contender(2.3, 2.0, 6.0, deformed=1.6)]
    rows.append({"case_id": "f", "visibility": 0.1, "rms_tre_mm": 90.0, "screened": flip})
    good = [_contender(2.0, 2.0, 5.0, deformed=1.5, chosen=True), _contender(2.05, 1.95, 80.0, deformed=1.9)]
    rows.append({"case_id": "s", "visibility": 0.15, "rms_tre_mm": 5.0, "screened": good if spoil else good[:1]})
    return rows


def test_the_verdict_takes_the_cheapest_of_the_lowest_pooled_means_without_harm() -> None:
    table, line, chosen = verdict({"a": _set(), "b": _set(), "c": _set()})
    assert chosen == ("rigid", 1.25) and line.startswith("Rigid r1.25 passes rules 1 and 2 (pooled mean 9.25 -> 5.05")
    assert (
        table[2]
        == "| a (20) | 9.25 / 1 | 9.25 / 1 | 5.05 / 0 | 5.05 / 0 | 9.25 / 1 | 5.05 / 0 | 5.05 / 0 | 9.25 / 1 | 5.05 / 0 | 5.05 / 0 |"
    )
    # the rigid judge spoils a right pose on one set (80 mm: a gross pose more): only the deformed judges pass
    table, line, chosen = verdict({"a": _set(), "b": _set(), "c": _set(spoil=True)})
    assert chosen == ("deformed", 1.25), (line, table)  # at 1.1 the flip's truth (1.15 x) is not a contender
    # nothing mended anywhere: no gain, none chosen
    calm = [r if r["case_id"] != "f" else {**r, "rms_tre_mm": 6.0, "screened": []} for r in _set()]
    assert verdict({"a": calm, "b": calm, "c": calm})[2] is None


def test_collected_rows_reproduce_the_methods_own_pose(tmp_path: Path) -> None:
    paths = write_cases(tmp_path / "cases", per_bin=1)[:3]  # ellipsoids at 20-50 %: the threshold is raised to reach
    config = Config.from_dict({**SETTINGS, "ransac_candidate_visibility": 1.0}).to_dict()
    rows = [collect_case(case_info(path), config) for path in paths]
    contenders = [c for row in rows for c in row["screened"]]
    assert contenders and any(c["deformed_residual_mm"] is not None for c in contenders)  # the stage ran on some
    for row in rows:
        if row["screened"]:
            assert sum(c["chosen"] for c in row["screened"]) == 1
            lowest = min(c["short_residual_mm"] for c in row["screened"])
            assert all(c["short_residual_mm"] <= 1.5 * lowest for c in row["screened"])
            assert row["added_ms"] > 0.0
    for c in contenders:
        assert np.isfinite(c["full_residual_mm"]) and np.isfinite(c["rms_tre_mm"])
        if c["full_residual_mm"] > 5.0:  # deform_max_residual_mm: the stage refuses a gross pose before its fit
            assert c["deformed_residual_mm"] is None and c["holdout_gain"] is None
    assert reproduction_mismatches(rows) == []


def test_the_built_in_judge_gives_the_composed_pose(tmp_path: Path) -> None:
    """Rule 3's check on real cases: contender_judge_ratio 1.5 built in gives the pose composed from kept numbers."""
    paths = write_cases(tmp_path / "cases", per_bin=1)[:3]
    config = Config.from_dict({**SETTINGS, "ransac_candidate_visibility": 1.0}).to_dict()
    infos = [case_info(path) for path in paths]
    kept = [collect_case(info, config) for info in infos]
    judged = [judged_case(info, config) for info in infos]
    assert check_mismatches(judged, kept) == []
    assert [r["own_mm"] for r in judged] == pytest.approx([r["rms_tre_mm"] for r in kept])
    assert all(np.isfinite(r["bound_mm"]) and r["judge_ms"] >= 0 for r in judged)
    assert any(r["judge_ms"] > 0 for r in judged)  # the judge ran on some
    off = [{**judged[0], "judged_mm": judged[0]["judged_mm"] + 1.0}, *judged[1:]]
    assert check_mismatches(off, kept) == [judged[0]["case_id"]]


def test_the_judgement_table_reads_the_noise_copies_per_bin() -> None:
    def row(i: int, vis: float, own: float, judged: float, noise: bool = True) -> dict:
        return {
            "case_id": f"c{i}" + ("+noise2mm" if noise else ""),
            "visibility": vis,
            "own_mm": own,
            "judged_mm": judged,
            "bound_mm": 5.0,
        }

    rows = [row(0, 0.12, 30.0, 6.0), row(1, 0.13, 6.0, 8.0), row(2, 0.12, 90.0, 90.0, noise=False)]
    table = judgement_table({"s": rows})
    assert table[2] == "| s | [0.10, 0.15) | 2 | 18.00 / 50.0 % / 1 | 7.00 / 100.0 % / 0 | 5.00 | 1.40x |"
    assert len(table) == 3  # no other bin has a pose


def test_a_margin_keeps_the_screenings_choice_unless_the_stage_clearly_prefers_another() -> None:
    own = _contender(2.0, 2.0, 5.0, deformed=2.00, chosen=True)
    close = _contender(2.1, 2.0, 90.0, deformed=1.97)  # 1.5 % lower
    clear = _contender(2.2, 2.0, 6.0, deformed=1.80)  # 10 % lower
    assert judged_choice([own, close], "deformed", 1.5, margin=0.0) == 1
    assert judged_choice([own, close], "deformed", 1.5, margin=0.02) == 0
    assert judged_choice([own, close, clear], "deformed", 1.5, margin=0.05) == 2
    assert judged_choice([own, close, clear], "deformed", 1.5, margin=0.10) == 0  # 1.80 is not below 0.9 x 2.00
    twin_first = [_contender(2.1, 2.0, 7.0, deformed=1.5), _contender(2.0, 2.0, 5.0, deformed=1.5, chosen=True)]
    assert judged_choice(twin_first, "deformed", 1.5) == 0  # margin 0: the judge as chosen, first of equals
    assert judged_choice(twin_first, "deformed", 1.5, margin=0.02) == 1  # an equal key never overrules
    table, line, chosen = margin_verdict({"a": _set(), "b": _set(), "c": _set()})
    assert (
        chosen is None and "none is chosen" in line and table[0].startswith("| set (poses at [0.05, 0.2)) | margin 0 |")
    )
