"""The learned matcher's descriptors are invariant to rotation + translation of either input."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from liver_p2p_reg.registration.features.learned.descriptors import NUM_FEATURES, local_features
from liver_p2p_reg.registration.features.learned.model import MatcherNet, ModelConfig


def _surface(n: int, rng: np.random.Generator) -> np.ndarray:
    """A bumpy ellipsoid surface (no symmetry), roughly inside the unit sphere."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = 1.0 + 0.15 * np.sin(3 * d[:, 0]) * np.cos(2 * d[:, 1]) + 0.1 * d[:, 2] ** 2
    return d * r[:, None] * np.array([0.9, 0.6, 0.45])


def _describe(net: MatcherNet, src: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    f_s = torch.as_tensor(local_features(src), dtype=torch.float32)
    f_t = torch.as_tensor(local_features(tgt), dtype=torch.float32)
    with torch.no_grad():
        xs, xt, _, _ = net(torch.as_tensor(src), torch.as_tensor(tgt), f_s, f_t)
    return xs.numpy(), xt.numpy()


def test_input_features_are_invariant(rng: np.random.Generator) -> None:
    pts = _surface(400, rng)
    moved = pts @ Rotation.random(random_state=3).as_matrix().T + np.array([5.0, -2.0, 7.0])
    a, b = local_features(pts), local_features(moved)
    assert a.shape == (400, NUM_FEATURES)
    assert np.isfinite(a).all()
    np.testing.assert_allclose(a, b, atol=1e-9)
    assert a.std(axis=0)[:6].min() > 1e-4  # the features actually vary over the surface


def test_descriptors_invariant_to_rotation_of_either_input(rng: np.random.Generator) -> None:
    torch.manual_seed(0)
    net = MatcherNet(ModelConfig()).eval()
    src = _surface(600, rng)
    tgt = src[src[:, 0] > 0.2] + rng.normal(scale=0.005, size=(int((src[:, 0] > 0.2).sum()), 3))
    xs, xt = _describe(net, src, tgt)
    for seed in range(3):
        R_s, R_t = Rotation.random(2, random_state=seed).as_matrix()
        xs2, xt2 = _describe(net, src @ R_s.T + rng.normal(size=3), tgt @ R_t.T + rng.normal(size=3))
        np.testing.assert_allclose(xs2, xs, atol=1e-4)
        np.testing.assert_allclose(xt2, xt, atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(xs, axis=1), 1.0, atol=1e-5)
    # Not trivially invariant: the descriptors differ between points and depend on the other cloud.
    assert np.abs(xs - xs.mean(axis=0)).max() > 1e-2
    xs_other, _ = _describe(net, src, tgt[: len(tgt) // 2])
    assert np.abs(xs_other - xs).max() > 1e-4


def test_inference_pooling_equals_the_training_pooling_exactly(rng: np.random.Generator) -> None:
    # Inference max-pools onto the nodes with index_reduce, training with scatter_reduce (its gradients).
    torch.manual_seed(1)
    net = MatcherNet(ModelConfig(width=16, heads=2, layers=1, out_dim=8, max_nodes=32)).eval()
    src = torch.as_tensor(_surface(300, rng))
    features = torch.as_tensor(local_features(src.numpy()), dtype=torch.float32)
    h = net.embed(features).detach()
    _, pooled_train, _ = net._nodes(src, h)
    with torch.no_grad():
        _, pooled_infer, _ = net._nodes(src, h)
    assert torch.equal(pooled_train.detach(), pooled_infer)
    assert (pooled_infer > -1e3).all()  # every node owns points: the maxima are real, not the fill value
