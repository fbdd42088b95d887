"""Outward normals of a cloud computed in a child process, so a one-shot command imports torch meanwhile.

A `liver-p2p register` process spends most of its time importing torch (for the matcher) and
Open3D (for the ICP's source normals), one after the other on one core. The normals depend
only on the source, so the command starts a child that imports Open3D and computes them with
the very same function (`features.fpfh.outward_normals`) while this process imports torch;
`outward_normals` then takes the child's result for exactly those points. Same function, same
input bits: the same normals. If the child fails, the normals are computed here as before.

`normals_in_child` is the blocking form, for large clouds: Open3D's normal estimation holds the GIL
(1.5 s for 300 k points), which would stall a node's signal handling and callbacks; waiting on a child's
pipe does not.
"""

from __future__ import annotations

import io
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

PACKAGE_PARENT = str(Path(__file__).resolve().parents[1])
# The child: read the points (a file, or "-": stdin), compute the normals with the package's own function (in
# this process: no grandchild), write them (a file, or "-": stdout). On Linux it dies with the thread that
# started it, so a node stopped mid-warm-up leaves no orphan computing on.
CHILD = """import ctypes, io, sys
try:
    ctypes.CDLL(None).prctl(1, 9)  # PR_SET_PDEATHSIG, SIGKILL
except (OSError, AttributeError):
    pass
sys.path.insert(0, sys.argv[1])
import numpy as np
from liver_p2p_reg.registration.features.fpfh import local_outward_normals
src = io.BytesIO(sys.stdin.buffer.read()) if sys.argv[2] == "-" else sys.argv[2]
normals = local_outward_normals(np.load(src), float(sys.argv[4]), int(sys.argv[5]))
if sys.argv[3] == "-":
    out = io.BytesIO()
    np.save(out, normals)
    sys.stdout.buffer.write(out.getvalue())
else:
    np.save(sys.argv[3], normals)
"""
_PENDING: list[BackgroundNormals] = []


def child_command(points_in: str | Path, normals_out: str | Path, radius: float, max_nn: int) -> list[str]:
    """The command line of a CHILD reading `points_in` and writing `normals_out` ("-": stdin / stdout)."""
    return [
        sys.executable,
        "-c",
        CHILD,
        PACKAGE_PARENT,
        str(points_in),
        str(normals_out),
        repr(float(radius)),
        str(int(max_nn)),
    ]


class BackgroundNormals:
    """`outward_normals(points, radius, max_nn)` being computed by a child process."""

    def __init__(self, points: np.ndarray, radius: float, max_nn: int = 30) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.radius, self.max_nn = float(radius), int(max_nn)
        self.folder = Path(tempfile.mkdtemp(prefix="liver_p2p_normals_"))
        np.save(self.folder / "points.npy", self.points)
        self.child = subprocess.Popen(
            child_command(self.folder / "points.npy", self.folder / "normals.npy", self.radius, self.max_nn),
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


def normals_in_child(points: np.ndarray, radius: float, max_nn: int = 30) -> np.ndarray | None:
    """`outward_normals(points, radius, max_nn)` computed by a child process and waited for here without
    holding the GIL (through pipes, no files); None when the child fails."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    sent = io.BytesIO()
    np.save(sent, points)
    try:
        done = subprocess.run(
            child_command("-", "-", radius, max_nn), input=sent.getvalue(), capture_output=True, check=False
        )
        normals = np.load(io.BytesIO(done.stdout)) if done.returncode == 0 else None
    except (OSError, ValueError):
        return None
    return normals if normals is not None and normals.shape == points.shape else None
