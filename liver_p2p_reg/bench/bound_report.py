"""Tables of the error bound on collected poses: coverage, width against the error, and what the verdict says."""

from __future__ import annotations

from typing import Any

import numpy as np

from liver_p2p_reg.bench.bound_data import OTHER_REASONS
from liver_p2p_reg.bench.bound_fit import coverage_at, pose_index

TRUE_BINS = ((0.05, 0.1), (0.1, 0.15), (0.15, 0.2), (0.2, 0.3))  # the protocol's bins, true visibility
BAD_MM = 10.0  # interior RMS error from which a pose is dangerous (the laparoscopic safety margin)
BOOTSTRAP = 2000


def family(set_name: str) -> str:
    """The deformation family and crop of a set, from its name."""
    fam = "ARAP" if "arap" in set_name else "FEM"
    return f"{fam}, {'camera' if 'camera' in set_name else 'random'} crops"


def judge(data: dict[str, np.ndarray], calibration: Any, coverage: float, warn_mm: float) -> dict[str, np.ndarray]:
    """Per pose: covered share of its markers, interior bound, verdict; per marker its bound."""
    point_bound, pose_bound = coverage_at(data, calibration, coverage)
    per = pose_index(data)
    n = len(data["count"])
    covered = np.bincount(per, (data["errors"] <= point_bound).astype(float), minlength=n) / np.maximum(
        data["count"], 1
    )
    others = np.array([bool(r) for r in data["reasons"]])  # "failed" and every other reason warn
    bound_warns = ~(pose_bound <= warn_mm)
    return {
        "covered": covered,
        "pose_bound": pose_bound,
        "pose_covered": data["rms_mm"] <= pose_bound,
        "point_bound": point_bound,
        "warned": others | bound_warns,
        "bound_warns": bound_warns,
        "other_warns": others,
    }


def bin_rows(data: dict[str, np.ndarray], judged: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """One row per (family, true-visibility bin) and a pooled row per family."""
    rows = []
    per = pose_index(data)
    fams = np.array([family(s) for s in data["set"]])
    for fam in sorted(set(fams)):
        for lo, hi in [*TRUE_BINS, (TRUE_BINS[0][0], TRUE_BINS[-1][1])]:
            sel = (fams == fam) & (data["visibility"] >= lo) & (data["visibility"] < hi)
            if sel.any():
                rows.append(_row(data, judged, per, sel, fam, f"[{lo:.2f}, {hi:.2f})"))
    return rows


def _row(data: dict, judged: dict, per: np.ndarray, sel: np.ndarray, fam: str, label: str) -> dict[str, Any]:
    marker = sel[per]
    bad = data["rms_mm"] >= BAD_MM
    warned = judged["warned"]
    bounds = judged["point_bound"][marker]
    err = data["errors"][marker]
    good = sel & ~bad
    return {
        "family": fam,
        "bin": label,
        "poses": int(sel.sum()),
        "coverage": float(np.mean(judged["covered"][sel])),
        "pose_coverage": float(np.mean(judged["pose_covered"][sel])),
        "median_bound_mm": float(np.median(bounds)),
        "median_error_mm": float(np.median(err)),
        "width_ratio": float(np.median(bounds) / max(np.median(err), 1e-9)),
        "bad": int((sel & bad).sum()),
        "bad_ok": int((sel & bad_ok_mask(data, judged)).sum()),
        "worst_ok_mm": worst_ok_mm(data, judged, sel),
        "good_warned": float((good & warned).sum() / max(good.sum(), 1)),
        "bad_by_bound_only": int((sel & bad & judged["bound_warns"] & ~judged["other_warns"]).sum()),
        "bad_by_others_only": int((sel & bad & ~judged["bound_warns"] & judged["other_warns"]).sum()),
    }


def bad_ok_mask(data: dict[str, np.ndarray], judged: dict[str, np.ndarray]) -> np.ndarray:
    """Per pose: bad (interior RMS error >= BAD_MM) and given an OK verdict."""
    return (data["rms_mm"] >= BAD_MM) & ~judged["warned"]


def worst_ok_mm(data: dict[str, np.ndarray], judged: dict[str, np.ndarray], sel: np.ndarray) -> float:
    """The largest interior RMS error (mm) of a selected pose with an OK verdict: how far off an OK can be
    (NaN when every selected pose warned)."""
    passed = sel & ~judged["warned"]
    return float(np.max(data["rms_mm"][passed])) if passed.any() else float("nan")


def passed_bad(data: dict[str, np.ndarray], judged: dict[str, np.ndarray]) -> dict[str, float]:
    """The bad poses with an OK verdict: how many, their interior RMS errors' range and their interior bounds'
    range (mm), and how many of them lie 1.5x the bad threshold or more off (NaN ranges when there are none)."""
    hit = bad_ok_mask(data, judged)
    err, bound = data["rms_mm"][hit], judged["pose_bound"][hit]
    nan = float("nan")
    return {
        "count": int(hit.sum()),
        "error_min_mm": float(err.min()) if hit.any() else nan,
        "error_max_mm": float(err.max()) if hit.any() else nan,
        "bound_min_mm": float(bound.min()) if hit.any() else nan,
        "bound_max_mm": float(bound.max()) if hit.any() else nan,
        "far": int((err >= 1.5 * BAD_MM).sum()),
    }


def bootstrap_coverage(data: dict[str, np.ndarray], judged: dict[str, np.ndarray], seed: int) -> tuple[float, float]:
    """95 % interval of the pooled coverage, resampling livers (the unit that is not exchangeable within)."""
    livers = np.unique(data["liver_id"])
    by = [np.flatnonzero(data["liver_id"] == liver) for liver in livers]
    rng = np.random.default_rng(seed)
    values = []
    for _ in range(BOOTSTRAP):
        pick = np.concatenate([by[i] for i in rng.integers(0, len(livers), len(livers))])
        values.append(float(np.mean(judged["covered"][pick])))
    lo, hi = np.percentile(values, [2.5, 97.5])
    return float(lo), float(hi)


def reason_rows(data: dict[str, np.ndarray], judged: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """What each verdict reason adds: bad poses it catches (alone), good poses it warns."""
    bad = data["rms_mm"] >= BAD_MM
    reasons = {r: np.array([r in str(s).split(",") for s in data["reasons"]]) for r in (*OTHER_REASONS, "failed")}
    reasons["error_bound"] = judged["bound_warns"]
    rows = []
    for name, hit in reasons.items():
        rest = np.zeros_like(hit)
        for other, h in reasons.items():
            if other != name:
                rest |= h
        rows.append(
            {
                "reason": name,
                "bad_caught": int((bad & hit).sum()),
                "bad_caught_alone": int((bad & hit & ~rest).sum()),
                "good_warned": int((~bad & hit).sum()),
            }
        )
    return rows
