"""Synthetic liver-sized cases shared by the core and command-line tests: a lumpy blob and a moved crop of it."""

from __future__ import annotations

import numpy as np

from liver_p2p_reg.metrics import transform_points


def blob_mm(rng: np.random.Generator, n: int = 15000) -> np.ndarray:
    """An asymmetric lumpy ellipsoid surface about 200 mm long (liver-sized)."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = 1 + 0.2 * np.sin(3 * d[:, 0] + 1) * np.cos(2 * d[:, 1]) + 0.15 * d[:, 2] ** 3 + 0.1 * d[:, 0] * d[:, 1]
    return d * r[:, None] * np.array([100.0, 75.0, 55.0]) + np.array([10.0, -200.0, 40.0])


def rigid(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = q * np.sign(np.linalg.det(q)), rng.uniform(-100, 100, 3)
    return T


def partial_case(rng: np.random.Generator, share: float = 0.35):
    """(source, target, T_true, source fiducials, target fiducials): a moved crop of the blob."""
    source = blob_mm(rng)
    centre = source[np.argmax(source[:, 0] + 0.5 * source[:, 2])]
    keep = np.argsort(np.linalg.norm(source - centre, axis=1))[: int(share * len(source))]
    T = rigid(rng)
    target = transform_points(T, source[keep])
    fid_s = source[::300] * 0.8 + 0.2 * source.mean(axis=0)  # points inside the surface
    return source, target, T, fid_s, transform_points(T, fid_s)
