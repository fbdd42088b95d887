"""Exact closest-point and k-nearest search over a fixed cloud: pykdtree's k-d tree, scipy's cKDTree where it is missing."""

from __future__ import annotations

import os

import numpy as np
from scipy.spatial import cKDTree

try:  # a required dependency (setup.py); a ROS workspace built without its pip step still registers
    from pykdtree.kdtree import KDTree as _FastTree
except ImportError:  # pragma: no cover - exercised only where pykdtree is not installed
    _FastTree = None

BACKEND = "pykdtree" if _FastTree is not None else "scipy"

# pykdtree answers in parallel with its own libgomp, which is not fork-safe: once a process has
# queried it, a child forked from that process (a DataLoader worker, a fork-context process pool)
# blocks forever in its first pykdtree query. Forked children therefore search with scipy: the
# same distances, bit for bit; only exact ties may name another point.
_in_forked_child = False


def _mark_forked_child() -> None:
    global _in_forked_child
    _in_forked_child = True


os.register_at_fork(after_in_child=_mark_forked_child)


class NearestIndex:
    """The closest point (or the k closest) of a fixed float64 cloud to each query point, exact.

    Why pykdtree: the ICP loops ask it ~100 times per registration for a few hundred points each,
    and it answers in about half cKDTree's time with the same pairs and the same float64
    distances (checked case by case, test_nearest). Only where two cloud points are exactly
    equally close (lattice-like synthetic clouds) may the two libraries name different ones.
    In a forked child process every index searches with scipy (see _mark_forked_child).
    """

    def __init__(self, points: np.ndarray, backend: str = BACKEND) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        if self.points.ndim != 2 or self.points.shape[1] != 3 or len(self.points) == 0:
            raise ValueError(f"NearestIndex needs a non-empty (N, 3) cloud, got shape {self.points.shape}")
        if backend not in ("pykdtree", "scipy") or (backend == "pykdtree" and _FastTree is None):
            raise ValueError(f"NearestIndex backend {backend!r} is not available; this install has {BACKEND!r}")
        self.backend = "scipy" if _in_forked_child else backend
        self._tree = _FastTree(self.points) if self.backend == "pykdtree" else cKDTree(self.points)

    def _fork_safe(self) -> None:
        """Swap an index inherited across a fork to scipy before its first search in the child."""
        if _in_forked_child and self.backend == "pykdtree":
            # the tree before the name: another thread that reads "scipy" must find a cKDTree there
            self._tree = cKDTree(self.points)
            self.backend = "scipy"

    def __reduce__(self) -> tuple:
        """Pickled as its cloud and backend (pykdtree's tree cannot be): rebuilt where it is unpickled."""
        return NearestIndex, (self.points, self.backend)

    def __len__(self) -> int:
        return len(self.points)

    def query(self, queries: np.ndarray, distance_upper_bound: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """(distances (Q,), indices (Q,) intp) of each query's closest cloud point; beyond the bound: inf and len(self)."""
        q = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
        self._fork_safe()
        if self.backend == "scipy":
            return self._tree.query(q, k=1, distance_upper_bound=distance_upper_bound)
        bound = None if np.isinf(distance_upper_bound) else float(distance_upper_bound)
        dist, idx = self._tree.query(q, k=1, distance_upper_bound=bound)
        return dist, idx.astype(np.intp)

    def query_k(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(distances (Q, k), indices (Q, k) intp) of each query's k closest cloud points, nearest first.

        The same distances as cKDTree's, bit for bit; among exactly equidistant points the order may differ.
        """
        if not 1 <= k <= len(self.points):
            raise ValueError(f"query_k needs 1 <= k <= {len(self.points)} (the cloud's size), got {k}")
        q = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
        self._fork_safe()
        if self.backend == "scipy":
            dist, idx = self._tree.query(q, k=k, workers=-1)
        else:
            dist, idx = self._tree.query(q, k=k)
        return dist.reshape(len(q), k), idx.reshape(len(q), k).astype(np.intp)
