"""Per-point error bound of a rigid pose: what the fit pins down, the lever arm from the view, the misfit."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.registration.confidence import NORMAL_NEIGHBORS, motion_jacobian, pca_normals
from liver_p2p_reg.registration.nearest import NearestIndex
from liver_p2p_reg.registration.refine import trimmed_icp

MAX_SOURCE = 3000  # preop points the fit's Hessian is built on (a stride sample: ~1 ms tree)
MAX_VIEW = 2000  # intraop points kept to measure each point's distance from the visible patch
MIN_PAIRS = 6
MAX_PAIRS = 600  # trimmed pairs the Hessian is built from (a stride sample: normals dominate the cost)
# The interior a pose-level bound is taken over: the preop surface sample pulled halfway to its centroid. Always this
# stand-in, never the fiducials a benchmark case carries: the product has none, and a bound calibrated or judged at
# the fiducials is not the bound the product computes (docs/results/error_bound_interior.md).
INTERIOR_SHRINK = 0.5
INTERIOR_POINTS = 300  # stride sample of the preop surface the interior stand-in is made of
# What a calibration records as the interior its pose quantiles were made over (files without it: the fiducials).
INTERIOR_STAND_IN = f"preop surface sample shrunk {INTERIOR_SHRINK:g} to its centroid"
# The features every bound is computed from, in this order. A calibration's coefficients follow a prefix of it: files
# made before log_halves hold the first seven (docs/benchmark_real/RULE_bound_halves.md).
FEATURES = (
    "const",
    "log_rigid",
    "log_lever",
    "log_residual",
    "log_visibility",
    "log_rival_gap",
    "log_rival_ratio",
    "log_halves",
)
HALVES = FEATURES.index("log_halves")  # made only for a calibration that uses it (PoseEvidence.half_T)
RIVAL_GAP_MM = 5.0  # a hypothesis whose pose differs by more than this on the organ is a rival, not the same pose
RIVAL_RATIO_CAP = 4.0  # no rival, or one fitting this much worse: as good as none
HALF_POINTS = 300  # view points each half-view refit uses (a stride sample)
HALF_MIN_POINTS = 12  # a half with fewer is left out
HALF_ITERATIONS = 5  # ICP iterations of each half-view refit
# Bumped on any change to how a feature is computed that the constants below do not name (a formula, a gate, the
# cut into halves): a collection made by another version is not reused.
EVIDENCE_VERSION = 1
# What the features are computed with: a collection of them made with other values is not reused (calibrate-bound).
EVIDENCE_SETTINGS = {
    "version": EVIDENCE_VERSION,
    "normal_neighbors": NORMAL_NEIGHBORS,
    "max_source": MAX_SOURCE,
    "max_view": MAX_VIEW,
    "min_pairs": MIN_PAIRS,
    "max_pairs": MAX_PAIRS,
    "interior_shrink": INTERIOR_SHRINK,
    "interior_points": INTERIOR_POINTS,
    "rival_gap_mm": RIVAL_GAP_MM,
    "rival_ratio_cap": RIVAL_RATIO_CAP,
    "half_points": HALF_POINTS,
    "half_min_points": HALF_MIN_POINTS,
    "half_iterations": HALF_ITERATIONS,
}


@dataclass(frozen=True)
class PoseEvidence:
    """What one registration knows about its own error, in the preop frame (mm, radians)."""

    T_target_source: np.ndarray  # (4, 4) the pose
    centre_mm: np.ndarray  # (3,) centre of the visible patch in the preop frame
    cov: np.ndarray  # (6, 6) pose covariance per unit misfit (rotation about centre_mm, translation)
    sigma_mm: float  # RMS point-to-plane misfit of the trimmed pairs
    view_mm: np.ndarray  # (M, 3) the intraop view moved into the preop frame (a stride sample)
    residual_mm: float
    visibility: float
    interior_mm: np.ndarray  # (K, 3) where the pose-level bound is taken: the shrunk preop surface (interior_stand_in)
    view_tree: NearestIndex | None = None  # over view_mm, built once
    # the best-fitting rival hypothesis (another basin): its pose and residual / the best residual
    rival_T: np.ndarray | None = None
    rival_ratio: float = RIVAL_RATIO_CAP
    # what the half-view refits are made from (half_T): the paired view points, the preop points they paired with and
    # those points' normals (mm, preop frame), and the fit's trim ratio; empty: too few pairs, no halves
    paired_mm: np.ndarray | None = None
    paired_surface_mm: np.ndarray | None = None
    paired_normals: np.ndarray | None = None
    trim_ratio: float = 1.0

    @functools.cached_property
    def half_T(self) -> tuple[np.ndarray, ...]:
        """The poses (preop frame, relative to the pose) of the view's halves refitted alone (half_view_refits).
        Made on first use (~4 ms): only a calibration that uses log_halves (or a collection for one) pays for them."""
        if self.paired_mm is None or self.paired_surface_mm is None or self.paired_normals is None:
            return ()
        return half_view_refits(
            self.view_mm, self.paired_mm, self.paired_surface_mm, self.paired_normals, self.trim_ratio
        )

    def rigid_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """RMS displacement of each point under the pose's misfit-driven covariance (mm); inf if unconstrained."""
        if not np.all(np.isfinite(self.cov)):
            return np.full(len(points_mm), np.inf)
        A = motion_jacobian(np.asarray(points_mm, float) - self.centre_mm)
        # E|dx|^2 = tr(A cov A^T)
        spread2 = np.sum((A @ self.cov) * A, axis=(1, 2))
        return self.sigma_mm * np.sqrt(np.maximum(spread2, 0.0))

    def lever_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """Distance of each point from the visible patch (mm): deformation the view cannot see grows with it."""
        tree = self.view_tree if self.view_tree is not None else NearestIndex(self.view_mm)
        dist, _ = tree.query(np.asarray(points_mm, float))
        return dist

    def features(self, points_mm: np.ndarray, count: int = len(FEATURES)) -> np.ndarray:
        """(N, count) features of each point, the first `count` of FEATURES (a calibration's: a later feature is not
        computed for one that does not use it); non-finite where the pose is unconstrained."""
        points_mm = np.asarray(points_mm, float).reshape(-1, 3)
        n = len(points_mm)
        out = np.empty((n, len(FEATURES)))
        out[:, 0] = 1.0
        with np.errstate(divide="ignore", invalid="ignore"):
            out[:, 1] = np.log1p(self.rigid_mm(points_mm))
            out[:, 2] = np.log1p(self.lever_mm(points_mm))
            out[:, 3] = np.log(max(self.residual_mm, 0.0) + 0.5)
            out[:, 4] = np.log(max(self.visibility, 1e-3)) if np.isfinite(self.visibility) else np.nan
            out[:, 5] = 0.0 if self.rival_T is None else np.log1p(self.rival_gap_mm(points_mm))
            out[:, 6] = np.log(min(max(self.rival_ratio, 1.0), RIVAL_RATIO_CAP))
            out[:, HALVES] = np.log1p(self.halves_mm(points_mm)) if count > HALVES else np.nan
        return out[:, :count]

    def halves_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """RMS over the half-view refits of how far each point moves from the pose (mm); 0 without halves."""
        points_mm = np.asarray(points_mm, float).reshape(-1, 3)
        if not self.half_T:
            return np.zeros(len(points_mm))
        moved2 = [np.sum((transform_points(T, points_mm) - points_mm) ** 2, axis=1) for T in self.half_T]
        return np.sqrt(np.mean(moved2, axis=0))

    def rival_gap_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """How far each point lies between the chosen pose and the rival's (mm): where a flip would move it."""
        if self.rival_T is None:
            return np.zeros(len(points_mm))
        return np.linalg.norm(
            transform_points(self.rival_T, points_mm) - transform_points(self.T_target_source, points_mm), axis=1
        )


