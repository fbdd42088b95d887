"""Markdown cells and tables of the benchmark reports: numbers, mean ± std, percentages, pipe tables."""

from __future__ import annotations

import math

import numpy as np

from liver_p2p_reg.bench.stats import mean_std

DASH = "–"


def fmt(value: float, digits: int = 2) -> str:
    """A number with `digits` decimals, or a dash for none or a non-finite one."""
    return DASH if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def pm(values: np.ndarray) -> str:
    """`mean ± std` of the values (population std), or a dash for none."""
    mean, std = mean_std(values)
    return DASH if not math.isfinite(mean) else f"{mean:.2f} ± {std:.2f}"


def pct(value: float) -> str:
    """A share as a percentage with one decimal, or a dash for nan."""
    return DASH if not math.isfinite(value) else f"{100 * value:.1f} %"


def md_table(header: list[str], rows: list[list[str]]) -> list[str]:
    """The lines of a Markdown pipe table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines
