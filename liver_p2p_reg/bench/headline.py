"""The headline numbers with their uncertainty: bootstrap intervals over livers, and the worst fiducial of a pose.

Cases cut from one liver share its anatomy and its deformations, so they are not independent draws:
an interval from resampling cases would be too narrow. The intervals here resample whole livers with
replacement (percentile bootstrap, a fixed seed, so a summary regenerates identically).
"""

from __future__ import annotations

import math
import re
from typing import TYPE_CHECKING

import numpy as np

from liver_p2p_reg.bench.cases import BIN_LABELS
from liver_p2p_reg.bench.markdown import fmt, md_table, pm
from liver_p2p_reg.bench.stats import SAFETY_TAU_MM, Row, by_bin, in_bin, select, success, where

if TYPE_CHECKING:
    from liver_p2p_reg.bench.tables import Tables

N_RESAMPLES = 2000
LEVEL = 0.95
SEED = 0


def liver_of(case_id: str) -> str:
    """The liver a case was cut from (`case_L<id>_...`; noise copies and density twins share it); a case id
    without one is its own resampling unit."""
    m = re.search(r"_L(\d+)_", case_id)
    return m.group(1) if m else case_id


def bootstrap_mean(values: np.ndarray, livers: list[str]) -> tuple[float, float, float]:
    """(mean, low, high): the mean of `values` and its LEVEL percentile-bootstrap interval over livers.

    Resampling livers, the mean of a resample is its livers' summed values over their summed counts.
    With one liver there is nothing to resample: the interval is nan.
    """
    values = np.asarray(values, float)
    if values.size == 0:
        return math.nan, math.nan, math.nan
    keys, index = np.unique(np.asarray(livers), return_inverse=True)
    sums = np.bincount(index, weights=values, minlength=len(keys))
    counts = np.bincount(index, minlength=len(keys)).astype(float)
    mean = float(values.mean())
    if len(keys) < 2:
        return mean, math.nan, math.nan
    picks = np.random.default_rng(SEED).integers(len(keys), size=(N_RESAMPLES, len(keys)))
    resampled = sums[picks].sum(axis=1) / counts[picks].sum(axis=1)
    lo, hi = np.percentile(resampled, [50 * (1 - LEVEL), 50 * (1 + LEVEL)])
    return mean, float(lo), float(hi)


def _cell(values: np.ndarray, rows: list[Row], scale: float = 1.0, digits: int = 2) -> str:
    mean, lo, hi = bootstrap_mean(values, [liver_of(r["case_id"]) for r in rows])
    if not math.isfinite(mean):
        return fmt(mean)
    interval = f" [{fmt(scale * lo, digits)}, {fmt(scale * hi, digits)}]" if math.isfinite(lo) else ""
    return f"{fmt(scale * mean, digits)}{interval}"


def table_mean_interval(t: Tables) -> list[str]:
    """Mean RMS-TRE per bin with its 95 % bootstrap interval over livers."""
    header = ["method", *(BIN_LABELS[i] for i in t.bins), "all"]
    table = []
    for m in t.methods:
        mine = select(t.main, method=m)
        cells = [_cell(np.array([r["rms_tre_mm"] for r in rs], float), rs) for rs in _per_bin(mine, t.bins)]
        table.append([t.name(m), *cells, _cell(np.array([r["rms_tre_mm"] for r in mine], float), mine)])
    return md_table(header, table)


def table_success_interval(t: Tables, tau_mm: float = SAFETY_TAU_MM) -> list[str]:
    """Success rate (%) at tau per bin with its 95 % bootstrap interval over livers."""
    header = ["method", *(BIN_LABELS[i] for i in t.bins), "all"]
    table = []
    for m in t.methods:
        mine = select(t.main, method=m)
        cells = [_cell(success(rs, tau_mm).astype(float), rs, 100.0, 1) for rs in _per_bin(mine, t.bins)]
        table.append([t.name(m), *cells, _cell(success(mine, tau_mm).astype(float), mine, 100.0, 1)])
    return md_table(header, table)


def table_max_tre(t: Tables) -> list[str]:
    """The largest TRE over each pose's fiducials (its worst interior point), mean ± std per bin."""
    header = ["method", *(BIN_LABELS[i] for i in t.bins), "all"]
    table = []
    for m in t.methods:
        mine = select(t.main, method=m)
        groups = by_bin(mine, key="max_tre_mm")
        everything = np.array([r["max_tre_mm"] for r in mine], float)
        table.append([t.name(m), *(pm(groups[i]) for i in t.bins), pm(everything)])
    return md_table(header, table)


def headline_sections(t: Tables, heading: str = "## ") -> list[str]:
    """The three tables with their titles (`heading` "## " in summary.md, "" in a README block)."""

    def title(text: str) -> str:
        return f"{heading}{text}" if heading else f"{text}:"

    return [
        title("Mean RMS-TRE (mm) with its 95 % bootstrap interval over livers"),
        "",
        *table_mean_interval(t),
        "",
        title(f"Success rate at {SAFETY_TAU_MM:g} mm (%) with its 95 % bootstrap interval over livers"),
        "",
        *table_success_interval(t),
        "",
        title("Maximum TRE over a pose's fiducials (mm, its worst interior point), mean ± std"),
        "",
        *table_max_tre(t),
        "",
    ]


def _per_bin(rows: list[Row], bins: list[int]) -> list[list[Row]]:
    return [where(rows, in_bin(i)) for i in bins]
