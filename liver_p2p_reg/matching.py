"""Feature matching: score matrix, dual-softmax confidence, mutual nearest neighbours."""

from __future__ import annotations

import torch


def score_matrix(x_source: torch.Tensor, x_target: torch.Tensor) -> torch.Tensor:
    """S = x_S x_T^T for L2-normalized features: (..., N, d) x (M, d) -> (..., N, M)."""
    return x_source @ x_target.transpose(-1, -2)


def dual_softmax(scores: torch.Tensor, temperature: float) -> torch.Tensor:
    """Confidence softmax_row(S / T) * softmax_col(S / T) over the last two dims."""
    scaled = scores / temperature
    return torch.softmax(scaled, dim=-1) * torch.softmax(scaled, dim=-2)


def mutual_nearest(confidence: torch.Tensor, threshold: float = 0.0) -> torch.Tensor:
    """Boolean mask of pairs that are each other's best match (and above `threshold`)."""
    row_best = confidence == confidence.amax(dim=-1, keepdim=True)
    col_best = confidence == confidence.amax(dim=-2, keepdim=True)
    return row_best & col_best & (confidence > threshold)


def matches_per_row(confidence: torch.Tensor, threshold: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """For each source row: its best target column and a weight (confidence if mutual, else 0).

    Returns (target_index (..., N) long, weight (..., N)); a row has at most one mutual match,
    so this dense form carries every mutual-NN correspondence and batches over patches.
    """
    mask = mutual_nearest(confidence, threshold)
    weight_matrix = confidence * mask
    weight, index = weight_matrix.max(dim=-1)
    return index, weight
