"""The two-part rule of the screening experiments: no set worse (mean, gross poses), then the lowest pooled mean."""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence
from typing import Any

import numpy as np

GROSS_MM = 20.0
MIN_GAIN_MM = 0.2
TIE_MM = 0.01  # pooled means this close are a tie: the earlier candidate (the cheaper or smaller) wins


Choice = Callable[[list[dict[str, Any]]], int]  # a case's kept candidates -> the index of the one taken


def composed(rows: list[dict[str, Any]], choose: Choice) -> np.ndarray:
    """Each case's RMS-TRE when `choose` picks among its kept candidates (`screened`; the method's own pose where
    none were kept)."""
    return np.array(
        [r["screened"][choose(r["screened"])]["rms_tre_mm"] if r["screened"] else r["rms_tre_mm"] for r in rows]
    )


def reproduction_mismatches(rows: list[dict[str, Any]], own: Choice, tolerance_mm: float = 1e-6) -> list[str]:
    """Cases where `own` (the screening's own choice composed from the kept numbers) is not the method's pose: then
    the composition is not the pipeline's."""
    bad = []
    for r in rows:
        if not r["screened"]:
            continue
        pick = r["screened"][own(r["screened"])]
        if not pick["chosen"] or abs(pick["rms_tre_mm"] - r["rms_tre_mm"]) > tolerance_mm:
            bad.append(r["case_id"])
    return bad


def rule_verdict(
    tre: dict[str, dict[Hashable, np.ndarray]],
    baseline: Hashable,
    candidates: Sequence[Hashable],
    label: dict[Hashable, str],
    noun: str,
) -> tuple[list[str], str, Hashable | None]:
    """The table (per set: mean / poses off by >= GROSS_MM, for the baseline and each candidate; then the pooled
    mean), the verdict line, and the chosen candidate (None: none).

    Rule 1: on every set, neither the mean nor the count of gross poses is above the baseline's. Rule 2: among those
    passing, the lowest pooled mean (a tie within TIE_MM: the first in `candidates`' order), lowering the baseline's
    pooled mean by at least MIN_GAIN_MM.
    """
    columns = (baseline, *candidates)
    head = "| set (poses at [0.05, 0.2)) | " + " | ".join(label[c] for c in columns) + " |"
    table = [head, "|" + "---|" * (len(columns) + 1)]
    for name, by in tre.items():
        cells = [f"{by[c].mean():.2f} / {int((by[c] >= GROSS_MM).sum())}" for c in columns]
        table.append(f"| {name} ({len(by[baseline])}) | " + " | ".join(cells) + " |")
    pooled = {c: float(np.concatenate([by[c] for by in tre.values()]).mean()) for c in columns}
    table.append("| pooled mean | " + " | ".join(f"{pooled[c]:.2f}" for c in columns) + " |")
    passing = [
        c
        for c in candidates
        if all(
            by[c].mean() <= by[baseline].mean() and (by[c] >= GROSS_MM).sum() <= (by[baseline] >= GROSS_MM).sum()
            for by in tre.values()
        )
    ]
    if not passing:
        return table, f"No {noun} passes rule 1 on all three sets: none is chosen.", None
    lowest = min(pooled[c] for c in passing)
    best = next(c for c in passing if pooled[c] <= lowest + TIE_MM)
    name = label[best][:1].upper() + label[best][1:]
    gain = pooled[baseline] - pooled[best]
    if gain < MIN_GAIN_MM:
        return (
            table,
            f"{name} passes rule 1 but lowers the pooled mean by {gain:.2f} mm (< {MIN_GAIN_MM}): none is chosen.",
            None,
        )
    return table, f"{name} passes rules 1 and 2 (pooled mean {pooled[baseline]:.2f} -> {pooled[best]:.2f} mm).", best
