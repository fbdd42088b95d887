"""The benchmark's non-rigid table: each `METHOD+deform` row against its own rigid pose, per visibility range."""

from __future__ import annotations

import math

import numpy as np

from liver_p2p_reg.bench.jobs import DEFORM_SUFFIX
from liver_p2p_reg.bench.markdown import fmt, md_table, pct
from liver_p2p_reg.bench.stats import SAFETY_TAU_MM, Row

# The ranges the non-rigid stage is judged in: where a laparoscope looks ([0.1, 0.2) as one), then each bin above.
RANGES = ((0.05, 0.1), (0.1, 0.2), *((lo / 10, (lo + 1) / 10) for lo in range(2, 9)), (0.9, 1.0001))
HARM_MM = 1.0  # a pose within SAFETY_TAU_MM made worse by more than this counts as harm


def _label(lo: float, hi: float) -> str:
    return f"[{lo:.2f},{min(hi, 1.0):.2f}{']' if hi > 1 else ')'}"


def deform_rows(rows: list[Row]) -> list[Row]:
    """The main `+deform` rows; those with benchmark-added noise when there are any (the judged condition)."""
    mine = [r for r in rows if str(r["method"]).endswith(DEFORM_SUFFIX) and not r.get("variant")]
    noisy = [r for r in mine if r.get("added_noise_mm", 0.0) > 0]
    return noisy or mine


def table_deform(rows: list[Row]) -> list[str] | None:
    """Mean interior TRE rigid -> deformed, its ratio, success@10 mm, harm and how often the stage was applied."""
    mine = deform_rows(rows)
    if not mine:
        return None
    header = [
        "method",
        "visibility",
        "poses",
        "rigid mean (mm)",
        "deformed mean (mm)",
        "deformed / rigid",
        f"success@{SAFETY_TAU_MM:g} rigid -> deformed",
        f"harm (> {HARM_MM:g} mm worse, rigid < {SAFETY_TAU_MM:g} mm)",
        "applied",
        "stage p50 (ms)",
    ]
    out = []
    for method in sorted({r["method"] for r in mine}):
        for lo, hi in RANGES:
            part = [r for r in mine if r["method"] == method and lo <= r["visibility"] < hi]
            rigid = np.array([r["rigid_rms_tre_mm"] for r in part], float)
            ok = np.isfinite(rigid)
            if not ok.any():
                continue
            deformed = np.array([r["rms_tre_mm"] for r in part], float)[ok]
            rigid = rigid[ok]
            applied = np.array([bool(r.get("deform_applied")) for r in part])[ok]
            ms = np.array([r.get("runtime_deform_ms", math.nan) for r in part], float)[ok]
            harm = int(np.sum((rigid < SAFETY_TAU_MM) & (deformed - rigid > HARM_MM)))
            out.append(
                [
                    method,
                    _label(lo, hi),
                    str(rigid.size),
                    fmt(float(rigid.mean()), 2),
                    fmt(float(deformed.mean()), 2),
                    fmt(float(deformed.mean() / rigid.mean()), 3),
                    f"{pct(float(np.mean(rigid < SAFETY_TAU_MM)))} -> {pct(float(np.mean(deformed < SAFETY_TAU_MM)))}",
                    f"{harm} of {int(np.sum(rigid < SAFETY_TAU_MM))}",
                    pct(float(applied.mean())),
                    fmt(float(np.nanmedian(ms)) if np.isfinite(ms).any() else math.nan, 0),
                ]
            )
    return md_table(header, out) if out else None
