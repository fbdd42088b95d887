"""The named registration methods: feature + P2P pipelines and the classical baselines."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial import cKDTree

from . import baselines
from .confidence import pose_uncertainty
from .config import Config
from .errors import InputError, RegistrationError
from .features.fpfh import FPFHProvider
from .freespace import Scorer, penalized
from .metrics import transform_points
from .preprocess import (
    Normalization,
    denormalize_transform,
    source_normalization,
    statistical_inliers,
    target_normalization,
    voxel_downsample,
)
from .refine import source_search_index, trimmed_icp
from .registrar import MethodContext, method, remember_latest
from .result import Candidate, RegistrationResult

if TYPE_CHECKING:  # torch and the P2P module are imported where used: the Open3D baselines need neither
    from .features.base import FeatureProvider
    from .p2p import P2PSettings


@dataclass
class Prepared:
    """Both clouds normalized (full and voxelized) plus the maps back to mm."""

    source_norm: Normalization
    target_norm: Normalization
    source_full: np.ndarray  # (N0, 3) normalized, not voxelized (refinement)
    target_full: np.ndarray
    source: np.ndarray  # (N, 3) voxelized
    target: np.ndarray  # (M, 3) voxelized
    source_tree: cKDTree  # of `source`, built once per model (residuals are measured against it)

    @property
    def visibility(self) -> float:
        return len(self.target) / len(self.source)


def prepare(
    source_mm: np.ndarray, target_mm: np.ndarray, config: Config, cache: dict[str, Any] | None = None
) -> Prepared:
    """The paper's preprocessing; refuses a target much larger than the source after voxelization
    (`max_target_ratio`: a noisy full view may voxelize a few percent larger; swapped files do not).

    With a cache, the source's share (normalization, voxelization) is computed once per model.
    """

    def source_part() -> tuple[Normalization, np.ndarray, np.ndarray, cKDTree]:
        norm = source_normalization(source_mm)
        full = norm.apply(source_mm)
        voxels = voxel_downsample(full, config.voxel_size_norm)
        return norm, full, voxels, cKDTree(voxels)

    if cache is None:
        ns, src_full, src, src_tree = source_part()
    else:
        ns, src_full, src, src_tree = remember_latest(
            cache, "prepared-source", source_mm, (config.voxel_size_norm,), source_part
        )
    if config.outlier_std_ratio > 0:
        target_mm = target_mm[statistical_inliers(target_mm, config.outlier_neighbors, config.outlier_std_ratio)]
    nt = target_normalization(target_mm, ns)
    tgt_full = nt.apply(target_mm)
    tgt = voxel_downsample(tgt_full, config.voxel_size_norm)
    if len(src) < 3 or len(tgt) < 3:
        raise InputError(f"too few points after voxelization (source {len(src)}, target {len(tgt)}); need >= 3 each")
    if len(tgt) > config.max_target_ratio * len(src):
        raise InputError(
            f"target ({len(tgt)} voxels) is more than {config.max_target_ratio:g}x the source ({len(src)} voxels): "
            "expected the complete preoperative surface as SOURCE and the partial view as TARGET"
        )
    return Prepared(ns, nt, src_full, tgt_full, src, tgt, src_tree)


def residual_norm(T_norm: np.ndarray, prep: Prepared) -> float:
    """Mean closest-point distance target -> transformed voxelized source (normalized units).

    Measured in the source frame (the target moved by the inverse; distances are the same), so
    the source's k-d tree is built once per model, not once per evaluated pose.
    """
    T_inv = np.linalg.inv(T_norm)
    dist, _ = prep.source_tree.query(transform_points(T_inv, prep.target), k=1)
    return float(dist.mean())


def _refine(
    T_norm: np.ndarray,
    prep: Prepared,
    config: Config,
    cache: dict[str, Any],
    *,
    max_points: int | None = None,
    max_iterations: int | None = None,
) -> np.ndarray:
    # The preoperative source is the same frame after frame: reuse its k-d tree and normals.
    index = remember_latest(
        cache,
        "icp-source-index",
        prep.source_full,
        (config.normal_radius_norm,),
        lambda: source_search_index(prep.source_full, config.normal_radius_norm),
    )
    return trimmed_icp(
        T_norm,
        prep.source_full,
        prep.target_full,
        max_iterations=max_iterations or config.icp_max_iterations,
        max_corr=config.icp_max_corr_norm,
        trim_ratio=config.icp_trim_ratio,
        max_target_points=max_points or config.icp_max_points,
        normal_radius=config.normal_radius_norm,
        source_index=index,
    )


def uncertainty_mm(T_norm: np.ndarray, prep: Prepared, config: Config, times: dict[str, float]) -> float:
    """`confidence.pose_uncertainty` of a final pose on the voxelized clouds (ICP's gate and trim), in mm.

    Records its time as the "confidence" stage in `times`.
    """
    t = time.perf_counter()
    value = pose_uncertainty(
        T_norm, prep.source, prep.target, max_corr=config.icp_max_corr_norm, trim_ratio=config.icp_trim_ratio
    )
    times["confidence"] = _lap(t)
    return value * prep.source_norm.scale_mm


def _screen_candidates(
    poses_norm: list[np.ndarray],
    order: list[int],
    prep: Prepared,
    config: Config,
    cache: dict[str, Any],
    scorer: Scorer | None = None,
) -> tuple[int, list[tuple[int, np.ndarray, float, float]]]:
    """Short ICP from each distinct candidate (best-ranked first); the lowest residual after it wins
    (with a known sensor origin: the lowest residual made worse by its free-space violation).

    Returns the winner's index and every screened (index, pose, residual, violation), normalized
    units; the full refinement then starts from the winner's own pose (not from the screened one),
    so that a winner P2P also chose gets exactly the unscreened result.
    """
    tried: list[np.ndarray] = []
    screened: list[tuple[int, np.ndarray, float]] = []
    for i in order:
        T = poses_norm[i]
        # near-duplicates (< ~5 deg and 0.05 normalized apart) would converge to the same pose
        if any(
            np.linalg.norm(T[:3, :3] - P[:3, :3]) < 0.1 and np.linalg.norm(T[:3, 3] - P[:3, 3]) < 0.05 for P in tried
        ):
            continue
        tried.append(T)
        T_s = _refine(
            T, prep, config, cache, max_points=config.screen_icp_points, max_iterations=config.screen_icp_iterations
        )
        screened.append((i, T_s, residual_norm(T_s, prep)))
        if len(tried) >= config.refine_candidates:
            break
    assert screened  # order holds at least the chosen candidate
    violation = scorer([T_s for _, T_s, _ in screened]) if scorer is not None else np.full(len(screened), np.nan)
    keys = [penalized(res, v, config.free_space_weight) for (_, _, res), v in zip(screened, violation, strict=True)]
    best = int(np.argmin(keys))  # the first of equals, as P2P's own choice
    return screened[best][0], [(i, T_s, res, float(v)) for (i, T_s, res), v in zip(screened, violation, strict=True)]


def free_space_scorer(prep: Prepared, config: Config, ctx: MethodContext) -> Scorer | None:
    """The free-space scorer of this registration's view; None without a known sensor origin."""
    if ctx.sensor_origin_mm is None:
        return None
    origin = prep.target_norm.apply(ctx.sensor_origin_mm[None])[0]
    band = config.free_space_band_mm / prep.source_norm.scale_mm
    return Scorer(prep.source, prep.target, origin, config.voxel_size_norm, band)


def _free_space_choice(out: Any, violation: np.ndarray, config: Config) -> int:
    """P2P's selection rule with each candidate's score made worse by its free-space violation."""
    ok = out.ok.cpu().numpy()
    if not ok.any():
        return out.chosen
    factor = 1.0 + config.free_space_weight * np.nan_to_num(violation, nan=0.0)
    if config.selection == "inlier-count":
        score = -out.inliers.cpu().numpy().astype(np.float64) / factor
    else:
        score = out.residual.double().cpu().numpy() * factor
    return int(np.argmin(np.where(ok, score, np.inf)))


def _final_free_space(scorer: Scorer | None, T_norm: np.ndarray, times: dict[str, float]) -> tuple[float, str]:
    """The final pose's violation and the scorer's status; records the scorer's time as the "free_space" stage."""
    if scorer is None:
        return float("nan"), ""
    violation = float(scorer([T_norm])[0])
    times["free_space"] = scorer.ms
    return violation, scorer.status


def p2p_settings(config: Config, use_p2p: bool) -> P2PSettings:
    """Map the Config onto the P2P module's settings."""
    from .p2p import P2PSettings, geometric_radii

    return P2PSettings(
        k=config.k,
        temperature=config.temperature,
        confidence_threshold=config.confidence_threshold,
        selection=config.selection,
        inlier_radius=config.inlier_radius_norm,
        candidate_proposal=config.candidate_proposal,
        use_p2p=use_p2p,
        mutual_only=config.mutual_only,
        max_patch_rows=config.max_patch_rows,
        consensus_seeds=config.consensus_seeds,
        consensus_sigma=config.consensus_sigma_norm,
        refit_radii=geometric_radii(
            config.refit_radius_start_norm, config.refit_radius_end_norm, config.refit_iterations
        ),
    )


def run_feature_pipeline(
    source_mm: np.ndarray,
    target_mm: np.ndarray,
    config: Config,
    ctx: MethodContext,
    provider: FeatureProvider | Callable[[], FeatureProvider],
    *,
    use_p2p: bool,
    refine: bool,
) -> RegistrationResult:
    """preprocess -> features -> dual-softmax matching [-> P2P] [-> refine] -> result in mm.

    `provider` may be a function making one: it is called after the inputs passed `prepare`, so
    a bad input (swapped clouds, too few points) is reported before torch or a model is loaded.
    """
    times: dict[str, float] = {}
    t = time.perf_counter()
    prep = prepare(source_mm, target_mm, config, ctx.cache)
    prepare_ms = _lap(t)
    import torch

    from .p2p import p2p_register

    if config.device == "cuda" and not torch.cuda.is_available():
        raise InputError("device 'cuda' requested but torch sees no CUDA device; use device: cpu")
    if callable(provider):  # first call in a process: the model's loading counts in "total" only
        provider = provider()
    t = time.perf_counter()
    device = torch.device(config.device)
    src = torch.as_tensor(prep.source, dtype=torch.float32, device=device)
    tgt = torch.as_tensor(prep.target, dtype=torch.float32, device=device)
    times["preprocess"] = prepare_ms + _lap(t)
    t = time.perf_counter()
    with torch.no_grad():
        x_src, x_tgt = provider.describe(src, tgt, ctx.cache)
        times["features"] = _lap(t)
        out = p2p_register(src, tgt, x_src, x_tgt, p2p_settings(config, use_p2p))
    times.update(out.runtime_ms)
    scale = prep.source_norm.scale_mm
    R, tr = out.R.double().cpu().numpy(), out.t.double().cpu().numpy()
    candidates, poses_norm = [], []
    for i, name in enumerate(out.names):
        T_norm = np.eye(4)
        T_norm[:3, :3], T_norm[:3, 3] = R[i], tr[i]
        poses_norm.append(T_norm)
        candidates.append(
            Candidate(
                name=name,
                T_target_source=denormalize_transform(T_norm, prep.source_norm, prep.target_norm),
                residual_mm=float(out.residual[i]) * scale,
                n_matches=int(out.n_matches[i]),
                ok=bool(out.ok[i]),
                inliers=int(out.inliers[i]),
            )
        )
    chosen = out.chosen
    scorer = free_space_scorer(prep, config, ctx)
    if scorer is not None and scorer.view is not None:
        violation = scorer(poses_norm)
        for candidate, v in zip(candidates, violation, strict=True):
            candidate.free_space_violation = float(v)
        chosen = _free_space_choice(out, violation, config)
    if not candidates[chosen].ok:
        raise RegistrationError(
            f"{provider.name}: no candidate had >= 3 non-degenerate matches (visibility {prep.visibility:.2f})"
        )
    T_norm = poses_norm[chosen]
    residual = float(out.residual[chosen])
    screened: list[Candidate] = []
    if refine and config.refine_candidates > 1:
        t = time.perf_counter()
        if scorer is None or scorer.view is None:
            others = sorted(
                (i for i, c in enumerate(candidates) if c.ok and i != chosen), key=lambda i: out.residual[i]
            )
        else:
            others = sorted(
                (i for i, c in enumerate(candidates) if c.ok and i != chosen),
                key=lambda i: penalized(
                    float(out.residual[i]), candidates[i].free_space_violation, config.free_space_weight
                ),
            )
        chosen, tried = _screen_candidates(poses_norm, [chosen, *others], prep, config, ctx.cache, scorer)
        screened = [
            Candidate(
                name=candidates[i].name,
                T_target_source=denormalize_transform(T_s, prep.source_norm, prep.target_norm),
                residual_mm=res * scale,
                n_matches=candidates[i].n_matches,
                inliers=candidates[i].inliers,
                free_space_violation=v,
            )
            for i, T_s, res, v in tried
        ]
        T_norm = poses_norm[chosen]
        times["screen"] = _lap(t)
    if refine:
        t = time.perf_counter()
        T_norm = _refine(T_norm, prep, config, ctx.cache)
        residual = residual_norm(T_norm, prep)
        times["refine"] = _lap(t)
    uncertainty = uncertainty_mm(T_norm, prep, config, times)
    violation_final, free_space = _final_free_space(scorer, T_norm, times)
    return RegistrationResult(
        T_target_source=denormalize_transform(T_norm, prep.source_norm, prep.target_norm),
        method=provider.name,
        residual_mm=residual * scale,
        runtime_ms=times,
        candidates=candidates,
        screened=screened,
        uncertainty_mm=uncertainty,
        free_space_violation=violation_final,
        free_space=free_space,
        chosen=chosen,
        n_matches=candidates[chosen].n_matches,
        visibility=prep.visibility,
        n_source=len(prep.source),
        n_target=len(prep.target),
    )


def run_global_pipeline(
    source_mm: np.ndarray,
    target_mm: np.ndarray,
    config: Config,
    ctx: MethodContext,
    estimate: Callable[[np.ndarray, np.ndarray, Config, dict[str, Any]], np.ndarray],
    *,
    refine: bool,
) -> RegistrationResult:
    """preprocess -> one global estimate (RANSAC, FGR, ICP) [-> refine] -> result in mm."""
    times: dict[str, float] = {}
    t = time.perf_counter()
    prep = prepare(source_mm, target_mm, config, ctx.cache)
    times["preprocess"] = _lap(t)
    t = time.perf_counter()
    T_norm = np.asarray(estimate(prep.source, prep.target, config, ctx.cache), dtype=np.float64)
    times["estimate"] = _lap(t)
    if not np.isfinite(T_norm).all():
        raise RegistrationError("the estimator returned a non-finite transform")
    if refine:
        t = time.perf_counter()
        T_norm = _refine(T_norm, prep, config, ctx.cache)
        times["refine"] = _lap(t)
    return _single_result(T_norm, prep, times, "estimate", config, ctx)


def _single_result(
    T_norm: np.ndarray, prep: Prepared, times: dict[str, float], name: str, config: Config, ctx: MethodContext
) -> RegistrationResult:
    """The result of a one-hypothesis method (no P2P candidates) from its normalized transform."""
    uncertainty = uncertainty_mm(T_norm, prep, config, times)
    residual = residual_norm(T_norm, prep) * prep.source_norm.scale_mm
    T_mm = denormalize_transform(T_norm, prep.source_norm, prep.target_norm)
    violation, free_space = _final_free_space(free_space_scorer(prep, config, ctx), T_norm, times)
    return RegistrationResult(
        T_target_source=T_mm,
        method="",
        residual_mm=residual,
        runtime_ms=times,
        candidates=[Candidate(name, T_mm, residual, 0, free_space_violation=violation)],
        chosen=0,
        uncertainty_mm=uncertainty,
        free_space_violation=violation,
        free_space=free_space,
        visibility=prep.visibility,
        n_source=len(prep.source),
        n_target=len(prep.target),
    )


def _lap(start: float) -> float:
    return (time.perf_counter() - start) * 1e3


def _fpfh(config: Config) -> FPFHProvider:
    return FPFHProvider(config.normal_radius_norm, config.fpfh_radius_norm)


@method("fpfh")
def fpfh_c2p(source_mm, target_mm, config: Config, ctx: MethodContext) -> RegistrationResult:
    """FPFH features, complete-to-partial dual-softmax matching only."""
    return run_feature_pipeline(source_mm, target_mm, config, ctx, _fpfh(config), use_p2p=False, refine=False)


@method("fpfh-p2p")
def fpfh_p2p(source_mm, target_mm, config: Config, ctx: MethodContext) -> RegistrationResult:
    """FPFH features + the P2P module."""
    return run_feature_pipeline(source_mm, target_mm, config, ctx, _fpfh(config), use_p2p=True, refine=False)


@method("fpfh-p2p-icp")
def fpfh_p2p_icp(source_mm, target_mm, config: Config, ctx: MethodContext) -> RegistrationResult:
    """FPFH + P2P, then trimmed point-to-plane ICP."""
    return run_feature_pipeline(source_mm, target_mm, config, ctx, _fpfh(config), use_p2p=True, refine=True)


@method("fpfh-ransac")
def fpfh_ransac(source_mm, target_mm, config: Config, ctx: MethodContext) -> RegistrationResult:
    """Open3D FPFH + RANSAC (max correspondence distance 0.05 normalized)."""
    return run_global_pipeline(source_mm, target_mm, config, ctx, baselines.fpfh_ransac, refine=False)


@method("fpfh-ransac-icp")
def fpfh_ransac_icp(source_mm, target_mm, config: Config, ctx: MethodContext) -> RegistrationResult:
    """FPFH + RANSAC, then trimmed point-to-plane ICP."""
    return run_global_pipeline(source_mm, target_mm, config, ctx, baselines.fpfh_ransac, refine=True)


@method("fgr")
def fgr(source_mm, target_mm, config: Config, ctx: MethodContext) -> RegistrationResult:
    """Open3D Fast Global Registration on FPFH matches."""
    return run_global_pipeline(source_mm, target_mm, config, ctx, baselines.fast_global_registration, refine=False)


@method("icp")
def icp(source_mm, target_mm, config: Config, ctx: MethodContext) -> RegistrationResult:
    """Point-to-plane ICP from identity (centroids aligned by the preprocessing)."""

    def estimate(src: np.ndarray, tgt: np.ndarray, cfg: Config, cache: dict) -> np.ndarray:
        return baselines.icp_point_to_plane(src, tgt, np.eye(4), cfg)

    return run_global_pipeline(source_mm, target_mm, config, ctx, estimate, refine=False)


@method("track")
def track(source_mm, target_mm, config: Config, ctx: MethodContext) -> RegistrationResult:
    """Trimmed point-to-plane ICP from a prior pose (the previous frame's): no global search."""
    return _from_prior(source_mm, target_mm, config, ctx, "track", refine=True)


@method("evaluate")
def evaluate(source_mm, target_mm, config: Config, ctx: MethodContext) -> RegistrationResult:
    """A given pose as is (no search, no ICP): its residual, uncertainty, free-space violation and TRE."""
    return _from_prior(source_mm, target_mm, config, ctx, "evaluate", refine=False)


def _from_prior(
    source_mm: np.ndarray, target_mm: np.ndarray, config: Config, ctx: MethodContext, name: str, *, refine: bool
) -> RegistrationResult:
    """The result of a prior pose (`initial_T_mm`), refined by ICP or as given."""
    if ctx.initial_T_mm is None:
        raise InputError(f"method '{name}' starts from a prior pose and needs initial_T_mm (the previous registration)")
    t = time.perf_counter()
    prep = prepare(source_mm, target_mm, config, ctx.cache)
    times = {"preprocess": _lap(t)}
    T_norm = np.linalg.inv(_norm_to_mm(prep.target_norm)) @ ctx.initial_T_mm @ _norm_to_mm(prep.source_norm)
    if refine:
        t = time.perf_counter()
        T_norm = _refine(T_norm, prep, config, ctx.cache)
        times["refine"] = _lap(t)
    return _single_result(T_norm, prep, times, "tracked" if refine else "given", config, ctx)


@method("procrustes")
def procrustes_oracle(source_mm, target_mm, config: Config, ctx: MethodContext) -> RegistrationResult:
    """Oracle: least-squares rigid fit of the ground-truth fiducials (lower bound of rigid error)."""
    if ctx.source_fiducials_mm is None or ctx.target_fiducials_mm is None:
        raise InputError("method 'procrustes' is the ground-truth oracle and needs source and target fiducials")
    if len(ctx.source_fiducials_mm) < 3:
        raise InputError("method 'procrustes' needs at least 3 fiducial pairs")
    t = time.perf_counter()
    T = baselines.kabsch_np(ctx.source_fiducials_mm, ctx.target_fiducials_mm)
    times = {"estimate": _lap(t)}
    prep = prepare(source_mm, target_mm, config, ctx.cache)
    T_norm = np.linalg.inv(_norm_to_mm(prep.target_norm)) @ T @ _norm_to_mm(prep.source_norm)
    residual = residual_norm(T_norm, prep) * prep.source_norm.scale_mm
    uncertainty = uncertainty_mm(T_norm, prep, config, times)
    violation, free_space = _final_free_space(free_space_scorer(prep, config, ctx), T_norm, times)
    return RegistrationResult(
        T_target_source=T,
        method="procrustes",
        residual_mm=residual,
        runtime_ms=times,
        candidates=[Candidate("fiducials", T, residual, len(ctx.source_fiducials_mm), free_space_violation=violation)],
        chosen=0,
        uncertainty_mm=uncertainty,
        free_space_violation=violation,
        free_space=free_space,
        n_matches=len(ctx.source_fiducials_mm),
        visibility=prep.visibility,
        n_source=len(prep.source),
        n_target=len(prep.target),
    )


def _norm_to_mm(norm: Normalization) -> np.ndarray:
    """4x4 matrix mapping normalized coordinates to mm: p_mm = s p_norm + c."""
    T = np.eye(4)
    T[:3, :3] *= norm.scale_mm
    T[:3, 3] = norm.centroid_mm
    return T
