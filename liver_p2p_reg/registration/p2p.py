"""The patches-to-partial (P2P) module: K patch candidates + selection, on any point features."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from liver_p2p_reg.config import P2PSection
from liver_p2p_reg.registration.matching import (
    log_dual_softmax,
    log_dual_softmax_with_patches,
    matches_per_row,
    score_matrix,
)
from liver_p2p_reg.registration.nearest import NearestIndex
from liver_p2p_reg.registration.procrustes import weighted_procrustes

MIN_REFIT_MATCHES = 6  # a re-fit on fewer matches than this keeps the previous pose
# consensus_pose: matches per hypothesis (the seed and its most compatible partners), and the
# distance (normalized) within which a hypothesis scores a match's confidence
CONSENSUS_GROUP = 16
CONSENSUS_INLIER = 0.1


def geometric_radii(start: float, end: float, count: int) -> tuple[float, ...]:
    """`count` radii shrinking geometrically from `start` to `end` (the robust re-fit schedule)."""
    return tuple(float(r) for r in np.geomspace(start, end, count)) if count > 0 else ()


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
    # with consensus_seeds > 0, indices 1+K .. 1+2K repeat 0..K started from the consensus pose
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
    tree = NearestIndex(source.detach().cpu().double().numpy())
    R_np, t_np, tgt = R.cpu().double().numpy(), t.cpu().double().numpy(), target.cpu().double().numpy()
    out = np.full(len(R_np), np.inf)
    # Candidates that converged to the same pose (a consensus-started twin often ends where its
    # plain candidate did) are measured once; "same" is 1e-9 normalized, far below any residual.
    poses = np.concatenate([R_np.reshape(len(R_np), 9), t_np], axis=1)
    first = np.arange(len(R_np))  # each candidate's first equal pose (itself unless repeated)
    good = []
    for c in np.flatnonzero(ok.cpu().numpy()):
        same = [g for g in good if np.abs(poses[g] - poses[c]).max() < 1e-9]
        if same:
            first[c] = same[0]
        else:
            good.append(c)
    if good:
        # All candidates' queries in one call: y_s = R^T (y - t), as row vectors (y - t) @ R.
        queries = np.einsum("cmi,cij->cmj", tgt[None] - t_np[good][:, None], R_np[good])
        dist, _ = tree.query(queries.reshape(-1, 3))
        out[good] = dist.reshape(len(good), -1).mean(axis=1)
        out = out[first]  # failed candidates point at themselves and stay inf
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


def pair_distances_sq(R: torch.Tensor, t: torch.Tensor, source: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """||R_q s_p + t_q - y_p||^2 for every pose q and matched pair p: (B, Q, P).

    R (B, Q, 3, 3), t (B, Q, 3), source/target (B, P, 3). Expanded into matrix products
    (|s|^2 + |t|^2 + |y|^2 - 2 t.y + 2 (R^T t).s - 2 vec(R).vec(y s^T)) because a (B, Q, P, 3)
    difference tensor and its norm over the last axis cost ~20x more on CPU.
    """
    outer = (target[..., :, None] * source[..., None, :]).flatten(-2)  # (B, P, 9): y s^T
    rt_t = (R.transpose(-1, -2) @ t[..., None])[..., 0]  # (B, Q, 3): R^T t
    return (
        (source.square().sum(-1) + target.square().sum(-1))[:, None, :]
        + t.square().sum(-1)[..., None]
        - 2 * t @ target.transpose(-1, -2)
        + 2 * rt_t @ source.transpose(-1, -2)
        - 2 * R.flatten(-2) @ outer.transpose(-1, -2)
    )


def consensus_pose(
    source: torch.Tensor, target: torch.Tensor, weights: torch.Tensor, settings: P2PSection
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Best of the hypotheses grown from each strong match and its most compatible partners.

    Batched: matched pairs source/target (B, P, 3), weights (B, P). Two correct matches keep
    their distance under a rigid motion (up to the deformation), whatever the pose, so the
    pairwise compatibility of the `consensus_seeds` most confident matches, sharpened by its
    second order (SC^2: compatible pairs that share many compatible partners), groups correct
    matches without a pose guess. Each seed's group gives one Procrustes hypothesis; the one
    that brings the most match confidence within `CONSENSUS_INLIER` wins. A weighted fit of all
    matches is pulled by the wrong ones; on a small smooth view they can be the majority, and
    the robust re-fit then starts (and stays) in the wrong basin. Returns R (B,3,3), t (B,3), ok (B,).
    """
    with torch.no_grad():
        b, p = weights.shape
        q = min(settings.consensus_seeds, p)
        top_w, top = torch.topk(weights, q, dim=1)  # (B, Q)
        seeds_src = torch.gather(source, 1, top[..., None].expand(-1, -1, 3))
        seeds_tgt = torch.gather(target, 1, top[..., None].expand(-1, -1, 3))
        valid = top_w > 0
        mismatch = torch.cdist(seeds_src, seeds_src) - torch.cdist(seeds_tgt, seeds_tgt)
        pair_valid = (valid[:, :, None] & valid[:, None, :]).to(weights.dtype)
        compat = (1 - mismatch.square() / settings.consensus_sigma_norm**2).clamp(min=0) * pair_valid
        compat2 = compat * (compat @ compat)
        g = min(CONSENSUS_GROUP, q)
        group = torch.topk(compat2, g, dim=2).indices.reshape(b, q * g)  # each seed's row includes itself
        g_src = torch.gather(seeds_src, 1, group[..., None].expand(-1, -1, 3)).view(b * q, g, 3)
        g_tgt = torch.gather(seeds_tgt, 1, group[..., None].expand(-1, -1, 3)).view(b * q, g, 3)
        R, t, ok = weighted_procrustes(g_src, g_tgt)
        R, t, ok = R.view(b, q, 3, 3), t.view(b, q, 3), ok.view(b, q) & valid
        dist2 = pair_distances_sq(R, t, source, target)  # (B, Q, P)
        score = torch.where(dist2 < CONSENSUS_INLIER**2, weights[:, None], 0.0).sum(dim=-1)
        score = torch.where(ok, score, -1.0)
        best = score.argmax(dim=1)
        rows = torch.arange(b, device=weights.device)
        return R[rows, best], t[rows, best], ok[rows, best] & (score[rows, best] > 0)


