"""Rotation- and translation-invariant local geometric input features per point (float64)."""

from __future__ import annotations

import numpy as np

from liver_p2p_reg.registration.nearest import NearestIndex

# Gaussian neighbourhood scales in normalized units (voxel 0.04): fine, medium, coarse.
SCALES_NORM = (0.05, 0.09, 0.16)
NEIGHBOURS = 64  # kNN support of every scale (radius ~0.18 at voxel 0.04: the coarse window)
FEATURES_PER_SCALE = 8
NUM_FEATURES = FEATURES_PER_SCALE * len(SCALES_NORM) + 2


def local_features(points: np.ndarray, scales: tuple[float, ...] = SCALES_NORM) -> np.ndarray:
    """(N, 3) points -> (N, NUM_FEATURES) invariant features.

    Only distances, covariance eigenvalues and sign-resolved normal offsets enter, so the
    result is unchanged (to float64 rounding) by any rotation + translation of the input.
    Normals are oriented away from the cloud's own centroid (an equivariant point).
    """
    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    k = min(NEIGHBOURS, n)
    dist, idx = NearestIndex(pts).query_k(pts, k)
    # take() and einsum() at about half the time of fancy indexing and a broadcast product; the features are
    # the same bits (einsum writes +0.0 where the product is -0.0, which the sums below cannot tell apart).
    offs = np.take(pts, idx, axis=0) - pts[:, None, :]  # (N, k, 3) neighbour offsets
    # Second moments once for all scales: each scale is then one weighted sum (a matmul).
    outer = np.einsum("nki,nkj->nkij", offs, offs).reshape(n, k, 9)
    outward = pts - pts.mean(axis=0)
    feats = []
    normals = []
    for sigma in scales:
        w = np.exp(-0.5 * (dist / sigma) ** 2)
        wsum = w.sum(axis=1, keepdims=True)
        wn = (w / wsum)[:, None, :]  # (N, 1, k)
        mean_off = np.matmul(wn, offs)[:, 0]  # centroid - point
        second = np.matmul(wn, outer)[:, 0].reshape(n, 3, 3)
        cov = second - mean_off[:, :, None] * mean_off[:, None, :]
        evals, evecs = np.linalg.eigh(cov)  # ascending
        evals = np.clip(evals, 0.0, None)
        total = evals.sum(axis=1) + 1e-12
        normal = evecs[:, :, 0]
        sign = np.where(np.einsum("nc,nc->n", normal, outward) < 0, -1.0, 1.0)
        normal = normal * sign[:, None]
        normals.append(normal)
        offset = -mean_off  # point - centroid
        feats += [
            evals[:, 2] / total,
            evals[:, 1] / total,
            evals[:, 0] / total,  # surface variation (curvature proxy)
            np.log(np.sqrt(total) / sigma + 1e-6),
            np.linalg.norm(offset, axis=1) / sigma,
            np.einsum("nc,nc->n", offset, normal) / sigma,  # signed: convex vs concave
            np.log(wsum[:, 0] / (sigma / 0.04) ** 2 + 1e-6),  # density drops at the crop border
            (evals[:, 2] - evals[:, 1]) / (evals[:, 2] + 1e-12),  # linearity: ridge / border
        ]
    feats.append(np.abs(np.einsum("nc,nc->n", normals[0], normals[1])))
    feats.append(np.abs(np.einsum("nc,nc->n", normals[1], normals[2])))
    return np.stack(feats, axis=1)
