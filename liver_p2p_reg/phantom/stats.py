"""Dataset statistics and Fig. 4-style histograms (deformation RMS, max deformation, initial RMS-TRE, visibility)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom.dataset import LOW_VISIBILITY_BINS, VISIBILITY_BINS
from liver_p2p_reg.plotting import pyplot

STAT_COLUMNS = (
    ("deformation_rms_mm", "deformation RMS (mm)"),
    ("deformation_max_mm", "max deformation (mm)"),
    ("initial_rms_tre_mm", "initial RMS-TRE (mm)"),
    ("visibility", "visibility M/N"),
)


def summarize(rows: Sequence[dict]) -> dict:
    """Per column: count, mean, std, min, percentiles, max; plus cases per visibility bin."""
    if not rows:
        raise InputError("the dataset lists no cases")
    out: dict = {"cases": len(rows), "livers": len({r["liver_id"] for r in rows})}
    for key, _ in STAT_COLUMNS:
        v = np.array([r[key] for r in rows], dtype=np.float64)
        out[key] = {
            "mean": float(v.mean()),
            "std": float(v.std()),
            "min": float(v.min()),
            "p50": float(np.percentile(v, 50)),
            "p95": float(np.percentile(v, 95)),
            "max": float(v.max()),
        }
    vis = np.array([r["visibility"] for r in rows])
    bins = {}
    for lo, hi in (*LOW_VISIBILITY_BINS, *VISIBILITY_BINS):
        upper = vis <= hi if hi >= 1.0 else vis < hi
        count = int(np.sum((vis >= lo) & upper))
        if count or lo >= 0.2:  # the bins below 0.2 only where a set has them (the v2 sets)
            digits = 2 if lo < 0.2 else 1
            bins[f"[{lo:.{digits}f},{hi:.{digits}f}{']' if hi >= 1.0 else ')'}"] = count
    out["visibility_bins"] = bins
    err = np.abs(np.array([r["visibility"] - r["visibility_requested"] for r in rows]))
    out["visibility_abs_error_max"] = float(err.max())
    return out


def plot_histograms(rows: Sequence[dict], path: str | Path, title: str = "") -> Path:
    """Write a 1x4 panel of histograms like the paper's Fig. 4."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.6), dpi=90)
    for ax, (key, label) in zip(axes, STAT_COLUMNS, strict=True):
        v = np.array([r[key] for r in rows], dtype=np.float64)
        ax.hist(v, bins=30, color="#b5523b", edgecolor="white")
        ax.set_xlabel(label)
        ax.set_ylabel("cases")
        ax.set_title(f"mean {v.mean():.2f}, max {v.max():.2f}", fontsize=9)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
