"""The non-rigid stage after the rigid pose: build (once) and fit the preop liver's elastic model, or say why not.

It never makes a result worse silently: when the view cannot support a deformation (too few points, a gross
rigid pose, no closed preop solid, a fit that does not lower the residual, an implausible displacement) the
deformation is not applied, the rigid pose stands, and `reason` says why in one line.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.context import remember_latest

if TYPE_CHECKING:
    from liver_p2p_reg.config import Config
    from liver_p2p_reg.registration.deform_fit import FitOutcome
    from liver_p2p_reg.registration.mechanics.modes import ElasticModel
    from liver_p2p_reg.result import RegistrationResult


@dataclass
class Deformation:
    """The non-rigid stage's outcome: the refined pose and the displacement of any preop point."""

    applied: bool
    reason: str  # "" when applied, else why the rigid result stands (one line)
    T_target_source: np.ndarray  # (4, 4) the rigid pose refined with the deformation (the rigid pose if not applied)
    coefficients_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rms_displacement_mm: float = 0.0  # over the model's mesh nodes (the volume)
    max_displacement_mm: float = 0.0
    strain_energy_mj: float = 0.0  # at modes.YOUNGS_MODULUS_KPA
    iterations: int = 0
    residual_before_mm: float = float("nan")  # robust mean closest-point distance at the rigid pose
    residual_after_mm: float = float("nan")
    holdout_gain: float = float("nan")  # the held-out-half check's gain (nan: not run)
    runtime_ms: float = 0.0  # the fit (the model's build is `model_build_ms`, once per preop model)
    model_build_ms: float = 0.0
    n_modes: int = 0
    n_nodes: int = 0
    model: ElasticModel | None = field(default=None, repr=False)

    def displacement_at(self, points_mm: np.ndarray) -> np.ndarray:
        """Displacement (P, 3) of preop points in the preop frame (zero when not applied)."""
        points_mm = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        if not self.applied or self.model is None:
            return np.zeros_like(points_mm)
        return self.model.displacement_at(points_mm, self.coefficients_mm)

    def deformed_position_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """Where preop points are now, in the target (sensor) frame: T (p + u(p))."""
        p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3) + self.displacement_at(points_mm)
        return p @ self.T_target_source[:3, :3].T + self.T_target_source[:3, 3]

    def to_json_dict(self) -> dict[str, Any]:
        """The `deformation` block of the result JSON."""

        def num(x: float) -> float | None:
            return round(float(x), 4) if np.isfinite(x) else None

        return {
            "applied": bool(self.applied),
            "reason": self.reason,
            "transform": np.asarray(self.T_target_source).tolist(),
            "rms_displacement_mm": num(self.rms_displacement_mm),
            "max_displacement_mm": num(self.max_displacement_mm),
            "strain_energy_mj": num(self.strain_energy_mj),
            "iterations": int(self.iterations),
            "residual_before_mm": num(self.residual_before_mm),
            "residual_after_mm": num(self.residual_after_mm),
            "holdout_gain": num(self.holdout_gain),
            "runtime_ms": num(self.runtime_ms),
            "model_build_ms": num(self.model_build_ms),
            "n_modes": int(self.n_modes),
            "n_nodes": int(self.n_nodes),
        }


def elastic_model(
    cache: dict[str, Any],
    source_mm: np.ndarray,
    triangles: np.ndarray | None,
    config: Config,
    fit_points_mm: np.ndarray | None = None,
) -> ElasticModel:
    """The preop model's elastic model, built once per (source, triangles, settings) and kept in the cache;
    with `fit_points_mm` (the registered cloud beside a mesh), the same model fitted through those points."""
    from liver_p2p_reg.registration.features.fpfh import outward_normals
    from liver_p2p_reg.registration.mechanics.modes import build_elastic_model

    def normals_of(points: np.ndarray) -> np.ndarray:
        extent = float(np.max(np.ptp(points, axis=0)))
        return outward_normals(points / extent, 0.05)  # the radius is relative to the extent

    tris = None if triangles is None else np.ascontiguousarray(triangles, dtype=np.int64)
    key_points = source_mm if tris is None else np.concatenate([source_mm.ravel(), tris.ravel().astype(np.float64)])
    params = (config.deform_modes, config.deform_target_tets, tris is not None)

    def build() -> ElasticModel | InputError:
        normals = normals_of(source_mm)
        try:
            return build_elastic_model(
                source_mm, normals, tris, n_modes=config.deform_modes, target_tets=config.deform_target_tets
            )
        except InputError as exc:  # kept: a model that cannot be built is not rebuilt (seconds) for every pose
            return exc

    model = remember_latest(cache, "elastic", key_points, params, build)
    if isinstance(model, InputError):
        raise InputError(str(model))
    if fit_points_mm is None or fit_points_mm is source_mm:
        return model
    # the fit's data term on the cloud the rigid pose was found on: denser than a decimated mesh's vertices
    fit = np.asarray(fit_points_mm, dtype=np.float64)
    # kept with the model it derives from: a rebuilt model never serves an old one's
    return remember_latest(model._surfaces, "surface", fit, (), lambda: model.on_surface(fit, normals_of(fit)))


def not_applied(T: np.ndarray, reason: str, **known: Any) -> Deformation:
    """The rigid result standing, with the reason."""
    return Deformation(applied=False, reason=reason, T_target_source=np.asarray(T, dtype=np.float64).copy(), **known)


