"""Closed triangle surfaces: watertightness, enclosed volume, inside/outside (winding number), and what a
tetrahedral mesher needs of one (`SurfaceMesh`)."""

from __future__ import annotations

from typing import Protocol

import numpy as np


class SurfaceMesh(Protocol):
    """A closed, outward-facing triangle surface in mm with an approximate signed distance (< 0 inside)."""

    vertices_mm: np.ndarray  # (V, 3)
    triangles: np.ndarray  # (F, 3)

    def implicit_mm(self, points_mm: np.ndarray) -> np.ndarray: ...


def edge_face_counts(triangles: np.ndarray) -> np.ndarray:
    """How many faces share each undirected edge (2 everywhere for a closed manifold surface)."""
    e = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return counts


def is_watertight(triangles: np.ndarray) -> bool:
    """Every edge shared by exactly two faces."""
    return bool(len(triangles) > 0 and np.all(edge_face_counts(triangles) == 2))


def mesh_volume_mm3(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """Signed volume by the divergence theorem (positive for outward-facing triangles)."""
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def winding_number(vertices: np.ndarray, triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Generalized winding number of a closed surface at points: ~1 inside, ~0 outside.

    Sum of signed solid angles of the triangles (Van Oosterom-Strackee formula) over 4 pi.
    """
    points = np.asarray(points, dtype=np.float64)
    out = np.zeros(len(points))
    tri = vertices[triangles]  # (F, 3, 3)
    for start in range(0, len(points), 64):
        p = points[start : start + 64]
        a, b, c = (tri[None, :, i, :] - p[:, None, :] for i in range(3))  # (P, F, 3)
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        dots = (
            la * lb * lc
            + np.einsum("pfi,pfi->pf", a, b) * lc
            + np.einsum("pfi,pfi->pf", b, c) * la
            + np.einsum("pfi,pfi->pf", c, a) * lb
        )
        out[start : start + 64] = np.arctan2(det, dots).sum(axis=1) * 2.0 / (4.0 * np.pi)
    return out
