"""The rule of docs/freespace/rule.md: free_space_weight and free_space_warn chosen from a sweep's benchmark rows."""

from __future__ import annotations

import math

import numpy as np

from liver_p2p_reg.bench.jobs import Variant

WEIGHTS = (0.5, 1.0, 2.0, 4.0, 8.0)  # candidate free_space_weight values
WARN_GRID = (0.10, 0.15, 0.20, 0.25, 0.30, 0.40)  # candidate free_space_warn thresholds
METHODS = ("learned-p2p-icp", "learned-p2p", "fpfh-p2p-icp")
GROSS_MM = 20.0  # a weight is admissible when it leaves no more poses off by this than the baseline
GOOD_MM = 10.0  # poses within this are the good ones a warning would flag needlessly
TIE_MM = 0.02  # weights within this of the lowest mean are a tie: the smallest one wins
FALSE_ALARM_SHARE = 0.02  # the warn threshold flags at most this share of the good poses


def variants(methods: list[str], weights: list[float]) -> list[Variant]:
    """Every method without the sensor origin, then with it at each candidate weight."""
    plain = [Variant(m) for m in methods]
    aware = [Variant(m, (("free_space_weight", w),), sensor_aware=True) for w in weights for m in methods]
    return plain + aware


def choose(rows: list[dict], methods: list[str], weights: list[float]) -> tuple[list[str], float, float]:
    """The rule: report lines, the chosen weight and warn threshold."""
    lines = ["| setting | " + " | ".join(f"{m} mean mm" for m in methods) + " | S mm | poses >= 20 mm |", ""]
    lines[1] = "|" + "---|" * (len(methods) + 3)

    def stats(label_of) -> tuple[list[float], float, int]:
        means, gross = [], 0
        for m in methods:
            tre = np.array([r["rms_tre_mm"] for r in rows if r["method"] == label_of(m)], float)
            means.append(float(tre.mean()))
            gross += int((tre >= GROSS_MM).sum())
        return means, float(np.mean(means)), gross

    base_means, base_s, base_gross = stats(lambda m: m)
    lines.append(f"| no origin | {' | '.join(f'{v:.3f}' for v in base_means)} | {base_s:.3f} | {base_gross} |")
    scores = {}
    for w in weights:
        means, s, gross = stats(lambda m, w=w: Variant(m, (("free_space_weight", w),), sensor_aware=True).label)
        lines.append(f"| weight {w:g} | {' | '.join(f'{v:.3f}' for v in means)} | {s:.3f} | {gross} |")
        if gross <= base_gross:
            scores[w] = s
    if not scores:
        return (
            [*lines, "", "No weight keeps the gross poses at the baseline's count: free space stays off."],
            0.0,
            math.inf,
        )
    lowest = min(scores.values())
    weight = min(w for w, s in scores.items() if s <= lowest + TIE_MM)
    chosen = [
        r
        for m in methods
        for r in rows
        if r["method"] == Variant(m, (("free_space_weight", weight),), sensor_aware=True).label
    ]
    good = np.array([r["free_space_violation"] for r in chosen if r["rms_tre_mm"] <= GOOD_MM], float)
    warn = next((t for t in WARN_GRID if np.mean(good > t) <= FALSE_ALARM_SHARE), WARN_GRID[-1])
    lines += [
        "",
        f"Admissible weights (poses >= {GROSS_MM:g} mm not above the baseline's {base_gross}): "
        f"{', '.join(f'{w:g}' for w in scores)}; lowest S {lowest:.3f} mm; chosen weight **{weight:g}** "
        f"(the smallest within {TIE_MM} mm of the lowest).",
        "",
        f"Violation of the chosen weight's poses within {GOOD_MM:g} mm (n = {good.size}): "
        + ", ".join(f"{q}th pct {np.percentile(good, q):.3f}" for q in (50, 90, 95, 98, 99)),
        "",
        "| warn threshold | "
        + " | ".join(f"{t:.2f}" for t in WARN_GRID)
        + " |\n|"
        + "---|" * (len(WARN_GRID) + 1)
        + "\n| share of good poses warned | "
        + " | ".join(f"{100 * np.mean(good > t):.1f} %" for t in WARN_GRID)
        + " |",
        "",
        f"Chosen warn threshold **{warn:.2f}** (the smallest warning at most {100 * FALSE_ALARM_SHARE:g} % of them).",
    ]
    return lines, weight, warn
