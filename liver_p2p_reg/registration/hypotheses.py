"""Scoring and choosing pose hypotheses: ICP screening, free space, uncertainty, a one-pose result."""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import RegistrationError
from liver_p2p_reg.registration.confidence import pose_uncertainty
from liver_p2p_reg.registration.context import MethodContext
from liver_p2p_reg.registration.freespace import Scorer, penalized
from liver_p2p_reg.registration.preprocess import PreprocessedPair, denormalize_transform, residual_norm
from liver_p2p_reg.registration.refine import refine_poses
from liver_p2p_reg.registration.surface_search import SEARCH_MARGIN, search_model, search_poses
from liver_p2p_reg.result import Candidate, RegistrationResult


def uncertainty_mm(T_norm: np.ndarray, prep: PreprocessedPair, config: Config, times: dict[str, float]) -> float:
    """`confidence.pose_uncertainty` of a final pose on the voxelized clouds (ICP's gate and trim), in mm.

    Records its time as the "confidence" stage in `times`.
    """
    t = time.perf_counter()
    value = pose_uncertainty(
        T_norm,
        prep.source,
        prep.target,
        max_corr=config.icp_max_corr_norm,
        trim_ratio=config.icp_trim_ratio,
        source_index=prep.source_tree,
    )
    times["confidence"] = lap_ms(t)
    return value * prep.source_norm.scale_mm


def screen_candidates(
    poses_norm: list[np.ndarray],
    order: list[int],
    prep: PreprocessedPair,
    config: Config,
    cache: dict[str, Any],
    scorer: Scorer | None = None,
    extra: int | None = None,
    searched: frozenset[int] = frozenset(),
) -> tuple[int, list[tuple[int, np.ndarray, float, float]]]:
    """Short ICP from each distinct candidate (best-ranked first); the lowest residual after it wins
    (with a known sensor origin: the lowest residual made worse by its free-space violation).

    Returns the winner's index and every screened (index, pose, residual, violation), normalized
    units; the full refinement then starts from the winner's own pose (not from the screened one),
    so that a winner P2P also chose gets exactly the unscreened result. At most `config.refine_candidates`
    distinct candidates are screened, besides `extra` (RANSAC's pose) and `searched` (the surface search's poses),
    which are screened whenever they are distinct. A searched pose wins only where its key is below
    `surface_search.SEARCH_MARGIN` times every other's: it comes without any match's evidence.
    """
    tried: list[np.ndarray] = []
    picked: list[int] = []
    counted = 0  # screened candidates other than `extra` and `searched`
    for i in order:
        always = i == extra or i in searched
        if not always and counted >= config.refine_candidates:
            continue  # full; `extra` and `searched` may still come
        T = poses_norm[i]
        # near-duplicates (< ~5 deg and 0.05 normalized apart) would converge to the same pose
        if any(
            np.linalg.norm(T[:3, :3] - P[:3, :3]) < 0.1 and np.linalg.norm(T[:3, 3] - P[:3, 3]) < 0.05 for P in tried
        ):
            continue
        tried.append(T)
        picked.append(i)
        counted += not always
    # The picks depend on the starting poses only, so their short ICPs run together (refine_poses).
    moved = refine_poses(
        tried, prep, config, cache, max_points=config.screen_icp_points, max_iterations=config.screen_icp_iterations
    )
    screened = [(i, T_s, residual_norm(T_s, prep)) for i, T_s in zip(picked, moved, strict=True)]
    assert screened  # order holds at least the chosen candidate
    violation = scorer([T_s for _, T_s, _ in screened]) if scorer is not None else np.full(len(screened), np.nan)
    keys = [
        penalized(res, v, config.free_space_weight) / (SEARCH_MARGIN if i in searched else 1.0)
        for (i, _, res), v in zip(screened, violation, strict=True)
    ]
    best = int(np.argmin(keys))  # the first of equals, as P2P's own choice
    return screened[best][0], [(i, T_s, res, float(v)) for (i, T_s, res), v in zip(screened, violation, strict=True)]


def ransac_candidate_wanted(prep: PreprocessedPair, config: Config) -> bool:
    """Whether this view is small enough for RANSAC's candidate (its estimated visibility below the threshold)."""
    return prep.visibility < config.ransac_candidate_visibility


def ransac_hypothesis(
    prep: PreprocessedPair, config: Config, ctx: MethodContext, times: dict[str, float]
) -> tuple[np.ndarray, Candidate] | None:
    """FPFH + RANSAC's pose (normalized) and its candidate record, on a view whose estimated visibility is below
    `ransac_candidate_visibility`; None on a larger view or when RANSAC finds no estimate.

    Why: on small views the learned matcher and FPFH fail on different cases (validation: the better of the two
    poses after ICP is right more often than either), and the screening ICP tells the two apart by their fit.
    Its time is recorded as the "ransac" stage (run beside the matcher, `RansacBeside`: as "ransac_beside").
    """
    if not ransac_candidate_wanted(prep, config):
        return None
    from liver_p2p_reg.registration.baselines import fpfh_ransac  # Open3D: only where the candidate is wanted

    t = time.perf_counter()
    try:
        T_norm = np.asarray(fpfh_ransac(prep.source, prep.target, config, ctx.cache), dtype=np.float64)
    except RegistrationError:
        T_norm = None  # no estimate: P2P's candidates alone
    times["ransac"] = lap_ms(t)
    if T_norm is None or not np.isfinite(T_norm).all():
        return None
    candidate = Candidate(
        name="fpfh-ransac",
        T_target_source=denormalize_transform(T_norm, prep.source_norm, prep.target_norm),
        residual_mm=residual_norm(T_norm, prep) * prep.source_norm.scale_mm,
        n_matches=0,
    )
    return T_norm, candidate


