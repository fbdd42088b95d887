"""A PNG to check a registration by eye: the moved preop surface over the intraop view."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.plotting import pyplot
from liver_p2p_reg.result import RegistrationResult

# Target points farther than this from the moved source are drawn in the colour map's last colour.
DISTANCE_CLIP_MM = 10.0
HISTOGRAM_MAX_MM = 3 * DISTANCE_CLIP_MM  # farther points are counted in one labelled overflow bar
HISTOGRAM_BINS = 60
# What a method name in the headline means when it is not one of the benchmark's methods.
METHOD_NOTES = {"track": "track = ICP refinement of the previous pose, no global search"}
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
    (e.g. the bag's name and frame) leads the headline.
    """
    fig = draw_registration(
        source_mm,
        target_mm,
        result,
        warnings=warnings,
        residual_warn_mm=residual_warn_mm,
        source_fiducials_mm=source_fiducials_mm,
        target_fiducials_mm=target_fiducials_mm,
        title=title,
    )
    path = Path(path)
    fig.savefig(path, dpi=110)
    pyplot().close(fig)
    return path


def draw_registration(
    source_mm: np.ndarray,
    target_mm: np.ndarray,
    result: RegistrationResult,
    *,
    warnings: list[str] | None = None,
    residual_warn_mm: float | None = None,
    source_fiducials_mm: np.ndarray | None = None,
    target_fiducials_mm: np.ndarray | None = None,
    title: str | None = None,
):
    """The figure `plot_registration` saves (matplotlib Figure)."""
    plt = pyplot()
    T = np.asarray(result.T_target_source, dtype=np.float64)
    moved = transform_points(T, np.asarray(source_mm, dtype=np.float64))
    target = np.asarray(target_mm, dtype=np.float64)
    dist_mm, _ = cKDTree(moved).query(target, k=1)
    status = "WARN: " + "; ".join(warnings) if warnings else "OK"
    fig, axes = plt.subplots(1, 4, figsize=(19, 5), gridspec_kw={"width_ratios": [1, 1, 1, 1]})
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
    _distance_histogram(axes[3], dist_mm, result.residual_mm, residual_warn_mm)
    headline = f"{title}: " if title else ""
    headline += f"{result.method}: residual {result.residual_mm:.2f} mm, uncertainty {result.uncertainty_mm:.1f} mm"
    if result.rms_tre_mm is not None:
        headline += f", RMS-TRE {result.rms_tre_mm:.2f} mm"
    if result.method in METHOD_NOTES:
        headline += f" ({METHOD_NOTES[result.method]})"
    fig.suptitle(f"{headline}\n{status}", color="firebrick" if warnings else "darkgreen")
    fig.tight_layout()
    return fig


def _distance_histogram(ax, dist_mm: np.ndarray, residual_mm: float, residual_warn_mm: float | None) -> None:
    """Histogram of the drawn distances, their mean, and the result's residual, each labelled with
    what it measures: the residual (the node's OK/WARN measure) is taken on the voxelized clouds
    after outlier removal, so it is larger than the mean of these dense distances."""
    width = HISTOGRAM_MAX_MM / HISTOGRAM_BINS
    inside = dist_mm[dist_mm < HISTOGRAM_MAX_MM]
    ax.hist(inside, bins=HISTOGRAM_BINS, range=(0.0, HISTOGRAM_MAX_MM), color="tab:blue", label="all intraop points")
    beyond = int(len(dist_mm) - len(inside))
    if beyond:
        ax.bar(
            HISTOGRAM_MAX_MM + width / 2,
            beyond,
            width=width,
            color="tab:orange",
            label=f"\u2265 {HISTOGRAM_MAX_MM:g} mm: {beyond} points",
        )
    ax.axvline(
        float(np.mean(dist_mm)), color="tab:blue", linestyle="-", label=f"mean of these: {np.mean(dist_mm):.2f} mm"
    )
    ax.axvline(
        residual_mm,
        color="black",
        linestyle="--",
        label=f"residual_mm {residual_mm:.2f} (voxelized, outliers removed)",
    )
    if residual_warn_mm is not None:
        ax.axvline(residual_warn_mm, color="red", linestyle=":", label=f"residual_warn_mm {residual_warn_mm:g}")
    ax.set_xlabel("intraop point -> moved preop (mm), all points")
    ax.set_ylabel("points")
    ax.legend(fontsize=7, loc="upper right")
