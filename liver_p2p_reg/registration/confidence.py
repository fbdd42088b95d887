"""Confidence of a final pose: how well the visible surface pins it down, and rival hypotheses."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from liver_p2p_reg.config import Config
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.registration.freespace import penalized
from liver_p2p_reg.registration.nearest import NearestIndex
from liver_p2p_reg.result import Candidate

MIN_PAIRS = 6  # fewer usable closest-point pairs than this: the pose is not constrained at all
NORMAL_NEIGHBORS = 10  # voxelized source points per normal (~ a 2-voxel radius)
SPREAD_POINTS = 300  # source points over which the pose error is averaged (the whole organ)


def pose_uncertainty(
    T_norm: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    *,
    max_corr: float,
    trim_ratio: float,
    source_index: NearestIndex | None = None,
) -> float:
    """Expected displacement of the organ's points under the fit's own misfit, normalized units.

    Linearizes the trimmed point-to-plane cost at the final pose (the pairs ICP would use) and
    propagates the RMS point-to-plane misfit sigma through it: sigma x GDOP, where GDOP is the
    RMS over the whole source of how far a point moves per unit of misfit. Small smooth views
    (a nearly flat or cylindrical patch) leave directions the surface does not constrain, so
    GDOP is large there even when the residual is small; a deformed view raises sigma. The
    misfit is treated as one error per pair, not as independent noise (which would shrink it
    by sqrt(pairs)): deformation errors are spatially correlated. Inf when nothing constrains.
    """
    # the voxelized source's index (the pipelines keep one per model); ~3000 points, built in about a millisecond
    tree = source_index if source_index is not None else NearestIndex(source)
    T = np.asarray(T_norm, dtype=np.float64)
    q = (target - T[:3, 3]) @ T[:3, :3]  # target in the source frame: R^T (y - t)
    dist, idx = tree.query(q)
    keep = dist < max_corr
    if keep.sum() < MIN_PAIRS:
        return float("inf")
    d_keep = dist[keep]
    sel = np.flatnonzero(keep)[d_keep <= np.quantile(d_keep, trim_ratio)]
    if len(sel) < MIN_PAIRS:
        return float("inf")
    p, s, n = q[sel], source[idx[sel]], pca_normals(source, tree, idx[sel])
    centre = p.mean(axis=0)  # rotations about the view's centre decouple from translations
    J = np.hstack([np.cross(p - centre, n), n])  # d(misfit)/d(omega, v) per pair
    sigma2 = float(np.mean(np.einsum("ij,ij->i", p - s, n) ** 2))
    H = J.T @ J / len(sel)
    try:
        cov = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return float("inf")
    if not np.all(np.isfinite(cov)):
        return float("inf")
    A = motion_jacobian(source[:: max(1, len(source) // SPREAD_POINTS)] - centre)
    spread2 = np.einsum("nij,jk,nik->n", A, cov, A)  # E|dx|^2 = tr(A cov A^T)
    gdop = float(np.sqrt(max(float(np.mean(spread2)), 0.0)))
    return float(np.sqrt(sigma2)) * gdop


def motion_jacobian(x: np.ndarray) -> np.ndarray:
    """(N, 3, 6): how points x (relative to the rotation centre) move per (omega, v): omega x x + v = A (omega, v)."""
    A = np.zeros((len(x), 3, 6))
    A[:, 0, 1], A[:, 0, 2], A[:, 1, 2] = x[:, 2], -x[:, 1], x[:, 0]
    A[:, 1, 0], A[:, 2, 0], A[:, 2, 1] = -x[:, 2], x[:, 1], -x[:, 0]
    A[:, :, 3:] = np.eye(3)
    return A


def pca_normals(points: np.ndarray, tree: NearestIndex, at: np.ndarray) -> np.ndarray:
    """Unit normals at points[at] (sign arbitrary: covariances are quadratic in them) by PCA of neighbours."""
    _, nb = tree.query_k(points[at], min(NORMAL_NEIGHBORS, len(points)))
    local = points[nb] - points[nb].mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))
    return vectors[:, :, 0]  # eigenvector of the smallest eigenvalue


def pose_gap_mm(T_a: np.ndarray, T_b: np.ndarray, source_mm: np.ndarray) -> float:
    """RMS distance between the source moved by two poses (mm): how different they are on the organ."""
    sample = source_mm[:: max(1, len(source_mm) // 500)]
    diff = transform_points(T_a, sample) - transform_points(T_b, sample)
    return float(np.sqrt(np.mean(np.sum(diff**2, axis=1))))


def is_ambiguous(
    hypotheses: Sequence[Candidate],
    source_mm: np.ndarray,
    residual_ratio: float,
    pose_mm: float,
    free_space_weight: float = 0.0,
) -> bool:
    """True when a rival hypothesis fits within `residual_ratio` of the best with a pose > `pose_mm` away.

    "Fits" is the residual made worse by the hypothesis' free-space violation when it is known
    (freespace.penalized): a rival the sensor's view rules out is no rival.
    """

    def score(c: Candidate) -> float:
        return penalized(c.residual_mm, c.free_space_violation, free_space_weight)

    ok = sorted((c for c in hypotheses if c.ok and np.isfinite(c.residual_mm)), key=score)
    if len(ok) < 2:
        return False
    best = ok[0]
    limit = residual_ratio * max(score(best), 1e-6)
    return any(
        pose_gap_mm(best.T_target_source, c.T_target_source, source_mm) > pose_mm for c in ok[1:] if score(c) <= limit
    )


def pose_warnings(
    residual_mm: float,
    ambiguous: bool,
    uncertainty_mm: float,
    config: Config,
    free_space_violation: float = float("nan"),
    error_bound_mm: float = float("nan"),
) -> dict[str, str]:
    """Why a registered pose should not be trusted as is (the node's WARN rules): reason -> message.

    Reasons: "residual", "ambiguous", "uncertainty", "free_space", "error_bound"; empty when the pose
    is OK. A NaN warns, except the free-space violation (NaN: the sensor origin is unknown) and the
    error bound (NaN: not computed for this pose; an unbounded pose is inf and warns).
    """
    out: dict[str, str] = {}
    if not residual_mm <= config.residual_warn_mm:
        out["residual"] = f"residual {residual_mm:.2f} mm above {config.residual_warn_mm} mm"
    if ambiguous:
        out["ambiguous"] = "ambiguous: two candidates fit nearly equally well with different poses"
    if not uncertainty_mm <= config.uncertainty_warn_mm:
        out["uncertainty"] = (
            f"pose poorly constrained by the visible surface: uncertainty {uncertainty_mm:.1f} mm "
            f"above {config.uncertainty_warn_mm} mm"
        )
    if free_space_violation > config.free_space_warn:
        out["free_space"] = (
            f"the pose puts preop surface where the sensor saw none: {free_space_violation:.0%} of the view "
            f"(above {config.free_space_warn:.0%})"
        )
    if error_bound_mm > config.structure_error_warn_mm:
        out["error_bound"] = (
            f"error bound at depth {error_bound_mm:.1f} mm ({config.error_coverage:.0%}) "
            f"above {config.structure_error_warn_mm} mm"
        )
    return out


def pose_bound_warnings(result: Any, config: Config, error_bound_mm: float | None = None) -> dict[str, str]:
    """`pose_warnings` of a RegistrationResult with its interior's error bound (or `error_bound_mm`): the verdict's
    reasons without structures and without the method's own notes (survey mode's gate)."""
    bound = getattr(result, "error_bound_mm", float("nan")) if error_bound_mm is None else error_bound_mm
    violation = getattr(result, "free_space_violation", float("nan"))
    return pose_warnings(result.residual_mm, result.ambiguous, result.uncertainty_mm, config, violation, bound)


def result_warnings(
    result: Any, config: Config, structure_bounds_mm: Mapping[str, np.ndarray] | None = None
) -> dict[str, str]:
    """`pose_warnings` of a RegistrationResult plus the warnings the method itself attached
    (e.g. prepared weights made for another liver): reason -> message.

    With structures (label -> per-point bounds, mm) the verdict follows their bounds: any point
    above `structure_error_warn_mm` warns, naming the structure; without, the interior's bound.
    """
    out = pose_bound_warnings(result, config, float("nan") if structure_bounds_mm else None)
    limit = config.structure_error_warn_mm
    wide = {label: float(np.max(b)) for label, b in (structure_bounds_mm or {}).items() if len(b)}
    wide = {label: b for label, b in wide.items() if not b <= limit}
    if wide:
        worst = max(wide, key=lambda label: wide[label])
        out["structures"] = (
            f"error bound at {', '.join(sorted(wide))} up to {wide[worst]:.1f} mm ({config.error_coverage:.0%}, "
            f"'{worst}') above {limit} mm"
        )
    out.update({f"method{i}": message for i, message in enumerate(getattr(result, "warnings", []))})
    return out


def origin_warnings(result: Any) -> list[str]:
    """`liver-p2p register`'s warning when its --sensor-origin cannot be the target's sensor (free space off): the
    command's JSON status and its flight recording's verdict both WARN for it."""
    if not result.free_space.startswith("off"):
        return []
    return [f"--sensor-origin ignored: {result.free_space.removeprefix('off: ')}"]