def pose_evidence(
    T_target_source: np.ndarray,
    source_mm: np.ndarray,
    target_mm: np.ndarray,
    *,
    residual_mm: float,
    visibility: float,
    trim_ratio: float,
    hypotheses: Sequence[tuple[np.ndarray, float]] = (),
) -> PoseEvidence:
    """Linearize the trimmed point-to-plane fit at the final pose, in mm, on stride samples of both clouds.

    Method-independent (any pose of any method): the target moved into the preop frame is paired
    with its closest preop points; pairs farther than 3x the median pair distance are not
    overlap, and the worst (1 - trim_ratio) of the rest are trimmed, as ICP does. `hypotheses`
    (pose, residual mm) are the method's other candidates: the best-fitting one in another basin is the rival.
    """
    T = np.asarray(T_target_source, dtype=np.float64)
    source = np.asarray(source_mm, float)[:: max(1, len(source_mm) // MAX_SOURCE)]
    view = transform_points(np.linalg.inv(T), np.asarray(target_mm, float))
    view = view[:: max(1, len(view) // MAX_VIEW)]
    interior_mm = interior_stand_in(source)
    tree = NearestIndex(source)
    dist, idx = tree.query(view)
    centre = view.mean(axis=0)
    cov, sigma, halves = np.full((6, 6), np.inf), float("nan"), {}
    # finite only: a view moved beyond float range pairs nothing (its index would be the tree's size)
    keep = np.flatnonzero(np.isfinite(dist) & (dist <= 3.0 * max(float(np.median(dist)), 1e-6)))
    if len(keep) >= MIN_PAIRS:
        keep = keep[dist[keep] <= np.quantile(dist[keep], trim_ratio)]
    keep = keep[:: max(1, len(keep) // MAX_PAIRS)]
    if len(keep) >= MIN_PAIRS:
        p, s = view[keep], source[idx[keep]]
        at, back = np.unique(idx[keep], return_inverse=True)  # one normal per preop point paired
        normals = pca_normals(source, tree, at)
        n = normals[back]
        halves = {"paired_mm": p, "paired_surface_mm": source[at], "paired_normals": normals, "trim_ratio": trim_ratio}
        J = np.hstack([np.cross(p - centre, n), n])  # d(misfit)/d(omega, v) per pair
        sigma = float(np.sqrt(np.mean(np.einsum("ij,ij->i", p - s, n) ** 2)))
        try:
            inv = np.linalg.inv(J.T @ J / len(keep))
            if np.all(np.isfinite(inv)):
                cov = inv
        except np.linalg.LinAlgError:
            pass
    return PoseEvidence(
        T_target_source=T,
        centre_mm=centre,
        cov=cov,
        sigma_mm=sigma,
        view_mm=view,
        residual_mm=float(residual_mm),
        visibility=float(visibility),
        interior_mm=interior_mm,
        view_tree=NearestIndex(view),
        **halves,
        **_rival(T, hypotheses, interior_mm, residual_mm),
    )


def half_view_refits(
    view: np.ndarray, paired: np.ndarray, surface: np.ndarray, normals: np.ndarray, trim_ratio: float
) -> tuple[np.ndarray, ...]:
    """Each half of the view refitted alone onto the paired preop surface (mm, preop frame), from the pose: the
    view cut through its paired points' centroid across their two longest principal axes, four halves; each half's
    motion (4x4) from the pose. A rigid view's halves agree; a bent one's pull the pose their own ways, and the
    tilt they disagree by is what reaches the interior (docs/benchmark_real/RULE_bound_halves.md)."""
    centre = paired.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((paired - centre).T))
    index = (NearestIndex(surface), normals)  # the paired points and their normals: ~600, built once
    out = []
    for axis in (axes[:, 2], axes[:, 1]):
        side = (view - centre) @ axis
        for half in (view[side <= 0], view[side > 0]):
            half = half[:: max(1, len(half) // HALF_POINTS)]
            if len(half) < HALF_MIN_POINTS:
                continue
            # trimmed_icp moves the "target" (the half) onto the "source" (the surface); its T maps the surface onto
            # the half, so the half moves by the inverse. tol 0: always HALF_ITERATIONS (a fixed cost)
            T = trimmed_icp(
                np.eye(4),
                surface,
                half,
                max_iterations=HALF_ITERATIONS,
                max_corr=np.inf,
                trim_ratio=trim_ratio,
                tol=0.0,
                source_index=index,
            )
            out.append(np.linalg.inv(T))
    return tuple(out)


def interior_stand_in(source_mm: np.ndarray) -> np.ndarray:
    """Where the pose-level bound is taken (mm): a stride sample of the preop surface pulled halfway to its centroid."""
    source_mm = np.asarray(source_mm, float)
    centroid = source_mm.mean(axis=0)
    return centroid + INTERIOR_SHRINK * (source_mm[:: max(1, len(source_mm) // INTERIOR_POINTS)] - centroid)


def _rival(
    T: np.ndarray, hypotheses: Sequence[tuple[np.ndarray, float]], points: np.ndarray, residual_mm: float
) -> dict:
    """The best-fitting hypothesis whose pose moves the organ by more than RIVAL_GAP_MM (RMS) from T."""
    usable = [(np.asarray(H, float), float(r)) for H, r in hypotheses if np.isfinite(r) and np.all(np.isfinite(H))]
    if not usable:
        return {}
    best = min([residual_mm, *(r for _, r in usable)])
    moved = transform_points(T, points)
    rivals = [
        (r, H)
        for H, r in usable
        if np.sqrt(np.mean(np.sum((transform_points(H, points) - moved) ** 2, axis=1))) > RIVAL_GAP_MM
    ]
    if not rivals:
        return {}
    r, H = min(rivals, key=lambda item: item[0])
    return {"rival_T": H, "rival_ratio": r / max(best, 1e-6)}
