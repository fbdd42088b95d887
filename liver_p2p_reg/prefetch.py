"""Outward normals of a cloud computed in a child process, so a one-shot command imports torch meanwhile.

A `liver-p2p register` process spends most of its time importing torch (for the matcher) and
Open3D (for the ICP's source normals), one after the other on one core. The normals depend
only on the source, so the command starts a child that imports Open3D and computes them with
the very same function (`features.fpfh.outward_normals`) while this process imports torch;
`outward_normals` then takes the child's result for exactly those points. Same function, same
input bits: the same normals. If the child fails, the normals are computed here as before.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

PACKAGE_PARENT = str(Path(__file__).resolve().parents[1])
# The child: read the points, compute the normals with the package's own function, write them.
CHILD = """import sys
sys.path.insert(0, sys.argv[1])
import numpy as np
from liver_p2p_reg.registration.features.fpfh import outward_normals
points = np.load(sys.argv[2])
np.save(sys.argv[3], outward_normals(points, float(sys.argv[4]), int(sys.argv[5])))
"""
_PENDING: list[BackgroundNormals] = []


class BackgroundNormals:
    """`outward_normals(points, radius, max_nn)` being computed by a child process."""

    def __init__(self, points: np.ndarray, radius: float, max_nn: int = 30) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.radius, self.max_nn = float(radius), int(max_nn)
        self.folder = Path(tempfile.mkdtemp(prefix="liver_p2p_normals_"))
        np.save(self.folder / "points.npy", self.points)
        args = [PACKAGE_PARENT, str(self.folder / "points.npy"), str(self.folder / "normals.npy")]
        self.child = subprocess.Popen(
            [sys.executable, "-c", CHILD, *args, repr(self.radius), str(self.max_nn)],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        _PENDING.append(self)

    def matches(self, points: np.ndarray, radius: float, max_nn: int) -> bool:
        points = np.asarray(points)
        return (
            (radius, max_nn) == (self.radius, self.max_nn)
            and points.shape == self.points.shape
            and points.dtype == np.float64
            and np.ascontiguousarray(points).tobytes() == self.points.tobytes()
        )

    def result(self) -> np.ndarray | None:
        """The child's normals (waits for it), or None when it failed."""
        try:
            if self.child.wait() != 0:
                return None
            normals = np.load(self.folder / "normals.npy")
        except (OSError, ValueError):
            return None
        finally:
            self.close()
        return normals if normals.shape == self.points.shape else None

    def close(self) -> None:
        """Stop the child if it still runs and remove its files (idempotent)."""
        if self.child.poll() is None:
            self.child.kill()
            self.child.wait()
        shutil.rmtree(self.folder, ignore_errors=True)
        if self in _PENDING:
            _PENDING.remove(self)


def take_prefetched(points: np.ndarray, radius: float, max_nn: int) -> np.ndarray | None:
    """The normals a child computed for exactly these points and parameters, else None."""
    for job in list(_PENDING):
        if job.matches(points, radius, max_nn):
            return job.result()
    return None
