"""Cross-fitted verdicts of a candidate bound calibration on validation collections: what the selection rules
(docs/benchmark_real/RULE_bound_*.md) compare candidates by."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from liver_p2p_reg.bench import bound_data
from liver_p2p_reg.bench.bound_fit import calibrate
from liver_p2p_reg.bench.bound_report import BAD_MM, TRUE_BINS, bad_ok_mask, judge
from liver_p2p_reg.registration.error_calibration import calibration_from_dict

SEED = 0  # the calibration's own liver split


def cross_fitted(data: dict[str, np.ndarray], config: Any, **calibrate_options: Any) -> dict[str, Any]:
    """Both folds of the calibration's liver split (seed 0) summed, each judged on the half that did not make its
    quantiles, at true visibility [0.05, 0.3) with the product's verdict: bad poses with OK, the share of good poses
    warned, the marker coverage of the bound per true-visibility bin. `calibrate_options` go to
    `bound_fit.calibrate` (rival edges, the scale's features)."""
    bad_ok = good = good_warned = 0
    covered: dict[tuple[float, float], list[float]] = {b: [] for b in TRUE_BINS}
    in_range = (data["visibility"] >= TRUE_BINS[0][0]) & (data["visibility"] < TRUE_BINS[-1][1])
    for swap in (False, True):
        raw = calibrate(data, SEED, swap=swap, **calibrate_options)
        held_out = np.isin(data["liver_id"], raw["fit_livers"])  # the half whose quantiles it did not make
        part = bound_data.subset(data, held_out & in_range)
        cal = calibration_from_dict({**raw, "method": config.method, "weights_sha256": ""})
        judged = judge(part, cal, config.error_coverage, config.structure_error_warn_mm)
        bad = part["rms_mm"] >= BAD_MM
        bad_ok += int(bad_ok_mask(part, judged).sum())
        good += int((~bad).sum())
        good_warned += int((~bad & judged["warned"]).sum())
        for lo, hi in TRUE_BINS:
            sel = (part["visibility"] >= lo) & (part["visibility"] < hi)
            covered[(lo, hi)] += judged["covered"][sel].tolist()
    return {
        "bad_ok": bad_ok,
        "good_warned": good_warned / max(good, 1),
        "coverage": {b: float(np.mean(v)) if v else math.nan for b, v in covered.items()},
    }


def rule_failures(candidate: dict[str, Any], baseline: dict[str, Any], min_gain: float, coverage_floor: float) -> list:
    """Why a candidate's `cross_fitted` verdicts fail the selection rules' shared criteria against the baseline's
    (empty: it passes them): (a) no more bad poses with OK, (c) every bin's coverage at least min(floor, the
    baseline's lowest bin), (b) good poses warned at least `min_gain` (absolute) below the baseline's."""
    floor = min(coverage_floor, min(baseline["coverage"].values()))
    fails = []
    if candidate["bad_ok"] > baseline["bad_ok"]:
        fails.append(f"(a) {candidate['bad_ok']} bad poses OK > {baseline['bad_ok']}")
    low = min(candidate["coverage"].values())
    if low < floor:
        fails.append(f"(c) lowest bin coverage {low:.1%} < {floor:.1%}")
    if candidate["good_warned"] > baseline["good_warned"] - min_gain:
        fails.append(
            f"(b) good warned {candidate['good_warned']:.1%}, not {min_gain * 100:g} points below "
            f"{baseline['good_warned']:.1%}"
        )
    return fails
