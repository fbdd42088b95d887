"""The surface search's rule: rows composed by M/N from one run at 0.20, the checks, the per-bin rule, the test
sets' judgement against published rows."""

from __future__ import annotations

from pathlib import Path

import pytest

from liver_p2p_reg.bench.cases_csv import write_rows
from liver_p2p_reg.bench.surface_search_rule import (
    CANDIDATE_RUN,
    METHOD,
    PUBLISHED,
    REFERENCE_RUN,
    VAL_SETS,
    compose,
    judged_on_test_sets,
    mismatches,
    validation_verdict,
)

# (true visibility, M/N, reference RMS-TRE, candidate's at 0.20): one case each
CASES = [
    (0.07, 0.06, 40.0, 5.0),  # the search rescues a tiny view
    (0.08, 0.09, 6.0, 6.0),
    (0.12, 0.13, 6.0, 30.0),  # ... and spoils one at the operating point, M/N 0.13
    (0.17, 0.18, 7.0, 7.0),
    (0.25, 0.26, 4.0, 4.0),  # no search at all: the same path
]


def _rows(cases=CASES, which: int = 3) -> dict[tuple[str, float], dict]:
    return {
        (f"c{i}", 2.0): {
            "case_id": f"c{i}",
            "method": METHOD,
            "added_noise_mm": 2.0,
            "visibility": visibility,
            "method_visibility": mn,
            "rms_tre_mm": case[which],
            "failed": False,
        }
        for i, case in enumerate(cases)
        for visibility, mn in [case[:2]]
    }


def _write(folder: Path, rows: dict) -> None:
    folder.mkdir(parents=True)
    write_rows(folder / "cases.csv", list(rows.values()))


def test_each_case_takes_the_search_below_the_threshold_and_the_reference_above() -> None:
    ref, cand = _rows(which=2), _rows(which=3)
    assert [r["rms_tre_mm"] for r in compose(ref, cand, 0.10)] == [5.0, 6.0, 6.0, 7.0, 4.0]
    assert [r["rms_tre_mm"] for r in compose(ref, cand, 0.15)] == [5.0, 6.0, 30.0, 7.0, 4.0]
    assert mismatches(ref, cand) == []
    with pytest.raises(ValueError, match="composed from a run at 0.2"):
        compose(ref, cand, 0.25)
    spoiled = _rows(CASES[:4] + [(0.25, 0.26, 4.0, 4.5)], which=3)  # no search, yet another result
    assert len(mismatches(ref, spoiled)) == 1


def test_a_bin_made_worse_rules_a_threshold_out(tmp_path: Path) -> None:
    for name in VAL_SETS:
        _write(tmp_path / REFERENCE_RUN / name, _rows(which=2))
        _write(tmp_path / CANDIDATE_RUN / name, _rows(which=3))
    table, line, chosen = validation_verdict(str(tmp_path))
    # 0.15 and 0.20 search the view at M/N 0.13 and spoil [0.10, 0.15) (rule 2); 0.10 passes
    assert chosen == 0.10 and "0.10 passes rules 1-3" in line
    assert "0.10: 6.00 (passes 1-3), 0.15: 12.00, 0.20: 12.00" in table[-1]
    assert any("| real-val-v2 | 0.15 | [0.10, 0.15) | 1 | 30.00 | 0.0 % | 1 | 1 |" in row for row in table)


def test_the_test_sets_judge_against_the_published_rows(tmp_path: Path, monkeypatch) -> None:
    published = {}
    for name in PUBLISHED:
        published[name] = str(tmp_path / "published" / name)
        _write(Path(published[name]), _rows(which=2))
        _write(tmp_path / "out" / "test-0.10" / name, {**_rows(which=2), **_rows(CASES[:1], which=3)})
    monkeypatch.setattr("liver_p2p_reg.bench.surface_search_rule.PUBLISHED", published)
    table, line, ok, _ = judged_on_test_sets(str(tmp_path / "out"), 0.10, "test-0.10")
    assert ok and "keeps rules 1 and 3 on all four test sets" in line
    assert any("| real-test-v2 | 0.10 | [0.05, 0.10) | 2 | 5.50 | 100.0 % | 0 | 2 |" in row for row in table)
    # a row at M/N >= 0.10 that differs from the published one voids the judgement
    _write(tmp_path / "out" / "test-0.10b" / "real-test-v2", _rows(CASES[:3] + [(0.17, 0.18, 7.0, 9.0)], which=3))
    for name in list(PUBLISHED)[1:]:
        _write(tmp_path / "out" / "test-0.10b" / name, _rows(which=2))
    _, line, ok, _ = judged_on_test_sets(str(tmp_path / "out"), 0.10, "test-0.10b")
    assert not ok and "composition check failed" in line


def test_the_test_sets_judge_against_a_reference_run_and_report_the_published_rows(tmp_path: Path, monkeypatch) -> None:
    published = {}
    for name in PUBLISHED:
        published[name] = str(tmp_path / "published" / name)
        _write(Path(published[name]), _rows(CASES[:4] + [(0.25, 0.26, 4.00001, 4.0)], which=2))  # another CPU
        _write(tmp_path / "out" / "ref" / name, _rows(which=2))
        _write(tmp_path / "out" / "test-0.10" / name, {**_rows(which=2), **_rows(CASES[:1], which=3)})
    monkeypatch.setattr("liver_p2p_reg.bench.surface_search_rule.PUBLISHED", published)
    table, line, ok, notes = judged_on_test_sets(str(tmp_path / "out"), 0.10, "test-0.10", "ref")
    assert ok and any("| real-test-v2 | default (0), this run | [0.05, 0.10) | 2 | 23.00 |" in row for row in table)
    assert (
        notes[0]
        == "real-test-v2: 5 rows beside the published ones, 1 differing, 0 by more than 0.01 mm, the largest by 1e-05 mm"
    )
