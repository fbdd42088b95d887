"""Synthetic liver-sized cases shared by the core and command-line tests: a lumpy blob and a moved crop of it, and
benchmark case files of deformed ellipsoids."""

from __future__ import annotations

from pathlib import Path

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


def crop(source: np.ndarray, share: float) -> tuple[np.ndarray, np.ndarray]:
    """(indices, centre): the `share` of the source's points nearest one end of the blob, a view's patch."""
    centre = source[np.argmax(source[:, 0] + 0.5 * source[:, 2])]
    return np.argsort(np.linalg.norm(source - centre, axis=1))[: int(share * len(source))], centre


def partial_case(rng: np.random.Generator, share: float = 0.35):
    """(source, target, T_true, source fiducials, target fiducials): a moved crop of the blob."""
    source = blob_mm(rng)
    keep, _ = crop(source, share)
    T = rigid(rng)
    target = transform_points(T, source[keep])
    fid_s = source[::300] * 0.8 + 0.2 * source.mean(axis=0)  # points inside the surface
    return source, target, T, fid_s, transform_points(T, fid_s)


def _fibonacci_ellipsoid(n: int, radii_mm: np.ndarray) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    unit = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)
    return unit * radii_mm


def _deform(points_mm: np.ndarray, amplitude_mm: float) -> np.ndarray:
    # A smooth, non-rigid displacement field so the oracle cannot reach zero error.
    x, y, z = points_mm.T
    disp = np.stack([np.sin(y / 25.0), np.cos(z / 30.0), np.sin(x / 20.0)], axis=1)
    return points_mm + amplitude_mm * disp


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def write_cases(folder: Path, per_bin: int = 2, seed: int = 7) -> list[Path]:
    """`per_bin` cases in each visibility bin [0.2,0.3) ... [0.9,1.0]: ellipsoid, deformation, crop, rigid motion."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    paths = []
    for b, lo in enumerate(np.arange(0.2, 0.95, 0.1)):
        for j in range(per_bin):
            radii = np.array([90.0, 65.0, 45.0]) * rng.uniform(0.9, 1.1, 3)
            source = _fibonacci_ellipsoid(700, radii)
            markers = rng.uniform(-0.5, 0.5, size=(40, 3)) * radii
            amplitude = rng.uniform(1.0, 10.0)
            deformed, deformed_markers = _deform(source, amplitude), _deform(markers, amplitude)
            visibility = float(lo + rng.uniform(0.01, 0.09))
            # A contiguous crop: the target points closest to a random surface point.
            seed_point = deformed[rng.integers(len(deformed))]
            keep = np.argsort(np.linalg.norm(deformed - seed_point, axis=1))[: int(round(visibility * len(deformed)))]
            R, t = _rotation(rng), rng.uniform(-100, 100, 3)
            case = {
                "src_pcd": source,
                "tgt_pcd": deformed[keep] @ R.T + t,
                "src_marker": markers,
                "tgt_marker": deformed_markers @ R.T + t,
                "R_gt": R,
                "t_gt": t,
                "visibility": visibility,
                "deformation_rms_mm": float(np.sqrt(np.mean(np.sum((deformed_markers - markers) ** 2, axis=1)))),
                "noise_mm": 0.0,
                "crop_mode": "random",
                "liver_id": b,
                "seed": 1000 + 10 * b + j,
            }
            path = folder / f"case_{b}_{j}.npz"
            np.savez(path, **case)
            paths.append(path)
    return paths
