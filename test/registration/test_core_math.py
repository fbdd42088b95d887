"""Weighted Procrustes, dual-softmax and mutual-NN matching against straightforward references."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from liver_p2p_reg.registration.matching import (
    dual_softmax,
    log_dual_softmax,
    log_dual_softmax_with_patches,
    matches_per_row,
    mutual_nearest,
    score_matrix,
)
from liver_p2p_reg.registration.procrustes import det3, to_homogeneous, weighted_procrustes


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _normalized(rng: np.random.Generator, n: int, d: int) -> torch.Tensor:
    x = torch.as_tensor(rng.normal(size=(n, d)))
    return x / x.norm(dim=1, keepdim=True)


@pytest.mark.parametrize("weighted", [False, True])
def test_procrustes_recovers_random_rigid_transforms(rng: np.random.Generator, weighted: bool) -> None:
    for _ in range(5):
        R_true, t_true = _random_rotation(rng), rng.uniform(-2, 2, 3)
        src = rng.normal(size=(50, 3))
        tgt = src @ R_true.T + t_true
        w = torch.as_tensor(rng.uniform(0.1, 1.0, 50)) if weighted else None
        R, t, ok = weighted_procrustes(torch.as_tensor(src), torch.as_tensor(tgt), w)
        assert bool(ok)
        np.testing.assert_allclose(R.numpy(), R_true, atol=1e-5)
        np.testing.assert_allclose(t.numpy(), t_true, atol=1e-5)
        assert np.linalg.det(R.numpy()) == pytest.approx(1.0, abs=1e-6)


def test_weights_select_the_consistent_subset(rng: np.random.Generator) -> None:
    """Zero-weighted outliers must not move the estimate (the weights really act)."""
    R_true, t_true = _random_rotation(rng), rng.uniform(-2, 2, 3)
    src = rng.normal(size=(40, 3))
    tgt = src @ R_true.T + t_true
    tgt[:10] += rng.normal(size=(10, 3)) * 5  # gross outliers
    w = torch.ones(40, dtype=torch.float64)
    w[:10] = 0
    R, t, ok = weighted_procrustes(torch.as_tensor(src), torch.as_tensor(tgt), w)
    assert bool(ok)
    np.testing.assert_allclose(R.numpy(), R_true, atol=1e-6)
    R_bad, _, _ = weighted_procrustes(torch.as_tensor(src), torch.as_tensor(tgt))
    assert np.abs(R_bad.numpy() - R_true).max() > 1e-2


def test_procrustes_never_returns_a_reflection(rng: np.random.Generator) -> None:
    src = rng.normal(size=(30, 3))
    mirrored = src * np.array([1.0, 1.0, -1.0])  # best orthogonal fit is a reflection
    R, _, ok = weighted_procrustes(torch.as_tensor(src), torch.as_tensor(mirrored))
    assert bool(ok)
    assert np.linalg.det(R.numpy()) == pytest.approx(1.0, abs=1e-6)


def test_cofactor_determinant_equals_lu_and_keeps_the_sign_of_rotations(rng: np.random.Generator) -> None:
    M = torch.as_tensor(rng.normal(size=(500, 3, 3)))
    torch.testing.assert_close(det3(M), torch.linalg.det(M), rtol=0, atol=1e-12)
    Q = torch.linalg.qr(M).Q.clone()  # orthogonal
    Q[::2, :, 2] *= -1  # every other one a reflection: det +-1, both signs
    assert torch.equal(torch.sign(det3(Q)), torch.sign(torch.linalg.det(Q)))
    assert set(torch.sign(det3(Q)).tolist()) == {-1.0, 1.0}


def test_batched_equals_looped(rng: np.random.Generator) -> None:
    B, N = 6, 40
    src = torch.as_tensor(rng.normal(size=(B, N, 3)))
    tgt = torch.as_tensor(rng.normal(size=(B, N, 3)))  # arbitrary (not rigid) pairs
    w = torch.as_tensor(rng.uniform(0, 1, size=(B, N)))
    R, t, ok = weighted_procrustes(src, tgt, w)
    for b in range(B):
        Rb, tb, okb = weighted_procrustes(src[b], tgt[b], w[b])
        assert bool(okb) == bool(ok[b])
        np.testing.assert_allclose(R[b].numpy(), Rb.numpy(), atol=1e-10)
        np.testing.assert_allclose(t[b].numpy(), tb.numpy(), atol=1e-10)
    T = to_homogeneous(R, t)
    assert T.shape == (B, 4, 4)
    np.testing.assert_allclose(T[:, 3].numpy(), np.tile([0, 0, 0, 1.0], (B, 1)))


def test_degenerate_inputs_report_failure(rng: np.random.Generator) -> None:
    src = torch.as_tensor(rng.normal(size=(20, 3)))
    tgt = src + 1.0
    two = torch.zeros(20, dtype=torch.float64)
    two[:2] = 1.0  # only two usable correspondences
    line = torch.as_tensor(np.outer(np.linspace(-1, 1, 20), [1.0, 2.0, 3.0]))  # collinear
    zero = torch.zeros(20, dtype=torch.float64)
    batch_src = torch.stack([src, src, line, src])
    batch_tgt = torch.stack([tgt, tgt, line + 1.0, tgt])
    weights = torch.stack([torch.ones(20, dtype=torch.float64), two, torch.ones(20, dtype=torch.float64), zero])
    R, t, ok = weighted_procrustes(batch_src, batch_tgt, weights)
    assert ok.tolist() == [True, False, False, False]
    assert torch.isfinite(R).all() and torch.isfinite(t).all()  # failures carry no NaN garbage
    np.testing.assert_allclose(R[0].numpy(), np.eye(3), atol=1e-8)
    np.testing.assert_allclose(t[0].numpy(), np.ones(3), atol=1e-8)


def _reference_dual_softmax(S: np.ndarray, temperature: float) -> np.ndarray:
    out = np.zeros_like(S)
    for i in range(S.shape[0]):
        for j in range(S.shape[1]):
            row = np.exp(S[i] / temperature).sum()
            col = np.exp(S[:, j] / temperature).sum()
            e = np.exp(S[i, j] / temperature)
            out[i, j] = (e / row) * (e / col)
    return out


@pytest.mark.parametrize("temperature", [0.1, 0.5, 0.01])
def test_dual_softmax_matches_reference(rng: np.random.Generator, temperature: float) -> None:
    xs, xt = _normalized(rng, 30, 8), _normalized(rng, 20, 8)
    S = score_matrix(xs, xt)
    np.testing.assert_allclose(S.numpy(), xs.numpy() @ xt.numpy().T, atol=1e-12)
    conf = dual_softmax(S, temperature).numpy()
    if temperature >= 0.1:  # the plain reference overflows for tiny temperatures
        np.testing.assert_allclose(conf, _reference_dual_softmax(S.numpy(), temperature), rtol=1e-9, atol=1e-300)
    # Both paths (shared exponential, per-axis logsumexp) agree with softmax * softmax.
    direct = torch.softmax(S / temperature, dim=1) * torch.softmax(S / temperature, dim=0)
    np.testing.assert_allclose(conf, direct.numpy(), rtol=1e-6, atol=1e-300)
    np.testing.assert_allclose(log_dual_softmax(S, temperature).exp().numpy(), conf, rtol=1e-12)


def _reference_mutual(conf: np.ndarray, threshold: float) -> set[tuple[int, int]]:
    pairs = set()
    for i in range(conf.shape[0]):
        j = int(np.argmax(conf[i]))
        if int(np.argmax(conf[:, j])) == i and conf[i, j] > threshold:
            pairs.add((i, j))
    return pairs


@pytest.mark.parametrize("threshold", [0.0, 0.05])
def test_mutual_nearest_matches_reference(rng: np.random.Generator, threshold: float) -> None:
    xs, xt = _normalized(rng, 40, 6), _normalized(rng, 25, 6)
    S = score_matrix(xs, xt)
    conf = dual_softmax(S, 0.1)
    expected = _reference_mutual(conf.numpy(), threshold)
    assert len(expected) > 3  # the test compares something
    mask = mutual_nearest(conf, threshold)
    assert {tuple(p) for p in torch.nonzero(mask).tolist()} == expected
    index, weight = matches_per_row(log_dual_softmax(S, 0.1), threshold)
    got = {(i, int(index[i])) for i in range(len(index)) if weight[i] > 0}
    assert got == expected
    for i, j in expected:
        assert float(weight[i]) == pytest.approx(float(conf[i, j]), rel=1e-9)


def test_row_best_matching_keeps_every_row_with_its_confidence(rng: np.random.Generator) -> None:
    S = score_matrix(_normalized(rng, 40, 6), _normalized(rng, 25, 6))
    conf = dual_softmax(S, 0.1).numpy()
    index, weight = matches_per_row(log_dual_softmax(S, 0.1), 0.0, mutual_only=False)
    np.testing.assert_array_equal(index.numpy(), conf.argmax(axis=1))
    np.testing.assert_allclose(weight.numpy(), conf.max(axis=1), rtol=1e-9)
    # the mutual pairs are a strict subset: rows that are not mutual keep a (small) weight
    _, mutual_weight = matches_per_row(log_dual_softmax(S, 0.1), 0.0, mutual_only=True)
    assert int((mutual_weight > 0).sum()) < int((weight > 0).sum()) == 40


def test_matching_batches_over_patches(rng: np.random.Generator) -> None:
    S = score_matrix(_normalized(rng, 3 * 20, 6), _normalized(rng, 15, 6)).reshape(3, 20, 15)
    index, weight = matches_per_row(log_dual_softmax(S, 0.1))
    for k in range(3):
        ik, wk = matches_per_row(log_dual_softmax(S[k], 0.1))
        assert torch.equal(index[k], ik)
        np.testing.assert_allclose(weight[k].numpy(), wk.numpy(), rtol=1e-12)


def test_dual_softmax_gradient_equals_the_plain_formula(rng: np.random.Generator) -> None:
    S = torch.tensor(rng.uniform(-1, 1, size=(2, 12, 9)), requires_grad=True)
    g = torch.as_tensor(rng.normal(size=(2, 12, 9)))
    (log_dual_softmax(S, 0.2) * g).sum().backward()
    fast = S.grad.clone()
    S.grad = None
    plain = torch.log(torch.softmax(S / 0.2, dim=-1) * torch.softmax(S / 0.2, dim=-2))
    (plain * g).sum().backward()
    np.testing.assert_allclose(fast.numpy(), S.grad.numpy(), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("temperature", [0.1, 0.005])  # shared-exponential path and its fallback
def test_patch_dual_softmax_equals_per_patch_computation(rng: np.random.Generator, temperature: float) -> None:
    S = score_matrix(_normalized(rng, 50, 6), _normalized(rng, 12, 6))
    patch_rows = torch.as_tensor(np.stack([rng.choice(50, 12, replace=False) for _ in range(4)]))
    full, patches = log_dual_softmax_with_patches(S.clone(), patch_rows, temperature)
    np.testing.assert_allclose(full.numpy(), log_dual_softmax(S, temperature).numpy(), rtol=1e-10, atol=1e-9)
    for k in range(4):
        expected = log_dual_softmax(S[patch_rows[k]], temperature)
        np.testing.assert_allclose(patches[k].numpy(), expected.numpy(), rtol=1e-10, atol=1e-9)
    # A row stride returns exactly those rows of each patch (column sums still over the whole patch).
    _, strided = log_dual_softmax_with_patches(S.clone(), patch_rows, temperature, row_stride=5)
    assert strided.shape == (4, 3, 12)
    np.testing.assert_allclose(strided.numpy(), patches[:, ::5].numpy(), rtol=1e-10, atol=1e-9)


def test_statistical_inliers_drop_flying_pixels_and_keep_the_surface(rng: np.random.Generator) -> None:
    from liver_p2p_reg.registration.preprocess import statistical_inliers

    u, v = rng.uniform(0, 100, (2, 4000))
    surface = np.stack([u, v, 0.002 * (u - 50) ** 2], axis=1)  # a gently curved 100 mm patch
    off_mm = rng.uniform(10, 40, (100, 1)) * rng.choice([-1.0, 1.0], (100, 1))
    flying = surface[:100] + off_mm * [0, 0, 1]  # 10-40 mm off the surface along the ray
    keep = statistical_inliers(np.vstack([surface, flying]), neighbors=20, std_ratio=2.0)
    assert keep[:4000].mean() > 0.95  # the surface stays
    assert keep[4000:].mean() < 0.2  # most flying pixels go
    assert statistical_inliers(surface[:3], 20, 2.0).all()  # too small to judge: keep all
    assert statistical_inliers(surface, 20, 0.0).all()  # disabled


def _voxel_means_reference(points: np.ndarray, voxel: float) -> np.ndarray:
    """Per-cell means by a dict, sorted by cell: what voxel_downsample must return."""
    cells: dict[tuple, list] = {}
    for p in points:
        cells.setdefault(tuple(np.floor(p / voxel).astype(np.int64)), []).append(p)
    return np.array([np.mean(cells[c], axis=0) for c in sorted(cells)])


@pytest.mark.parametrize("voxel", [0.04, 0.3, 1e-3])
def test_voxel_downsample_equals_per_cell_means(rng: np.random.Generator, voxel: float) -> None:
    from liver_p2p_reg.registration.preprocess import voxel_downsample

    points = rng.normal(size=(3000, 3)) * [1.0, 0.5, 0.2]
    np.testing.assert_allclose(voxel_downsample(points, voxel), _voxel_means_reference(points, voxel), atol=1e-12)


def test_voxel_downsample_survives_cells_too_far_apart_for_one_int64_key() -> None:
    """A far outlier (e.g. a flying pixel in metres among millimetres) must not merge cells."""
    from liver_p2p_reg.registration.preprocess import voxel_downsample
    from liver_p2p_reg.registration.visibility import count_voxels

    points = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [5.1, 0.0, 0.0], [5.3, 0.0, 0.0], [3e7, -3e7, 3e7]])
    out = voxel_downsample(points, 1.0)  # spans ~(3e7)^3 cells: more than an int64 key can number
    np.testing.assert_allclose(out, [[0.2, 0.2, 0.2], [5.2, 0.0, 0.0], [3e7, -3e7, 3e7]])
    assert count_voxels(points, 1.0) == 3


def test_icp_cross_product_has_np_cross_bits(rng: np.random.Generator) -> None:
    from liver_p2p_reg.registration.refine import cross_rows

    for n in (1, 5, 400):
        a, b = rng.normal(size=(n, 3)) * 30.0, rng.normal(size=(n, 3))
        assert cross_rows(a, b).tobytes() == np.cross(a, b).tobytes()  # ICP's poses stay bit for bit what they were
    assert np.array_equal(cross_rows(np.eye(3), np.roll(np.eye(3), -1, axis=0)), np.roll(np.eye(3), -2, axis=0))


def test_row_best_matching_has_argmax_bits_and_first_of_ties(rng: np.random.Generator) -> None:
    # max() replaced argmax() + gather(): the same index (the first of equal maxima) and the same value
    log_conf = torch.tensor(rng.normal(size=(3, 50, 30)), dtype=torch.float32)
    log_conf[0, 0, [4, 9]] = 10.0  # a tie in one row
    index, weight = matches_per_row(log_conf, 0.0, mutual_only=False)
    expected = log_conf.argmax(dim=-1)
    assert torch.equal(index, expected) and int(index[0, 0]) == 4
    assert weight.numpy().tobytes() == torch.gather(log_conf, -1, expected[..., None])[..., 0].exp().numpy().tobytes()


def test_farthest_points_has_the_plain_formula_bits(rng: np.random.Generator) -> None:
    from liver_p2p_reg.registration.features.learned.model import farthest_points

    def plain(pts: np.ndarray, k: int) -> list[int]:
        chosen, dist = [0], ((pts - pts[0]) ** 2).sum(axis=1)
        for _ in range(1, k):
            chosen.append(int(np.argmax(dist)))
            np.minimum(dist, ((pts - pts[chosen[-1]]) ** 2).sum(axis=1), out=dist)
        return chosen

    for n, k in ((5, 8), (300, 40), (2000, 250)):
        pts = rng.normal(size=(n, 3)) * rng.uniform(0.1, 10.0)
        assert farthest_points(torch.from_numpy(pts), k).tolist() == plain(pts, min(k, n))
