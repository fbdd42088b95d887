"""Aggregates over benchmark rows: per-bin RMS-TRE, success rates, Wilcoxon rank-sum tests, runtimes."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.stats import ranksums

from liver_p2p_reg.bench.cases import BIN_EDGES, BIN_LABELS, visibility_bin

Row = dict[str, Any]
ALPHA = 0.05  # significance level of the rank-sum tests (the paper's)
SUCCESS_TAU_MM = 20.0  # success = RMS-TRE below this and no failure (the paper's tau)
SAFETY_TAU_MM = 10.0  # the laparoscopic safety margin: success at this tau is reported beside it
# Preferred display order; the Procrustes oracle first, the rigid bound next, unknown methods last.
METHOD_ORDER = (
    "procrustes",
    "bound",
    "icp",
    "fgr",
    "fpfh",
    "fpfh-ransac",
    "fpfh-ransac-icp",
    "fpfh-p2p",
    "fpfh-p2p-icp",
    "learned",
    "learned-ransac",
    "learned-p2p",
    "learned-p2p-icp",
)


def order_methods(methods: set[str] | list[str]) -> list[str]:
    """Methods in display order: the oracle first, then METHOD_ORDER, then alphabetical; a
    `method[fs]` row (with the sensor origin) right after its method."""
    rank = {m: i for i, m in enumerate(METHOD_ORDER)}

    def key(m: str) -> tuple[int, str, bool]:
        base = m.removesuffix("[fs]")
        return rank.get(base, len(rank)), base, m != base

    return sorted(set(methods), key=key)


def main_rows(rows: list[Row], with_added_noise: bool = False) -> list[Row]:
    """Rows of the main runs (not ablation variants), by default without benchmark-added noise."""
    return [r for r in rows if not r.get("variant") and (with_added_noise or not r.get("added_noise_mm", 0.0) > 0)]


def by_bin(rows: list[Row], key: str = "rms_tre_mm") -> list[np.ndarray]:
    """Values of `key` grouped by visibility bin (one array per bin in BIN_LABELS)."""
    groups: list[list[float]] = [[] for _ in BIN_LABELS]
    for r in rows:
        b = visibility_bin(r["visibility"])
        if b is not None:
            groups[b].append(float(r[key]))
    return [np.asarray(g, float) for g in groups]


def in_bin(index: int) -> Callable[[Row], bool]:
    """Whether a row's visibility lies in bin `index` of BIN_LABELS (the last bin is closed)."""
    lo, hi = BIN_EDGES[index], BIN_EDGES[index + 1]
    last = index == len(BIN_LABELS) - 1
    return lambda r: lo <= r["visibility"] < hi or (last and r["visibility"] == hi)


def select(rows: list[Row], **equal: Any) -> list[Row]:
    """Rows whose fields equal the given values."""
    return [r for r in rows if all(r.get(k) == v for k, v in equal.items())]


def where(rows: list[Row], pred: Callable[[Row], bool]) -> list[Row]:
    """Rows for which `pred` holds."""
    return [r for r in rows if pred(r)]


def success(rows: list[Row], tau_mm: float = SUCCESS_TAU_MM) -> np.ndarray:
    """Boolean per row: no failure and RMS-TRE below tau."""
    return np.array([(not r["failed"]) and r["rms_tre_mm"] < tau_mm for r in rows], bool)


def success_rate(rows: list[Row], tau_mm: float = SUCCESS_TAU_MM) -> float:
    """Share of successful rows (nan for no rows)."""
    return float(np.mean(success(rows, tau_mm))) if rows else math.nan


def success_curve(rows: list[Row], taus_mm: np.ndarray) -> np.ndarray:
    """Success rate for each tau (failures never count as successes)."""
    if not rows:
        return np.full(len(taus_mm), np.nan)
    tre = np.array([math.inf if r["failed"] else r["rms_tre_mm"] for r in rows], float)
    return np.array([float(np.mean(tre < t)) for t in taus_mm])


def mean_std(values: np.ndarray) -> tuple[float, float]:
    """Mean and population std (nan for no values)."""
    if values.size == 0:
        return math.nan, math.nan
    return float(np.mean(values)), float(np.std(values))


def rank_sum(a: np.ndarray, b: np.ndarray) -> float:
    """Two-sided Wilcoxon rank-sum p-value of a vs b; nan when either side has < 2 values."""
    if a.size < 2 or b.size < 2:
        return math.nan
    if np.array_equal(np.sort(a), np.sort(b)):
        return 1.0
    return float(ranksums(a, b).pvalue)


def p2p_pairs(methods: list[str]) -> list[tuple[str, str]]:
    """(with P2P, without) pairs present: `X-p2p` vs `X` and vs `X-ransac`; `X-p2p-icp` vs `X-ransac-icp`."""
    pairs = []
    present = set(methods)
    for m in methods:
        if m.endswith("-p2p"):
            base = m[: -len("-p2p")]
            pairs += [(m, other) for other in (base, f"{base}-ransac") if other in present]
        elif m.endswith("-p2p-icp"):
            other = m[: -len("-p2p-icp")] + "-ransac-icp"
            if other in present:
                pairs.append((m, other))
    return pairs


def percentile(values: np.ndarray, q: float) -> float:
    """Percentile of finite values (nan when there are none)."""
    values = values[np.isfinite(values)]
    return float(np.percentile(values, q)) if values.size else math.nan


def stage_columns(rows: list[Row]) -> list[str]:
    """Per-stage runtime columns present in the rows, e.g. `runtime_features_ms`."""
    return sorted({k for r in rows for k in r if k.startswith("runtime_") and k != "runtime_ms"})
