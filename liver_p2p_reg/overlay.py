"""A PNG to check a registration by eye: the moved preop surface over the intraop view."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from .metrics import transform_points
from .plotting import pyplot
from .result import RegistrationResult

# Target points farther than this from the moved source are drawn in the colour map's last colour.
DISTANCE_CLIP_MM = 10.0
MAX_DRAWN_POINTS = 20_000  # per cloud: enough to see the shapes, quick to render
# (horizontal, vertical) sensor axes of each view: the camera's image plane first.
VIEWS = (((0, 1), "sensor x-y (camera view)"), ((0, 2), "sensor x-z"), ((1, 2), "sensor y-z"))


def _thin(points: np.ndarray, limit: int = MAX_DRAWN_POINTS) -> np.ndarray:
    """An even subsample (deterministic) of at most `limit` points."""
    return points if len(points) <= limit else points[:: int(np.ceil(len(points) / limit))]


def plot_registration(
    source_mm: np.ndarray,
    target_mm: np.ndarray,
    result: RegistrationResult,
    path: str | Path,
    *,
    warnings: list[str] | None = None,
    residual_warn_mm: float | None = None,
    source_fiducials_mm: np.ndarray | None = None,
    target_fiducials_mm: np.ndarray | None = None,
    title: str | None = None,
) -> Path:
    """Write three orthographic views of the moved source (grey) and the target (coloured by its
    distance to the moved source, mm) in the target's sensor frame, plus the distance histogram.

    Fiducials, when given, are drawn as pairs (moved source fiducial -> target fiducial); `title`
    (e.g. the bag's name) leads the headline.
    """
    plt = pyplot()
    T = np.asarray(result.T_target_source, dtype=np.float64)
    moved = transform_points(T, np.asarray(source_mm, dtype=np.float64))
    target = np.asarray(target_mm, dtype=np.float64)
    dist_mm, _ = cKDTree(moved).query(target, k=1)
    status = "WARN: " + "; ".join(warnings) if warnings else "OK"
    fig, axes = plt.subplots(1, 4, figsize=(19, 5), gridspec_kw={"width_ratios": [1, 1, 1, 0.8]})
    shown_src, shown_tgt, shown_d = _thin(moved), _thin(target), _thin(dist_mm)
    fid_pairs = None
    if source_fiducials_mm is not None and target_fiducials_mm is not None:
        fid_pairs = (
            transform_points(T, np.asarray(source_fiducials_mm, float)),
            np.asarray(target_fiducials_mm, float),
        )
    for ax, ((h, v), view_title) in zip(axes[:3], VIEWS, strict=True):
        ax.scatter(shown_src[:, h], shown_src[:, v], s=0.3, c="0.75", label="preop (moved)", rasterized=True)
        sc = ax.scatter(
            shown_tgt[:, h],
            shown_tgt[:, v],
            s=1.0,
            c=np.minimum(shown_d, DISTANCE_CLIP_MM),
            cmap="viridis",
            vmin=0.0,
            vmax=DISTANCE_CLIP_MM,
            label="intraop view",
            rasterized=True,
        )
        if fid_pairs is not None:
            moved_f, target_f = fid_pairs
            for a, b in zip(moved_f, target_f, strict=True):
                ax.plot([a[h], b[h]], [a[v], b[v]], color="red", linewidth=0.8)
            ax.scatter(target_f[:, h], target_f[:, v], s=6, marker="x", color="red", label="fiducial errors")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(view_title)
        ax.set_xlabel(f"{'xyz'[h]} (mm)")
        ax.set_ylabel(f"{'xyz'[v]} (mm)")
    axes[0].legend(loc="upper right", fontsize=7, markerscale=3)
    fig.colorbar(sc, ax=axes[2], label=f"distance to preop (mm, clipped at {DISTANCE_CLIP_MM:g})")
    hist = axes[3]
    hist.hist(np.minimum(dist_mm, 3 * DISTANCE_CLIP_MM), bins=60, color="tab:blue")
    hist.axvline(result.residual_mm, color="black", linestyle="--", label=f"residual {result.residual_mm:.2f} mm")
    if residual_warn_mm is not None:
        hist.axvline(residual_warn_mm, color="red", linestyle=":", label=f"residual_warn_mm {residual_warn_mm:g}")
    hist.set_xlabel("intraop point -> moved preop distance (mm)")
    hist.set_ylabel("points")
    hist.legend(fontsize=8)
    headline = f"{title}: " if title else ""
    headline += f"{result.method}: residual {result.residual_mm:.2f} mm, uncertainty {result.uncertainty_mm:.1f} mm"
    if result.rms_tre_mm is not None:
        headline += f", RMS-TRE {result.rms_tre_mm:.2f} mm"
    fig.suptitle(f"{headline}\n{status}", color="firebrick" if warnings else "darkgreen")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