def search_hypotheses(
    prep: PreprocessedPair, config: Config, ctx: MethodContext, times: dict[str, float]
) -> list[tuple[np.ndarray, Candidate]]:
    """The surface search's poses (normalized) and their candidate records, on a view whose estimated visibility is
    below `surface_search_visibility`; none on a larger view. Its time is recorded as the "search" stage."""
    if not prep.visibility < config.surface_search_visibility:
        return []
    t = time.perf_counter()
    poses = search_poses(prep, search_model(prep, ctx.cache))
    times["search"] = lap_ms(t)
    return [
        (
            T_norm,
            Candidate(
                name=f"surface-search-{k}",
                T_target_source=denormalize_transform(T_norm, prep.source_norm, prep.target_norm),
                residual_mm=residual_norm(T_norm, prep) * prep.source_norm.scale_mm,
                n_matches=0,
            ),
        )
        for k, T_norm in enumerate(poses)
    ]


class RansacBeside:
    """`ransac_hypothesis` computed on a thread of its own while the calling thread runs the matcher.

    Why: on two cores the network and the matching do not keep both busy, and RANSAC's pose depends on the
    prepared pair only, so its time can hide behind theirs. The same function on the same inputs: the same
    pose (Open3D's generator is seeded in the call, its RANSAC pinned to `open3d_threads`, and OpenMP keeps
    thread counts per calling thread, so torch's count in the calling thread is untouched). `result` waits for
    it and records the wait as the "ransac" stage (the time the registration spent on it) and the thread's own
    time as "ransac_beside".
    """

    def __init__(self, prep: PreprocessedPair, config: Config, ctx: MethodContext) -> None:
        self.times: dict[str, float] = {}
        self.value: tuple[np.ndarray, Candidate] | None = None
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, args=(prep, config, ctx), name="ransac-candidate")
        self.thread.daemon = True  # never holds the interpreter open (run_feature_pipeline joins it on every way out)
        self.thread.start()

    def _run(self, prep: PreprocessedPair, config: Config, ctx: MethodContext) -> None:
        try:
            self.value = ransac_hypothesis(prep, config, ctx, self.times)
        except BaseException as exc:  # handed to the calling thread in `result`
            self.error = exc

    def result(self, times: dict[str, float]) -> tuple[np.ndarray, Candidate] | None:
        """`ransac_hypothesis`'s value (or its exception), once the thread is done."""
        t = time.perf_counter()
        self.thread.join()
        times["ransac"] = lap_ms(t)
        if "ransac" in self.times:
            times["ransac_beside"] = self.times["ransac"]
        if self.error is not None:
            raise self.error
        return self.value


def free_space_scorer(prep: PreprocessedPair, config: Config, ctx: MethodContext) -> Scorer | None:
    """The free-space scorer of this registration's view; None without a known sensor origin."""
    if ctx.sensor_origin_mm is None:
        return None
    origin = prep.target_norm.apply(ctx.sensor_origin_mm[None])[0]
    band = config.free_space_band_mm / prep.source_norm.scale_mm
    return Scorer(prep.source, prep.target, origin, config.voxel_size_norm, band)


def free_space_choice(out: Any, violation: np.ndarray, config: Config) -> int:
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


def final_free_space(scorer: Scorer | None, T_norm: np.ndarray, times: dict[str, float]) -> tuple[float, str]:
    """The final pose's violation and the scorer's status; records the scorer's time as the "free_space" stage."""
    if scorer is None:
        return float("nan"), ""
    violation = float(scorer([T_norm])[0])
    times["free_space"] = scorer.ms
    return violation, scorer.status


def single_result(
    T_norm: np.ndarray, prep: PreprocessedPair, times: dict[str, float], name: str, config: Config, ctx: MethodContext
) -> RegistrationResult:
    """The result of a one-hypothesis method (no P2P candidates) from its normalized transform."""
    uncertainty = uncertainty_mm(T_norm, prep, config, times)
    residual = residual_norm(T_norm, prep) * prep.source_norm.scale_mm
    T_mm = denormalize_transform(T_norm, prep.source_norm, prep.target_norm)
    violation, free_space = final_free_space(free_space_scorer(prep, config, ctx), T_norm, times)
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


def lap_ms(start: float) -> float:
    """Milliseconds since `start` (a perf_counter reading)."""
    return (time.perf_counter() - start) * 1e3
