"""The default's RANSAC candidate: FPFH + RANSAC's pose screened beside P2P's candidates on small views, and the rule
that judged it (when it was the opt-in `learned-p2p-ransac-icp`)."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
from synthetic_cases import partial_case

from liver_p2p_reg import Config, InputError, Registrar
from liver_p2p_reg.bench.cases_csv import write_rows
from liver_p2p_reg.bench.ransac_candidate_rule import CANDIDATE, REFERENCE, RUN, SETS, median_ms, verdict
from liver_p2p_reg.errors import RegistrationError

METHOD = "learned-p2p-icp"
WITHOUT = {"ransac_candidate_visibility": 0.0}  # the default before the switch: no RANSAC candidate


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
    default = _register(case, Config(k=2, **WITHOUT))
    assert names[:-1] == [c.name for c in default.candidates]
    # on this easy crop RANSAC's pose is P2P's: skipped as a near-duplicate, P2P keeps its own screened poses
    assert [c.name for c in result.screened] == [c.name for c in default.screened]
    assert result.T_target_source.tobytes() == default.T_target_source.tobytes()
    assert result.runtime_ms["ransac"] > 0 and result.rms_tre_mm < 3.0
    ransac = result.candidates[-1]
    assert ransac.n_matches == 0 and np.isfinite(ransac.residual_mm) and ransac.ok


@pytest.mark.parametrize("below", [0.0, 0.01])  # the view's estimated visibility exactly (not below), or just over
def test_above_the_visibility_threshold_it_is_the_default_bit_for_bit(case, below: float) -> None:
    default = _register(case, Config(k=2, **WITHOUT))
    assert "ransac" not in default.runtime_ms and default.visibility > 0.02
    hybrid = _register(case, Config(k=2, ransac_candidate_visibility=default.visibility - below))
    assert "ransac" not in hybrid.runtime_ms and len(hybrid.candidates) == len(default.candidates)
    assert hybrid.T_target_source.tobytes() == default.T_target_source.tobytes()
    assert [c.name for c in hybrid.screened] == [c.name for c in default.screened]


def test_warm_up_takes_ransacs_path_only_where_the_method_has_it(case) -> None:
    source = case[0]
    for method, threshold, warmed in ((METHOD, 0.3, True), (METHOD, 0.0, False), ("learned-p2p-ransac-icp", 0.3, True)):
        registrar = Registrar(Config(k=2, ransac_candidate_visibility=threshold))
        registrar.warm_up(source, method)
        # the source's FPFH: RANSAC's pose was computed on the warm-up's cap, before any real view
        assert any(key.startswith("fpfh:") for key in registrar.cache) is warmed, (method, threshold)
        assert any(key.startswith("icp-source-index:") for key in registrar.cache)  # the rest warmed as before


def test_ransac_pose_is_screened_besides_refine_candidates(case) -> None:
    from liver_p2p_reg.registration.hypotheses import screen_candidates
    from liver_p2p_reg.registration.preprocess import preprocess_pair

    source, target, T, _, _ = case
    config = Config(refine_candidates=1)
    prep = preprocess_pair(source, target, config)
    s, cs, ct = prep.source_norm.scale_mm, prep.source_norm.centroid_mm, prep.target_norm.centroid_mm
    right = np.eye(4)
    right[:3, :3], right[:3, 3] = T[:3, :3], (T[:3, :3] @ cs + T[:3, 3] - ct) / s
    wrong = right @ np.diag([-1.0, -1.0, 1.0, 1.0])  # 180 deg about z: ICP cannot fix it
    other = right @ np.diag([1.0, -1.0, -1.0, 1.0])  # 180 deg about x
    poses = [wrong, other, right]
    # P2P's choice first, then RANSAC's pose (index 2), then P2P's others: one P2P pose and the extra one
    chosen, tried = screen_candidates(poses, [0, 2, 1], prep, config, {}, extra=2)
    assert [i for i, *_ in tried] == [0, 2] and chosen == 2
    assert [i for i, *_ in screen_candidates(poses, [0, 2, 1], prep, config, {})[1]] == [0]  # no extra: P2P's only
    chosen, tried = screen_candidates(poses, [0, 2, 1], prep, config.replace(refine_candidates=2), {}, extra=2)
    assert [i for i, *_ in tried] == [0, 2, 1] and chosen == 2


def test_free_space_ranks_the_ransac_pose_too() -> None:
    # A smaller crop seen from a sensor 1 m out along its outward direction (the node's default path: free
    # space on): every candidate gets its violation, and RANSAC's pose, distinct here, is screened second.
    source, target, T_true, fid_s, fid_t = partial_case(np.random.default_rng(7), share=0.15)
    outward = target.mean(axis=0) - (T_true[:3, :3] @ source.mean(axis=0) + T_true[:3, 3])
    origin = target.mean(axis=0) + 1000.0 * outward / np.linalg.norm(outward)
    result = Registrar(Config(k=2, ransac_candidate_visibility=1.0)).register(
        source, target, method=METHOD, source_fiducials_mm=fid_s, target_fiducials_mm=fid_t, sensor_origin_mm=origin
    )
    assert result.free_space == "on" and result.candidates[-1].name == "fpfh-ransac"
    assert all(np.isfinite(c.free_space_violation) for c in result.candidates + result.screened)
    assert [c.name for c in result.screened][1] == "fpfh-ransac"
    assert np.isfinite(result.free_space_violation) and result.rms_tre_mm < 3.0


def test_ransac_pose_answers_when_p2p_has_no_candidate(case) -> None:
    # No dual-softmax confidence reaches 1: every P2P candidate fails; without RANSAC's pose the method raises
    config = Config(k=2, confidence_threshold=1.0, ransac_candidate_visibility=1.0)
    with pytest.raises(RegistrationError, match="no candidate"):
        _register(case, config.replace(**WITHOUT))
    result = _register(case, config)
    assert result.candidates[result.chosen].name == "fpfh-ransac" and result.rms_tre_mm < 3.0


def test_the_opt_in_name_is_the_default_bit_for_bit(case) -> None:
    config = Config(k=2, ransac_candidate_visibility=1.0)
    default, alias = _register(case, config), _register(case, config, "learned-p2p-ransac-icp")
    assert alias.T_target_source.tobytes() == default.T_target_source.tobytes() and "ransac" in alias.runtime_ms
    assert [c.name for c in alias.candidates] == [c.name for c in default.candidates]


def test_the_default_screens_ransacs_pose_below_0_2_only(case) -> None:
    assert Config().ransac_candidate_visibility == 0.2 and Config().method == METHOD
    small = partial_case(np.random.default_rng(7), share=0.15)
    for view, below in ((small, True), (case, False)):
        result = _register(view, Config(k=2))
        assert (result.visibility < 0.2) is below and ("ransac" in result.runtime_ms) is below


def test_the_opt_in_name_is_the_default_for_calibrations() -> None:
    from liver_p2p_reg.registration.methods import canonical_method

    assert canonical_method("learned-p2p-ransac-icp") == METHOD == canonical_method(METHOD)
    assert canonical_method("fpfh-ransac-icp") == "fpfh-ransac-icp" and canonical_method("no-such") == "no-such"


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


def test_rule_refuses_one_more_gross_pose_above_0_2_and_counts_failures(tmp_path: Path) -> None:
    for dataset in SETS:
        reference = _rows(REFERENCE, [4.0, 30.0, 6.0], [5.0, 25.0])
        candidate = _rows(CANDIDATE, [4.0, 8.0, 6.0], [21.0, 22.0])  # lower mean below 0.2, two gross above
        candidate[0]["failed"] = True  # a failed registration: 1 m in the mean, gross, no success
        (tmp_path / RUN / dataset).mkdir(parents=True)
        write_rows(tmp_path / RUN / dataset / "cases.csv", reference + candidate)
    table, line = verdict(str(tmp_path), 100.0)
    assert "fails rule 1 on real-val-v2, 2 on real-val-v2" in line
    assert any(f"| {CANDIDATE} | [0.05, 0.2) | 3 | 338.00 | 66.7 % | 1 |" in row for row in table)
    assert any(f"| {CANDIDATE} | [0.2, 0.3) | 2 | 21.50 | 0.0 % | 2 |" in row for row in table)


def test_median_time_is_read_from_its_own_block_only(tmp_path: Path) -> None:
    speed = tmp_path / "speed.md"
    speed.write_text(
        f"<!-- SPEED:START -->\n| {CANDIDATE} | 99.0 | 1 |\n<!-- SPEED:END -->\n"
        f"<!-- SPEED-RANSAC:START -->\n| learned-p2p-icp | 80.0 | 1 |\n| {CANDIDATE} | 131.5 | 170.2 |\n"
        "<!-- SPEED-RANSAC:END -->\n"
    )
    assert median_ms(speed) == 131.5
    assert np.isnan(median_ms(tmp_path / "missing.md"))


@pytest.mark.parametrize("share", [0.08, 0.15])
def test_ransac_beside_the_matcher_is_the_sequential_result_bit_for_bit(share: float) -> None:
    """The candidate's RANSAC runs on a thread of its own while the matcher runs (hypotheses.RansacBeside): the pose,
    the candidates and the screened poses are those of running it after the matcher, bit for bit."""
    from liver_p2p_reg.registration import pipeline

    small = partial_case(np.random.default_rng(11), share=share)
    results = {}
    try:
        for beside in (False, True):
            pipeline.RANSAC_BESIDE = beside
            results[beside] = _register(small, Config(k=2))
    finally:
        pipeline.RANSAC_BESIDE = True
    after, beside = results[False], results[True]
    assert "ransac_beside" in beside.runtime_ms and "ransac_beside" not in after.runtime_ms
    assert beside.T_target_source.tobytes() == after.T_target_source.tobytes()
    assert [c.to_json_dict() for c in beside.candidates] == [c.to_json_dict() for c in after.candidates]
    assert [c.to_json_dict() for c in beside.screened] == [c.to_json_dict() for c in after.screened]
    assert "fpfh-ransac" in [c.name for c in beside.candidates]
    assert not [t for t in threading.enumerate() if t.name == "ransac-candidate"]  # none outlives its registration


def test_an_error_in_ransac_beside_reaches_the_caller() -> None:
    """Whatever RANSAC's thread raises is raised where its result is taken, as it would be in line."""
    from liver_p2p_reg.registration.context import MethodContext
    from liver_p2p_reg.registration.hypotheses import RansacBeside, ransac_hypothesis
    from liver_p2p_reg.registration.preprocess import preprocess_pair

    source, target, *_ = partial_case(np.random.default_rng(11), share=0.15)
    config = Config(k=2)
    prep = preprocess_pair(source, target, config, {})
    broken = MethodContext(None, None, (), None, None)  # a cache that is no dict: FPFH's memo cannot be kept
    with pytest.raises(TypeError) as in_line:
        ransac_hypothesis(prep, config, broken, {})
    with pytest.raises(TypeError) as beside:
        RansacBeside(prep, config, broken).result({})
    assert str(beside.value) == str(in_line.value)
