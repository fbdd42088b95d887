"""Feature matching: score matrix, dual-softmax confidence, mutual nearest neighbours."""

from __future__ import annotations

import torch


def score_matrix(x_source: torch.Tensor, x_target: torch.Tensor) -> torch.Tensor:
    """S = x_S x_T^T for L2-normalized features: (..., N, d) x (M, d) -> (..., N, M)."""
    return x_source @ x_target.transpose(-1, -2)


# exp() of scores shifted by their global maximum is safe while the scores' range (divided
# by the temperature) stays below this; beyond it the slower per-axis logsumexp is used.
_EXP_SAFE_RANGE = 60.0


def log_dual_softmax(scores: torch.Tensor, temperature: float) -> torch.Tensor:
    """log(softmax_row(S / T) * softmax_col(S / T)), computed stably.

    Fast path: one exp() of the globally shifted scores and two sums (the axis-wise
    logsumexp along dim -2 is several times slower on CPU); exact in float32 as long as the
    score range over the temperature is moderate, which L2-normalized features guarantee.
    """
    scaled = scores / temperature
    # The shift cancels mathematically, so it carries no gradient (and scaled may change in place).
    top = scaled.detach().amax(dim=(-2, -1), keepdim=True)
    low = scaled.detach().amin(dim=(-2, -1), keepdim=True)
    if bool(((top - low) < _EXP_SAFE_RANGE).all()):
        # In place on the one (N, M) buffer: fresh large tensors cost page faults on CPU, more
        # than the arithmetic. Autograd-safe: exp() keeps its output, not its input.
        shifted = scaled.sub_(top)
        e = shifted.exp()
        row = e.sum(dim=-1, keepdim=True).log_()
        col = e.sum(dim=-2, keepdim=True).log_()
        return shifted.mul_(2).sub_(row).sub_(col)
    return 2 * scaled - scaled.logsumexp(dim=-1, keepdim=True) - scaled.logsumexp(dim=-2, keepdim=True)


def log_dual_softmax_with_patches(
    scores: torch.Tensor, patch_rows: torch.Tensor, temperature: float, row_stride: int = 1
) -> tuple[torch.Tensor, torch.Tensor]:
    """Log dual-softmax of the whole (N, M) score matrix and of each patch's rows at once.

    patch_rows (K, P) indexes rows of `scores`; the patch result (K, P, M) equals
    log_dual_softmax(scores[patch_rows]). A patch's row normalizers are the whole matrix's
    (same rows, same columns); only its column sums differ, and those come from one
    (K, N) x (N, M) product with the patch-membership matrix, so the patches reuse the
    whole matrix's exponentials instead of computing K * P * M new ones.
    With row_stride > 1 only every row_stride-th row of each patch is returned, (K, P', M):
    those rows are exact (the column sums still cover the whole patch), at a fraction of the cost.
    """
    scaled = scores / temperature
    top = scaled.detach().amax()
    if float(top - scaled.detach().amin()) >= _EXP_SAFE_RANGE:
        full_patches = log_dual_softmax(scores[patch_rows], temperature)
        return log_dual_softmax(scores, temperature), full_patches[:, ::row_stride]
    shifted = scaled.sub_(top)
    e = shifted.exp()
    row = e.sum(dim=-1, keepdim=True).log_()  # (N, 1)
    col = e.sum(dim=-2, keepdim=True).log_()  # (1, M)
    member = torch.zeros(patch_rows.shape[0], scores.shape[0], dtype=e.dtype, device=e.device)
    member.scatter_(1, patch_rows, 1.0)  # (K, N)
    patch_col = (member @ e).log_()  # (K, M)
    patch_rows = patch_rows[:, ::row_stride]
    k, p = patch_rows.shape
    flat = patch_rows.reshape(-1)
    patches = shifted.index_select(0, flat).view(k, p, -1)  # (K, P, M); faster than fancy indexing
    patches = patches.mul_(2).sub_(row.index_select(0, flat).view(k, p, 1)).sub_(patch_col[:, None, :])
    return shifted.mul_(2).sub_(row).sub_(col), patches


def dual_softmax(scores: torch.Tensor, temperature: float) -> torch.Tensor:
    """Confidence softmax_row(S / T) * softmax_col(S / T) over the last two dims."""
    return log_dual_softmax(scores, temperature).exp()


def mutual_nearest(confidence: torch.Tensor, threshold: float = 0.0) -> torch.Tensor:
    """Boolean mask of pairs that are each other's best match (and above `threshold`)."""
    row_best = confidence == confidence.amax(dim=-1, keepdim=True)
    col_best = confidence == confidence.amax(dim=-2, keepdim=True)
    return row_best & col_best & (confidence > threshold)


def matches_per_row(
    log_confidence: torch.Tensor, threshold: float = 0.0, mutual_only: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """For each source row: its best target column and a weight (its confidence).

    With `mutual_only` the weight is 0 unless the pair is also its column's best (mutual NN);
    otherwise every row keeps its best match, weighted by the dual-softmax confidence, which
    is already low for rows whose column prefers another row.
    Takes the LOG confidence (log_dual_softmax) so no second (N, M) matrix is materialized.
    Returns (target_index (..., N) long, weight (..., N)); a row has at most one mutual match,
    so this dense form carries every mutual-NN correspondence and batches over patches.
    """
    # max() gives argmax()'s index (the first of equal maxima) with its value, ~3x faster on CPU than
    # argmax() and a gather; the value's gradient flows to the same entry.
    best_log, index = log_confidence.max(dim=-1)  # (..., N)
    weight = best_log.exp()
    keep = weight > threshold
    if mutual_only:
        # Mutual when the row's best entry is also its column's maximum. amax over rows is a
        # contiguous reduction, ~20x faster on CPU than argmax along dim -2.
        col_max = log_confidence.detach().amax(dim=-2)  # (..., M)
        keep = keep & (best_log.detach() >= torch.gather(col_max, -1, index))
    weight = torch.where(keep, weight, torch.zeros_like(weight))
    return index, weight
