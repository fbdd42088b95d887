"""Small views' close contenders judged after the full ICP by what a plausible deformation leaves unexplained.

Why (docs/benchmark_real/RULE_deformed_screening.md): on a small patch of a deformed organ, the true pose's rigid
residual is inflated by the deformation, while a wrong pose may sit on a region that happens to fit rigidly; the
screening's residual then picks the wrong one. Fitting the elastic stage from each contender and comparing what is
left judges the poses on what the deformation does not explain (validation: 14.98 -> 14.04 mm pooled at [0.05, 0.2)).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from liver_p2p_reg.config import Config
from liver_p2p_reg.registration.freespace import Scorer, penalized
from liver_p2p_reg.registration.preprocess import PreprocessedPair, denormalize_transform, residual_norm
from liver_p2p_reg.registration.refine import refine_poses

# (poses mm, their full-ICP residuals mm) -> each pose's key (mm, lowest wins)
KeysOf = Callable[[list[np.ndarray], list[float]], list[float]]
SAME_POSE_MM = 0.5  # refined poses this close (RMS at the preop points) share one stage fit: it would give the same
PROBE_POINTS = 2000  # preop points two refined poses are compared at


def judge_contenders(
    tried: list[tuple[int, np.ndarray, float, float]],
    chosen: int,
    T_norm: np.ndarray,
    poses_norm: list[np.ndarray],
    prep: PreprocessedPair,
    config: Config,
    cache: dict[str, Any],
    keys_of: KeysOf,
    scorer: Scorer | None = None,
) -> tuple[int, np.ndarray, dict[int, float]]:
    """The winner among the screening's contenders: those of `tried` (index, pose, short residual, violation) whose
    screening key (the short residual, made worse by its free-space violation when the sensor origin is known) is
    within `contender_judge_ratio` x the lowest, the screening's `chosen` (already refined to `T_norm`) always one.
    Each other contender is refined by the full ICP from its own pose, as the pipeline refines a winner; the keys
    are made worse by the refined poses' free-space violations alike (`scorer`; unchanged without an origin).
    Returns (winner index, its refined pose, each contender's key in mm); the first of equals wins.
    """
    weight = config.free_space_weight
    screening = {i: penalized(res, v, weight) for i, _, res, v in tried}
    lowest = min(screening.values())
    contenders = [i for i, *_ in tried if i == chosen or screening[i] <= config.contender_judge_ratio * lowest]
    if len(contenders) < 2:
        return chosen, T_norm, {}
    others = [i for i in contenders if i != chosen]
    refined = dict(zip(others, refine_poses([poses_norm[i] for i in others], prep, config, cache), strict=True))
    refined[chosen] = T_norm
    scale = prep.source_norm.scale_mm
    poses_mm = [denormalize_transform(refined[i], prep.source_norm, prep.target_norm) for i in contenders]
    keys = keys_of(poses_mm, [residual_norm(refined[i], prep) * scale for i in contenders])
    if scorer is not None and scorer.view is not None:
        violation = scorer([refined[i] for i in contenders])
        keys = [penalized(k, float(v), weight) for k, v in zip(keys, violation, strict=True)]
    best = int(np.argmin(keys))
    return contenders[best], refined[contenders[best]], dict(zip(contenders, keys, strict=True))


def elastic_keys(
    config: Config,
    cache: dict[str, Any],
    source_mm: np.ndarray,
    target_mm: np.ndarray,
    surface_mm: np.ndarray,
    triangles: np.ndarray | None,
    fit_points_mm: np.ndarray | None,
) -> KeysOf:
    """The judge's keys: each pose's residual after the elastic stage's fit from it (`deform.fitted_residual_mm`
    on the model of `surface_mm` + `triangles`), or its ICP residual where the stage does not fit."""
    from liver_p2p_reg.registration.deform import fitted_residual_mm

    probe = probe_points(source_mm)

    def keys(poses_mm: list[np.ndarray], residuals_mm: list[float]) -> list[float]:
        done: list[tuple[np.ndarray, float | None]] = []
        out = []
        for T, rigid in zip(poses_mm, residuals_mm, strict=True):
            moved = probe @ T[:3, :3].T + T[:3, 3]
            twin = next((k for k, (p, _) in enumerate(done) if rms_gap_mm(p, moved) < SAME_POSE_MM), None)
            if twin is None:
                fitted = fitted_residual_mm(T, rigid, surface_mm, target_mm, config, cache, triangles, fit_points_mm)
                done.append((moved, fitted))
                twin = len(done) - 1
            fitted = done[twin][1]
            out.append(rigid if fitted is None else fitted)
        return out

    return keys


def probe_points(source_mm: np.ndarray) -> np.ndarray:
    """The preop points (an even subsample of about PROBE_POINTS) at which two refined poses are compared."""
    return np.asarray(source_mm, dtype=np.float64)[:: max(len(source_mm) // PROBE_POINTS, 1)]


def rms_gap_mm(a_mm: np.ndarray, b_mm: np.ndarray) -> float:
    """RMS distance between two placements of the same points (mm)."""
    return float(np.sqrt(np.mean(np.sum((a_mm - b_mm) ** 2, axis=1))))