def _model_for(
    residual_mm: float,
    target_mm: np.ndarray,
    source_mm: np.ndarray,
    triangles: np.ndarray | None,
    config: Config,
    cache: dict[str, Any],
    fit_points_mm: np.ndarray | None,
) -> ElasticModel | str:
    """The elastic model to fit from a rigid pose of this residual on this view, or why the stage does not fit."""
    cfg = config.deformation
    if len(target_mm) < cfg.deform_min_points:
        return f"too little overlap: {len(target_mm)} view points < deform_min_points"
    if not residual_mm <= cfg.deform_max_residual_mm:
        return f"rigid residual {residual_mm:.1f} mm > {cfg.deform_max_residual_mm:g} mm: a gross pose"
    try:
        return elastic_model(cache, source_mm, triangles, config, fit_points_mm)
    except InputError as exc:
        return f"no elastic model: {exc}"


def _fit(model: ElasticModel, target_mm: np.ndarray, T: np.ndarray, config: Config) -> FitOutcome:
    """The stage's fit from the rigid pose T with the configured regularization and iterations."""
    from liver_p2p_reg.registration.deform_fit import fit_deformation

    cfg = config.deformation
    return fit_deformation(
        model, target_mm, T, regularization=cfg.deform_regularization, iterations=cfg.deform_iterations
    )


def fitted_residual_mm(
    T_mm: np.ndarray,
    residual_mm: float,
    source_mm: np.ndarray,
    target_mm: np.ndarray,
    config: Config,
    cache: dict[str, Any],
    triangles: np.ndarray | None = None,
    fit_points_mm: np.ndarray | None = None,
) -> float | None:
    """The stage's residual after its fit from the rigid pose `T_mm` (of ICP residual `residual_mm`): what the view
    leaves unexplained by a plausible deformation. None where the stage would not fit (`deform_result`'s checks
    before its fit; those after it and the held-out check do not run)."""
    model = _model_for(residual_mm, target_mm, source_mm, triangles, config, cache, fit_points_mm)
    if isinstance(model, str):
        return None
    fit = _fit(model, target_mm, np.asarray(T_mm, dtype=np.float64), config)
    return float(fit.residual_after_mm) if np.isfinite(fit.residual_after_mm) else None


def deform_result(
    result: RegistrationResult,
    source_mm: np.ndarray,
    target_mm: np.ndarray,
    config: Config,
    cache: dict[str, Any],
    triangles: np.ndarray | None = None,
    fit_points_mm: np.ndarray | None = None,
) -> Deformation:
    """Run the non-rigid stage from `result`'s rigid pose (never raises for data it cannot use); the model is
    built on `source_mm` (+ `triangles`) and fitted through `fit_points_mm` when given (else `source_mm`)."""
    from liver_p2p_reg.registration.deform_fit import holdout_gain

    T = np.asarray(result.T_target_source, dtype=np.float64)
    cfg = config.deformation
    if not result.ok:
        return not_applied(T, f"the rigid registration failed ({result.message or 'no pose'})")
    model = _model_for(result.residual_mm, target_mm, source_mm, triangles, config, cache, fit_points_mm)
    if isinstance(model, str):
        return not_applied(T, model)
    known = dict(model_build_ms=model.build_ms, n_modes=model.n_modes, n_nodes=len(model.mesh.nodes_mm), model=model)
    start = time.perf_counter()
    fit = _fit(model, target_mm, T, config)
    disp = model.nodal_displacement_mm(fit.coefficients_mm)
    norms = np.linalg.norm(disp, axis=1)
    stats = dict(
        coefficients_mm=fit.coefficients_mm,
        rms_displacement_mm=float(np.sqrt(np.mean(norms**2))),
        max_displacement_mm=float(norms.max()),
        strain_energy_mj=float(model.energy_mj_per_mm2 * np.sum(model.stiffness_ratio * fit.coefficients_mm**2)),
        iterations=fit.iterations,
        residual_before_mm=fit.residual_before_mm,
        residual_after_mm=fit.residual_after_mm,
        runtime_ms=(time.perf_counter() - start) * 1e3,
        **known,
    )
    before, after = fit.residual_before_mm, fit.residual_after_mm
    if not np.all(np.isfinite(fit.T_target_source)) or not np.all(np.isfinite(fit.coefficients_mm)):
        return not_applied(T, "the fit diverged (non-finite values)", **stats)
    if stats["max_displacement_mm"] > cfg.deform_max_displacement_mm:
        return not_applied(
            T,
            f"implausible deformation: {stats['max_displacement_mm']:.1f} mm > {cfg.deform_max_displacement_mm:g} mm",
            **stats,
        )
    if not after <= (1.0 - cfg.deform_min_gain) * before:
        return not_applied(T, f"the residual did not improve enough ({before:.2f} -> {after:.2f} mm)", **stats)
    if cfg.deform_holdout_check:
        # a deformation that fits the view may still extrapolate wrongly into the organ: ask it to predict
        stats["holdout_gain"] = holdout_gain(
            model, target_mm, T, regularization=cfg.deform_regularization, iterations=cfg.deform_iterations
        )
        stats["runtime_ms"] = (time.perf_counter() - start) * 1e3
        if not stats["holdout_gain"] >= cfg.deform_min_holdout_gain:
            return not_applied(
                T,
                f"the deformation does not predict the view's held-out half (gain {stats['holdout_gain']:.3f} "
                f"< {cfg.deform_min_holdout_gain:g})",
                **stats,
            )
    return Deformation(applied=True, reason="", T_target_source=fit.T_target_source, **stats)