def _fit_candidates(
    source: torch.Tensor, target: torch.Tensor, weights: torch.Tensor, settings: P2PSection
) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Poses for a batch of matched pairs (B, P, 3): the weighted fit, then (if on) the consensus twins.

    Every start is followed by the robust re-fit; plain and consensus starts are re-fitted in one
    batched call (half the small-tensor calls, which dominate at these sizes).
    """
    starts = [weighted_procrustes(source, target, weights)]
    if settings.consensus_seeds > 0:
        starts.append(consensus_pose(source, target, weights, settings))
    R, t, ok = (torch.cat(parts) for parts in zip(*starts, strict=True))
    radii = geometric_radii(settings.refit_radius_start_norm, settings.refit_radius_end_norm, settings.refit_iterations)
    if radii:
        copies = len(starts)
        R, t = robust_refit(
            source.repeat(copies, 1, 1),
            target.repeat(copies, 1, 1),
            weights.repeat(copies, 1),
            R,
            t,
            ok,
            radii,
        )
    b = source.shape[0]
    return [(R[i * b : (i + 1) * b], t[i * b : (i + 1) * b], ok[i * b : (i + 1) * b]) for i in range(len(starts))]


def p2p_register(
    source: torch.Tensor,
    target: torch.Tensor,
    x_source: torch.Tensor,
    x_target: torch.Tensor,
    settings: P2PSection,
) -> P2POutput:
    """Run complete-to-partial matching and, if k > 0, P2P on voxelized normalized clouds.

    source (N, 3), target (M, 3), x_source (N, d), x_target (M, d) (L2-normalized); settings:
    Config's P2P section (`config.p2p`), with k = 0 for the complete-to-partial candidate alone.
    Differentiable with respect to the features (until the discrete selection).
    """
    t0 = time.perf_counter()
    n, m = source.shape[0], target.shape[0]
    scores = score_matrix(x_source, x_target)  # (N, M)

    nodes = torch.empty(0, dtype=torch.long, device=source.device)
    patch_idx = None
    if settings.k > 0:
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
    # Matched pairs per candidate group: the whole source (1, N) and, with P2P, the patches (K, P).
    groups = [(source[None], target[tgt_idx][None], weight[None])]
    names = ["complete-to-partial"]
    if patch_idx is not None:
        # 4. Patch-to-target matching, all K patches at once.
        p_tgt_idx, p_weight = matches_per_row(
            patch_log_conf, settings.confidence_threshold, settings.mutual_only
        )  # (K, P)
        del patch_log_conf
        groups.append((source[patch_idx], target[p_tgt_idx], p_weight))
        names += [f"patch-{i}" for i in range(len(nodes))]
    per_group = [_fit_candidates(*group, settings) for group in groups]  # [group][start]
    starts = range(len(per_group[0]))
    fits = [per_group[g][s] for s in starts for g in range(len(groups))]  # plain candidates first, then twins
    if len(starts) > 1:
        names += [f"{name}-consensus" for name in names]
    R = torch.cat([f[0] for f in fits])
    t = torch.cat([f[1] for f in fits])
    ok = torch.cat([f[2] for f in fits])
    # Each candidate's own matches (a consensus-started candidate shares its plain twin's).
    matched_w = [w for _ in starts for group in groups for w in group[2].unbind(0)]
    n_matches = torch.stack([(w > 0).sum() for w in matched_w])
    t_match = time.perf_counter()

    # 5. Selection among the candidates.
    with torch.no_grad():
        residual = closest_point_residuals(source, target, R.detach(), t.detach(), ok)
        # Inlier count over the union of all correspondences (the paper's alternative rule).
        all_src = torch.cat([group[0].reshape(-1, 3) for group in groups])
        all_tgt = torch.cat([group[1].reshape(-1, 3) for group in groups])
        all_valid = torch.cat([group[2].reshape(-1) for group in groups]) > 0
        dist2 = pair_distances_sq(R.detach()[None], t.detach()[None], all_src[None], all_tgt[None])[0]  # (C, P)
        close = (dist2 < settings.inlier_radius_norm**2) & all_valid[None]
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
