"""The non-rigid fit: elastic mode coefficients and a rigid correction that pull the preop surface onto the view.

Energy (preop frame, target moved there by the rigid pose):
    E(q, xi) = sum_i w_i (n_i . (x_j(q) - G_xi y_i))^2 / sum_i w_i  +  alpha * sum_k (lambda_k / lambda_1) q_k^2
x_j(q) = x_j + B_j q is the deformed preop point closest to target point y_i (pairs go from the partial view to
the complete model, so the unobserved side has no data term and is held only by the strain energy), n_j its
normal, G_xi a small rigid motion of the view, w_i a Geman-McClure weight of the residual (outliers and
mis-paired points fade out). Gauss-Newton on (q, xi) with the pairs recomputed each iteration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from liver_p2p_reg.registration.mechanics.modes import ElasticModel
from liver_p2p_reg.registration.refine import axis_angle_rotation

MAX_MODEL_POINTS, MAX_TARGET_POINTS = 6000, 2500  # the fit's even subsamples of the model and the view
MIN_SCALE_MM = 1.0  # the robust kernel's scale never drops below this (2 mm sensor noise is normal)


@dataclass
class FitOutcome:
    """What the non-rigid fit found (coefficients in mm of each mode's volume-RMS displacement)."""

    coefficients_mm: np.ndarray  # (m,)
    T_target_source: np.ndarray  # (4, 4) the rigid pose refined with the deformation
    iterations: int
    residual_before_mm: float  # robust mean closest-point distance at the rigid pose, no deformation
    residual_after_mm: float  # the same measure after the fit
    pairs: int  # target points used


def robust_residual_mm(points_mm: np.ndarray, view_mm: np.ndarray) -> float:
    """Mean distance of the view's points to their closest surface point, the worst 10 % left out."""
    d = np.sort(cKDTree(points_mm).query(view_mm)[0])
    return float(d[: max(int(0.9 * len(d)), 1)].mean())


def plane_residual_mm(points_mm: np.ndarray, normals: np.ndarray, view_mm: np.ndarray) -> float:
    """Mean point-to-plane distance of the view's points to their closest surface point, the worst 10 % left
    out: unlike the point-to-point distance it does not reward a fit for moving samples toward noisy points."""
    _, j = cKDTree(points_mm).query(view_mm)
    d = np.sort(np.abs(np.einsum("ij,ij->i", normals[j], points_mm[j] - view_mm)))
    return float(d[: max(int(0.9 * len(d)), 1)].mean())


def even_stride(n_points: int, max_points: int) -> int:
    """The step of an even subsample of at most `max_points` of `n_points` points (1: all of them)."""
    return max(int(np.ceil(n_points / max_points)), 1)


def fit_deformation(
    model: ElasticModel,
    target_mm: np.ndarray,
    T_init: np.ndarray,
    *,
    regularization: float,
    iterations: int,
    max_model_points: int = MAX_MODEL_POINTS,
    max_target_points: int = MAX_TARGET_POINTS,
    deform: bool = True,
) -> FitOutcome:
    """Minimize the energy above from the rigid pose `T_init` (source -> target, mm); `deform=False` holds the
    modes at zero (the rigid correction alone, the held-out check's baseline)."""
    stride = even_stride(len(model.source_mm), max_model_points)
    x0 = model.source_mm[::stride]
    normals = model.source_normals[::stride]
    basis = model.source_basis(stride)  # (P, 3, m), kept with the model
    target = np.asarray(target_mm, dtype=np.float64)
    target = target[:: even_stride(len(target), max_target_points)]
    T = np.asarray(T_init, dtype=np.float64).copy()
    m = model.n_modes
    q = np.zeros(m)
    prior = regularization * np.concatenate([model.stiffness_ratio, np.zeros(6)])
    view = (target - T[:3, 3]) @ T[:3, :3]  # the view in the preop frame
    before = robust_residual_mm(x0, view)
    tree = None
    done = 0
    while done < iterations:
        done += 1
        view = (target - T[:3, 3]) @ T[:3, :3]
        if tree is None or deform:  # held at zero, the modes leave the surface (and its tree) where it is
            x = x0 + basis @ q
            tree = cKDTree(x)
        dist, j = tree.query(view)
        n = normals[j]
        r = np.einsum("ij,ij->i", n, x[j] - view)
        scale = max(1.4826 * float(np.median(np.abs(r))), MIN_SCALE_MM)
        w = 1.0 / (1.0 + (r / scale) ** 2) ** 2
        w *= dist < max(5.0 * float(np.median(dist)), 5.0)  # far pairs are not the same surface
        centre = view.mean(axis=0)
        J = np.empty((len(view), m + 6))
        J[:, :m] = np.einsum("id,idm->im", n, basis[j])
        J[:, m : m + 3] = -np.cross(view - centre, n)  # d r / d omega of the view's rotation about its centre
        J[:, m + 3 :] = -n
        sw = float(w.sum()) + 1e-12
        A = (J * w[:, None]).T @ J / sw + np.diag(prior) + 1e-9 * np.eye(m + 6)
        g = (J * w[:, None]).T @ r / sw + prior * np.concatenate([q, np.zeros(6)])
        step = np.zeros(m + 6)
        free = slice(0 if deform else m, m + 6)
        step[free] = -np.linalg.solve(A[free, free], g[free])
        q = q + step[:m]
        # The view moves by G (rotation about its centre, then translation); the pose becomes T G^-1.
        Rg = axis_angle_rotation(step[m : m + 3])
        G = np.eye(4)
        G[:3, :3] = Rg
        G[:3, 3] = centre - Rg @ centre + step[m + 3 :]
        T = T @ np.linalg.inv(G)
        if np.max(np.abs(step[:m])) < 0.01 and np.linalg.norm(step[m:]) < 1e-4:
            break
    view = (target - T[:3, 3]) @ T[:3, :3]
    after = robust_residual_mm(x0 + basis @ q, view)
    return FitOutcome(
        coefficients_mm=q,
        T_target_source=T,
        iterations=done,
        residual_before_mm=before,
        residual_after_mm=after,
        pairs=len(target),
    )


def holdout_gain(
    model: ElasticModel,
    target_mm: np.ndarray,
    T_init: np.ndarray,
    *,
    regularization: float,
    iterations: int,
) -> float:
    """Does the deformation predict view points it was not fitted to? The view is split in two halves by the
    plane through its centroid normal to its longest axis; on each half, the stage and the rigid correction
    alone are fitted to the other half and scored by the held-out half's robust point-to-plane residual.
    Returns the mean over the halves of 1 - deformed / rigid held-out residual (> 0: the deformation
    extrapolates to new data)."""
    target = np.asarray(target_mm, dtype=np.float64)
    target = target[:: even_stride(len(target), MAX_TARGET_POINTS)]  # as the fit decimates it
    T = np.asarray(T_init, dtype=np.float64)
    view = (target - T[:3, 3]) @ T[:3, :3]
    centred = view - view.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    side = centred @ axis <= np.median(centred @ axis)
    stride = even_stride(len(model.source_mm), MAX_MODEL_POINTS)
    x0, normals, basis = model.source_mm[::stride], model.source_normals[::stride], model.source_basis(stride)
    gains = []
    for held in (side, ~side):
        scores = []
        for deform in (True, False):
            fit = fit_deformation(
                model, target[~held], T, regularization=regularization, iterations=iterations, deform=deform
            )
            Tf = fit.T_target_source
            moved = x0 + basis @ fit.coefficients_mm if deform else x0  # the rigid fit moves no mode
            held_view = (target[held] - Tf[:3, 3]) @ Tf[:3, :3]
            scores.append(plane_residual_mm(moved, normals, held_view))
        gains.append(1.0 - scores[0] / scores[1] if scores[1] > 0 else 0.0)
    return float(np.mean(gains))
