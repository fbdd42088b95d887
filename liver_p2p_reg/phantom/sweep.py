"""A laparoscope sweeping over the anterior liver surface: one camera pose and visible-point set per frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from liver_p2p_reg.phantom.crop import camera_axes, visible_from


@dataclass
class SweepFrame:
    """One frame of a sweep: which surface points the camera sees, and where it stands (mm, liver frame)."""

    visible: np.ndarray  # indices into the swept points, nearest the optical axis first
    eye_mm: np.ndarray  # (3,)
    axes: np.ndarray  # (3, 3) columns x, y, z of the camera; camera coordinates = (p - eye) @ axes


def sweep_path(
    points: np.ndarray,
    normals: np.ndarray,
    n_frames: int,
    rng: np.random.Generator,
    distance_mm: tuple[float, float] = (88.0, 108.0),
    lateral_tilt: float = 0.7,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """(eye, unit viewing direction) per frame: a pass from one side of the anterior surface to the other.

    The camera aims at anterior surface points along a left-right pass that wanders up and down,
    tilting its axis towards the side it is over (so the union covers the flanks too), at a
    slowly varying distance: what a surgeon surveying the liver through one port does.
    """
    anterior = np.flatnonzero(normals[:, 1] > 0.3)
    if len(anterior) == 0:
        anterior = np.arange(len(points))
    front = points[anterior]
    x_lo, x_hi = np.percentile(front[:, 0], [8, 92])
    z_lo, z_hi = np.percentile(front[:, 2], [20, 80])
    phase = rng.uniform(0, 2 * np.pi, size=2)
    s = np.linspace(0.0, 1.0, n_frames)
    x = x_lo + (x_hi - x_lo) * s
    z = 0.5 * (z_lo + z_hi) + 0.5 * (z_hi - z_lo) * np.sin(2 * np.pi * 1.5 * s + phase[0])
    distance = np.mean(distance_mm) + 0.5 * np.ptp(distance_mm) * np.sin(2 * np.pi * s + phase[1])
    path = []
    for xi, zi, di in zip(x, z, distance, strict=True):
        # the front-most anterior point under the path's (x, z): the surface the camera aims at
        near = np.argsort(np.hypot(front[:, 0] - xi, front[:, 2] - zi))[:20]
        look_at = front[near[np.argmax(front[near, 1])]]
        side = (xi - 0.5 * (x_lo + x_hi)) / (0.5 * (x_hi - x_lo))
        view = np.array([lateral_tilt * side, 1.0, 0.35 * (zi - 0.5 * (z_lo + z_hi)) / (0.5 * (z_hi - z_lo) + 1e-9)])
        view /= np.linalg.norm(view)
        path.append((look_at + di * view, -view))
    return path


def sweep_frames(
    points: np.ndarray, normals: np.ndarray, n_frames: int, rng: np.random.Generator, **path_options: float
) -> list[SweepFrame]:
    """The camera's view of `points` (a dense sample of the liver surface, mm) at each pose of `sweep_path`."""
    frames = []
    for eye, z_axis in sweep_path(points, normals, n_frames, rng, **path_options):
        frames.append(SweepFrame(visible_from(points, eye, z_axis), eye, camera_axes(z_axis)))
    return frames
