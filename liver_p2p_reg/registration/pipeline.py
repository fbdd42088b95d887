"""The registration pipelines as direct calls: preprocess -> features -> matching [-> P2P] [-> screen, ICP]
-> uncertainty and free space -> result in mm; the one-estimate baselines, a prior pose and the oracle.

`methods.run_method` calls one of the four `run_*` functions below with its table row's options.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from liver_p2p_reg.config import Config, P2PSection
from liver_p2p_reg.errors import InputError, RegistrationError
from liver_p2p_reg.registration import baselines
from liver_p2p_reg.registration.contenders import judge_contenders
from liver_p2p_reg.registration.context import MethodContext
from liver_p2p_reg.registration.freespace import penalized
from liver_p2p_reg.registration.hypotheses import (
    RansacBeside,
    final_free_space,
    free_space_choice,
    free_space_scorer,
    lap_ms,
    ransac_candidate_wanted,
    ransac_hypothesis,
    screen_candidates,
    search_hypotheses,
    single_result,
    uncertainty_mm,
)
from liver_p2p_reg.registration.preprocess import (
    denormalize_transform,
    norm_to_mm,
    preprocess_pair,
    residual_norm,
)
from liver_p2p_reg.registration.refine import refine_pose
from liver_p2p_reg.result import Candidate, RegistrationResult

LOG = logging.getLogger("liver_p2p_reg")

# The candidate's RANSAC runs on a thread beside the matcher (hypotheses.RansacBeside); False runs it after the
# matcher, in line: the same results bit for bit (a test holds both to that), only slower on two cores.
RANSAC_BESIDE = True

if TYPE_CHECKING:  # torch and the P2P module are imported where used: the Open3D baselines need neither
    from liver_p2p_reg.registration.features.base import FeatureProvider

# The one-estimate methods' global step (normalized, voxelized clouds -> a normalized 4x4).
ESTIMATORS: dict[str, Callable[[np.ndarray, np.ndarray, Config, dict[str, Any]], np.ndarray]] = {
    "ransac": baselines.fpfh_ransac,
    "fgr": baselines.fast_global_registration,
    "icp": baselines.icp_from_identity,
}


def feature_provider(
    features: str, config: Config, ctx: MethodContext, source_mm: np.ndarray, warnings: list[str]
) -> FeatureProvider | Callable[[], FeatureProvider]:
    """The provider of a table row's `features` ("fpfh" | "learned"); the learned one as a function
    making it, so torch and the weights load only once the inputs passed the preprocessing."""
    if features == "fpfh":
        from liver_p2p_reg.registration.features.fpfh import FPFHProvider

        return FPFHProvider(config.normal_radius_norm, config.fpfh_radius_norm)
    if features == "learned":

        def make() -> FeatureProvider:
            from liver_p2p_reg.registration.features.learned.provider import learned_provider  # torch

            return learned_provider(config, ctx.cache, source_mm, warnings)

        return make
    raise InputError(f"unknown features {features!r}; choose fpfh or learned")


def require_device(device: str) -> None:
    """InputError when `device` is one torch cannot use here (cuda without a CUDA device)."""
    if device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise InputError("device 'cuda' requested but torch sees no CUDA device; use device: cpu")


def p2p_settings(config: Config, use_p2p: bool) -> P2PSection:
    """The P2P module's settings: Config's P2P section; k = 0 (no patches) for the methods without P2P."""
    return config.p2p if use_p2p else dataclasses.replace(config.p2p, k=0)


def run_feature_pipeline(
    source_mm: np.ndarray,
    target_mm: np.ndarray,
    config: Config,
    ctx: MethodContext,
    provider: str | FeatureProvider | Callable[[], FeatureProvider],
    *,
    use_p2p: bool,
    refine: bool,
    ransac_candidate: bool = False,
) -> RegistrationResult:
    """preprocess -> features -> dual-softmax matching [-> P2P] [-> refine] -> result in mm.

    `ransac_candidate`: FPFH + RANSAC's pose joins the candidates on small views and is always screened
    (`hypotheses.ransac_hypothesis`).

    `provider`: a table row's features ("fpfh" | "learned"), a provider, or a function making one:
    it is called after the inputs passed the preprocessing, so a bad input (swapped clouds, too few
    points) is reported before torch or a model is loaded.
    """
    warnings: list[str] = []
    if isinstance(provider, str):
        provider = feature_provider(provider, config, ctx, source_mm, warnings)
    times: dict[str, float] = {}
    t = time.perf_counter()
    prep = preprocess_pair(source_mm, target_mm, config, ctx.cache)
    prepare_ms = lap_ms(t)
    require_device(config.device)
    if callable(provider):  # first call in a process: the model's loading counts in "total" only
        provider = provider()
    # RANSAC's candidate pose beside the matcher, started once torch and the model are loaded (not beside their
    # first imports); joined on every way out, so no thread of this registration outlives it (an error in the
    # matcher then comes out after RANSAC's end)
    wanted = ransac_candidate and RANSAC_BESIDE and ransac_candidate_wanted(prep, config)
    beside = RansacBeside(prep, config, ctx) if wanted else None
    try:
        return _matched_and_screened(
            prep, prepare_ms, config, ctx, provider, use_p2p, refine, ransac_candidate, beside, times, warnings
        )
    finally:
        if beside is not None:
            beside.thread.join()


def _matched_and_screened(
    prep, prepare_ms, config, ctx, provider, use_p2p, refine, ransac_candidate, beside, times, warnings
) -> RegistrationResult:
    """`run_feature_pipeline` from the prepared pair on: features, matching, P2P, the candidates' screening,
    ICP, the result."""
    import torch

    from liver_p2p_reg.registration.p2p import p2p_register

    t = time.perf_counter()
    device = torch.device(config.device)
    src = torch.as_tensor(prep.source, dtype=torch.float32, device=device)
    tgt = torch.as_tensor(prep.target, dtype=torch.float32, device=device)
    times["preprocess"] = prepare_ms + lap_ms(t)
    t = time.perf_counter()
    with torch.inference_mode():
        x_src, x_tgt = provider.describe(src, tgt, ctx.cache)
        times["features"] = lap_ms(t)
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
    chosen, n_p2p = out.chosen, len(candidates)
    if beside is not None:
        extra = beside.result(times)
    else:
        extra = ransac_hypothesis(prep, config, ctx, times) if ransac_candidate else None
    if extra is not None:
        poses_norm.append(extra[0])
        candidates.append(extra[1])
    searched = search_hypotheses(prep, config, ctx, times) if ransac_candidate and refine else []
    first_searched = len(candidates)
    for T_norm, candidate in searched:
        poses_norm.append(T_norm)
        candidates.append(candidate)
    scorer = free_space_scorer(prep, config, ctx)
    if scorer is not None and scorer.view is not None:
        violation = scorer(poses_norm)
        for candidate, v in zip(candidates, violation, strict=True):
            candidate.free_space_violation = float(v)
        chosen = free_space_choice(out, violation[:n_p2p], config)
    if not candidates[chosen].ok and extra is not None:
        chosen = n_p2p  # P2P found nothing: RANSAC's pose alone
    elif not candidates[chosen].ok and searched:
        chosen = first_searched  # P2P and RANSAC found nothing: the search's best pose (the screening may move it)
    elif not candidates[chosen].ok:
        raise RegistrationError(
            f"{provider.name}: no candidate had >= 3 non-degenerate matches (visibility {prep.visibility:.2f})"
        )
    T_norm = poses_norm[chosen]
    residual = residual_norm(T_norm, prep) if chosen >= n_p2p else float(out.residual[chosen])
    screened: list[Candidate] = []
    if refine and (config.refine_candidates > 1 or extra is not None or searched):
        t = time.perf_counter()
        p2p_others = (i for i, c in enumerate(candidates[:n_p2p]) if c.ok and i != chosen)
        if scorer is None or scorer.view is None:
            others = sorted(p2p_others, key=lambda i: out.residual[i])
        else:
            others = sorted(
                p2p_others,
                key=lambda i: penalized(
                    float(out.residual[i]), candidates[i].free_space_violation, config.free_space_weight
                ),
            )
        # RANSAC's pose is screened second, beside (not instead of) P2P's own candidates
        first = [chosen] if extra is None or chosen == n_p2p else [chosen, n_p2p]
        ransac_index = None if extra is None else n_p2p
        # the search's poses after RANSAC's, each screened too (their own margin: screen_candidates)
        search_indices = frozenset(range(first_searched, len(candidates)))
        chosen, tried = screen_candidates(
            poses_norm,
            [*first, *sorted(search_indices - {chosen}), *others],
            prep,
            config,
            ctx.cache,
            scorer,
            ransac_index,
            search_indices,
        )
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
        times["screen"] = lap_ms(t)
    if refine:
        t = time.perf_counter()
        T_norm = refine_pose(T_norm, prep, config, ctx.cache)
        times["refine"] = lap_ms(t)
        judged = ransac_candidate and prep.visibility < config.ransac_candidate_visibility
        if judged and ctx.judge_keys is not None and config.contender_judge_ratio > 0 and len(screened) >= 2:
            t = time.perf_counter()
            try:
                chosen, T_norm, keys = judge_contenders(
                    tried, chosen, T_norm, poses_norm, prep, config, ctx.cache, ctx.judge_keys, scorer
                )
            except Exception as exc:  # the judge only refines a choice: whatever it raises, the screening's stands
                LOG.exception("the contenders' judge raised")
                warnings.append(f"the contenders' judge failed ({type(exc).__name__}: {exc}): the screening's pose")
                keys = {}
            for candidate, (i, *_) in zip(screened, tried, strict=True):
                candidate.judge_key_mm = keys.get(i, float("nan"))
            times["judge"] = lap_ms(t)
        residual = residual_norm(T_norm, prep)
    uncertainty = uncertainty_mm(T_norm, prep, config, times)
    violation_final, free_space = final_free_space(scorer, T_norm, times)
    return RegistrationResult(
        T_target_source=denormalize_transform(T_norm, prep.source_norm, prep.target_norm),
        method=provider.name,
        residual_mm=residual * scale,
        warnings=warnings,
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
    estimate: str,
    *,
    refine: bool,
) -> RegistrationResult:
    """preprocess -> one global estimate (ESTIMATORS: RANSAC, FGR, ICP) [-> refine] -> result in mm."""
    times: dict[str, float] = {}
    t = time.perf_counter()
    prep = preprocess_pair(source_mm, target_mm, config, ctx.cache)
    times["preprocess"] = lap_ms(t)
    t = time.perf_counter()
    T_norm = np.asarray(ESTIMATORS[estimate](prep.source, prep.target, config, ctx.cache), dtype=np.float64)
    times["estimate"] = lap_ms(t)
    if not np.isfinite(T_norm).all():
        raise RegistrationError("the estimator returned a non-finite transform")
    if refine:
        t = time.perf_counter()
        T_norm = refine_pose(T_norm, prep, config, ctx.cache)
        times["refine"] = lap_ms(t)
    return single_result(T_norm, prep, times, "estimate", config, ctx)


def run_from_prior(
    source_mm: np.ndarray, target_mm: np.ndarray, config: Config, ctx: MethodContext, name: str, *, refine: bool
) -> RegistrationResult:
    """The result of a prior pose (`initial_T_mm`), refined by ICP or as given."""
    if ctx.initial_T_mm is None:
        raise InputError(f"method '{name}' starts from a prior pose and needs initial_T_mm (the previous registration)")
    t = time.perf_counter()
    prep = preprocess_pair(source_mm, target_mm, config, ctx.cache)
    times = {"preprocess": lap_ms(t)}
    T_norm = np.linalg.inv(norm_to_mm(prep.target_norm)) @ ctx.initial_T_mm @ norm_to_mm(prep.source_norm)
    if refine:
        t = time.perf_counter()
        T_norm = refine_pose(T_norm, prep, config, ctx.cache)
        times["refine"] = lap_ms(t)
    return single_result(T_norm, prep, times, "tracked" if refine else "given", config, ctx)


def run_oracle(source_mm: np.ndarray, target_mm: np.ndarray, config: Config, ctx: MethodContext) -> RegistrationResult:
    """Oracle: least-squares rigid fit of the ground-truth fiducials (lower bound of rigid error)."""
    if ctx.source_fiducials_mm is None or ctx.target_fiducials_mm is None:
        raise InputError("method 'procrustes' is the ground-truth oracle and needs source and target fiducials")
    if len(ctx.source_fiducials_mm) < 3:
        raise InputError("method 'procrustes' needs at least 3 fiducial pairs")
    t = time.perf_counter()
    T = baselines.kabsch_np(ctx.source_fiducials_mm, ctx.target_fiducials_mm)
    times = {"estimate": lap_ms(t)}
    prep = preprocess_pair(source_mm, target_mm, config, ctx.cache)
    T_norm = np.linalg.inv(norm_to_mm(prep.target_norm)) @ T @ norm_to_mm(prep.source_norm)
    # The fiducials' fit itself, not its round trip through the normalization, is the oracle's pose.
    result = single_result(T_norm, prep, times, "fiducials", config, ctx)
    n_pairs = len(ctx.source_fiducials_mm)
    result.T_target_source, result.method, result.n_matches = T, "procrustes", n_pairs
    result.candidates = [dataclasses.replace(result.candidates[0], T_target_source=T, n_matches=n_pairs)]
    return result
