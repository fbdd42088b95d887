"""The patches-to-partial (P2P) module: K patch candidates + selection, on any point features."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree

from .matching import log_dual_softmax, log_dual_softmax_with_patches, matches_per_row, score_matrix
from .procrustes import weighted_procrustes

MIN_REFIT_MATCHES = 6  # a re-fit on fewer matches than this keeps the previous pose


def geometric_radii(start: float, end: float, count: int) -> tuple[float, ...]:
    """`count` radii shrinking geometrically from `start` to `end` (the robust re-fit schedule)."""
    return tuple(float(r) for r in np.geomspace(start, end, count)) if count > 0 else ()


@dataclass
class P2PSettings:
    """The module's knobs (taken from Config by the pipelines)."""

    k: int = 5
    temperature: float = 0.1
    confidence_threshold: float = 0.0
    selection: str = "closest-point"  # or "inlier-count"
    inlier_radius: float = 0.05  # normalized units (the paper's tau)
    candidate_proposal: bool = True  # False: patch nodes by FPS over the whole source
    use_p2p: bool = True  # False: only the complete-to-partial candidate
    max_patch_rows: int = 0  # > 0: match only an even subsample of about this many rows per patch (speed)
    mutual_only: bool = False  # True: strict mutual nearest neighbours (the paper); False: every row's best match
    # robust re-fit radii (normalized), largest first; () = off (the paper's single fit)
    refit_radii: tuple[float, ...] = geometric_radii(0.3, 0.04, 6)


@dataclass
class P2POutput:
    """All candidates (index 0 = complete-to-partial, 1..K = patches), in normalized units."""

    R: torch.Tensor  # (C, 3, 3)
    t: torch.Tensor  # (C, 3)
    ok: torch.Tensor  # (C,) bool
    n_matches: torch.Tensor  # (C,) long
    residual: torch.Tensor  # (C,) mean closest-point distance target -> moved source (inf if failed)
    inliers: torch.Tensor  # (C,) long
    chosen: int
    names: list[str]
    patch_nodes: torch.Tensor  # (K,) source indices of the patch nodes
    runtime_ms: dict[str, float] = field(default_factory=dict)


def farthest_point_sampling(points: torch.Tensor, k: int, start: int = 0) -> torch.Tensor:
    """Indices of k points by farthest point sampling from `start` (deterministic)."""
    n = points.shape[0]
    k = min(k, n)
    chosen = torch.empty(k, dtype=torch.long, device=points.device)
    dist = torch.full((n,), float("inf"), dtype=points.dtype, device=points.device)
    current = start
    for i in range(k):  # K is small (<= 8); the O(K N) loop is negligible
        chosen[i] = current
        dist = torch.minimum(dist, ((points - points[current]) ** 2).sum(dim=1))
        current = int(torch.argmax(dist))
    return chosen


def closest_point_residuals(
    source: torch.Tensor, target: torch.Tensor, R: torch.Tensor, t: torch.Tensor, ok: torch.Tensor
) -> torch.Tensor:
    """Mean distance from each target point to the closest moved source point, per candidate.

    Moves the target into the source frame (R^T (y - t)) so one k-d tree over the source
    serves every candidate: O(C M log N) instead of a (C, M, N) distance tensor.
    """
    tree = cKDTree(source.detach().cpu().double().numpy())
    R_np, t_np, tgt = R.cpu().double().numpy(), t.cpu().double().numpy(), target.cpu().double().numpy()
    out = np.full(len(R_np), np.inf)
    good = np.flatnonzero(ok.cpu().numpy())
    if len(good):
        # All candidates' queries in one call: y_s = R^T (y - t), as row vectors (y - t) @ R.
        queries = np.einsum("cmi,cij->cmj", tgt[None] - t_np[good][:, None], R_np[good])
        dist, _ = tree.query(queries.reshape(-1, 3), k=1)
        out[good] = dist.reshape(len(good), -1).mean(axis=1)
    return torch.as_tensor(out, dtype=target.dtype, device=target.device)


def robust_refit(
    source: torch.Tensor,
    target: torch.Tensor,
    weights: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    ok: torch.Tensor,
    radii: tuple[float, ...],
) -> tuple[torch.Tensor, torch.Tensor]:
    """Re-fit each candidate on the matches its own pose explains within shrinking radii.

    Batched over candidates: source/target (B, P, 3) matched pairs, weights (B, P), R (B, 3, 3),
    t (B, 3). One weighted Procrustes fit is pulled by every wrong match; keeping only the
    matches within a radius of the current pose, and shrinking the radius, converges to the
    pose of the consistent majority (a deterministic, RANSAC-free consensus). A candidate whose
    re-fit degenerates (fewer than 3 matches left) keeps its previous pose.
    """
    for radius in radii:
        moved = source @ R.transpose(-1, -2) + t[..., None, :]
        inside = ((moved - target).norm(dim=-1) < radius) & (weights > 0)
        # Too few matches left: re-fit on the previous set instead, so no degenerate SVD
        # (whose backward pass is NaN) is ever evaluated; the result is then discarded.
        enough = inside.sum(dim=-1) >= MIN_REFIT_MATCHES
        kept = torch.where(inside, weights, 0.0)
        R_new, t_new, ok_new = weighted_procrustes(source, target, torch.where(enough[..., None], kept, weights))
        use = ok_new & ok & enough
        R = torch.where(use[..., None, None], R_new, R)
        t = torch.where(use[..., None], t_new, t)
    return R, t


def p2p_register(
    source: torch.Tensor,
    target: torch.Tensor,
    x_source: torch.Tensor,
    x_target: torch.Tensor,
    settings: P2PSettings,
) -> P2POutput:
    """Run complete-to-partial matching and, if enabled, P2P on voxelized normalized clouds.

    source (N, 3), target (M, 3), x_source (N, d), x_target (M, d) (L2-normalized).
    Differentiable with respect to the features (until the discrete selection).
    """
    t0 = time.perf_counter()
    n, m = source.shape[0], target.shape[0]
    scores = score_matrix(x_source, x_target)  # (N, M)

    nodes = torch.empty(0, dtype=torch.long, device=source.device)
    patch_idx = None
    if settings.use_p2p and settings.k > 0:
        # 1. Visible source point estimation: score summed over targets, keep the top M.
        visibility_score = scores.sum(dim=1)  # (N,)
        n_visible = min(m, n)
        visible = torch.topk(visibility_score.detach(), n_visible).indices
        pool = visible if settings.candidate_proposal else torch.arange(n, device=source.device)
        # 2. Patch nodes by FPS, starting from the most visible point of the pool.
        start = int(torch.argmax(visibility_score[pool]))
        nodes = pool[farthest_point_sampling(source[pool], settings.k, start=start)]
        # 3. Patches: each node's min(M, N) nearest source points.
        d_nodes = torch.cdist(source[nodes], source)  # (K, N)
        patch_idx = torch.topk(d_nodes, min(m, n), dim=1, largest=False).indices  # (K, P)

    # Complete-to-partial candidate: dual-softmax + nearest neighbours on the whole source.
    if patch_idx is None:
        log_conf, patch_log_conf = log_dual_softmax(scores, settings.temperature), None
    else:
        stride = 1
        if settings.max_patch_rows > 0:
            stride = max(1, -(-patch_idx.shape[1] // settings.max_patch_rows))  # ceil
        log_conf, patch_log_conf = log_dual_softmax_with_patches(scores, patch_idx, settings.temperature, stride)
        patch_idx = patch_idx[:, ::stride]  # the rows whose matches were computed
    tgt_idx, weight = matches_per_row(log_conf, settings.confidence_threshold, settings.mutual_only)  # (N,), (N,)
    del log_conf
    R0, t0_vec, ok0 = weighted_procrustes(source, target[tgt_idx], weight)
    if settings.refit_radii:
        R0, t0_vec = robust_refit(
            source[None], target[tgt_idx][None], weight[None], R0[None], t0_vec[None], ok0[None], settings.refit_radii
        )
        R0, t0_vec = R0[0], t0_vec[0]
    R_list, t_list, ok_list = [R0[None]], [t0_vec[None]], [ok0[None]]
    matched_src = [source]
    matched_tgt = [target[tgt_idx]]
    matched_w = [weight]
    names = ["complete-to-partial"]

    if patch_idx is not None:
        # 4. Patch-to-target matching + weighted Procrustes, all K patches at once.
        p_tgt_idx, p_weight = matches_per_row(
            patch_log_conf, settings.confidence_threshold, settings.mutual_only
        )  # (K, P)
        del patch_log_conf
        patch_src = source[patch_idx]  # (K, P, 3)
        patch_tgt = target[p_tgt_idx]  # (K, P, 3)
        Rk, tk, okk = weighted_procrustes(patch_src, patch_tgt, p_weight)
        if settings.refit_radii:
            Rk, tk = robust_refit(patch_src, patch_tgt, p_weight, Rk, tk, okk, settings.refit_radii)
        R_list.append(Rk)
        t_list.append(tk)
        ok_list.append(okk)
        matched_src.extend(patch_src.unbind(0))
        matched_tgt.extend(patch_tgt.unbind(0))
        matched_w.extend(p_weight.unbind(0))
        names += [f"patch-{i}" for i in range(len(nodes))]
    R = torch.cat(R_list)
    t = torch.cat(t_list)
    ok = torch.cat(ok_list)
    n_matches = torch.stack([(w > 0).sum() for w in matched_w])
    t_match = time.perf_counter()

    # 5. Selection among the candidates.
    with torch.no_grad():
        residual = closest_point_residuals(source, target, R.detach(), t.detach(), ok)
        # Inlier count over the union of all correspondences (the paper's alternative rule).
        all_src = torch.cat(matched_src)
        all_tgt = torch.cat(matched_tgt)
        all_valid = torch.cat(matched_w) > 0
        moved_pairs = all_src[None] @ R.detach().transpose(1, 2) + t.detach()[:, None]
        close = ((moved_pairs - all_tgt[None]).norm(dim=2) < settings.inlier_radius) & all_valid[None]
        inliers = torch.where(ok, close.sum(dim=1), torch.zeros_like(close.sum(dim=1)))
        if not bool(ok.any()):
            chosen = 0
        elif settings.selection == "inlier-count":
            chosen = int(torch.argmax(inliers))
        else:
            chosen = int(torch.argmin(residual))
    t_end = time.perf_counter()
    return P2POutput(
        R=R,
        t=t,
        ok=ok,
        n_matches=n_matches,
        residual=residual,
        inliers=inliers,
        chosen=chosen,
        names=names,
        patch_nodes=nodes,
        runtime_ms={"matching": (t_match - t0) * 1e3, "selection": (t_end - t_match) * 1e3},
    )
