"""OFF reading in numpy, checked: counts the body holds, vertices of 3 numbers, faces of existing vertices.

Open3D's OFF reader crashed the process (segmentation fault) on a face of no index, took a negative index as a
vertex counted from the end, gave no points for a file of vertices alone and refused counts on the OFF line. This
reader gives Open3D's triangles, the vertices in full precision (Open3D parses them as float32), polygons split into
fans from their first vertex (Open3D ear-clips them: the same surface for a planar convex polygon; it fails on
others), and a one-line InputError for malformed files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from liver_p2p_reg.errors import InputError

# OFF with optional per-vertex texture, colour and normal columns (the first three numbers are x, y, z)
KEYWORDS = ("OFF", "COFF", "NOFF", "CNOFF", "STOFF", "STCOFF", "STNOFF", "STCNOFF")


def read_off(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, triangles (F, 3) int64) of a 3D OFF file; InputError unless it is well formed."""
    lines = []
    for raw in path.read_bytes().decode("latin-1").splitlines():
        words = raw.split("#", 1)[0].split()
        if words:
            lines.append(words)
    if not lines or lines[0][0] not in KEYWORDS:
        raise InputError(f"cannot read {path}: not an OFF file (it does not start with 'OFF')")
    head = lines[0][1:] or (lines[1] if len(lines) > 1 else [])
    rest = lines[1:] if lines[0][1:] else lines[2:]
    try:
        n_vertices, n_faces = int(head[0]), int(head[1])
    except (ValueError, IndexError):
        raise InputError(f"cannot read {path}: its OFF header has no vertex and face counts") from None
    if n_vertices < 0 or n_faces < 0:
        raise InputError(f"cannot read {path}: its OFF header declares {n_vertices} vertices and {n_faces} faces")
    if len(rest) < n_vertices + n_faces:
        held = max(len(rest) - n_vertices, 0)
        what = f"{n_faces} faces, the file holds {held}" if len(rest) >= n_vertices else f"{n_vertices} vertices"
        raise InputError(f"cannot read {path}: truncated: its header declares {what}")
    try:
        vertices = np.array([[float(w) for w in row[:3]] for row in rest[:n_vertices]], dtype=np.float64)
    except ValueError as exc:
        raise InputError(f"cannot read {path}: a vertex is not numbers ({exc})") from None
    if n_vertices and vertices.shape != (n_vertices, 3):
        raise InputError(f"cannot read {path}: a vertex has fewer than 3 coordinates")
    triangles = []
    for index, row in enumerate(rest[n_vertices : n_vertices + n_faces]):
        face = _face(path, index, row, n_vertices)
        triangles += [(face[0], face[i], face[i + 1]) for i in range(1, len(face) - 1)]
    return vertices.reshape(-1, 3), np.array(triangles, dtype=np.int64).reshape(-1, 3)


def _face(path: Path, index: int, row: list[str], n_vertices: int) -> list[int]:
    """The indices of a face row `n i_1 .. i_n [colour]`; InputError unless n >= 3 indices of existing vertices."""
    try:
        count = int(row[0])
        indices = [int(w) for w in row[1 : 1 + count]]
    except ValueError:
        raise InputError(f"cannot read {path}: face {index} is not integers") from None
    if count < 3:
        raise InputError(f"cannot read {path}: face {index} has {count} vertex indices, a face needs 3 or more")
    if len(indices) < count:
        raise InputError(f"cannot read {path}: face {index} declares {count} indices and holds {len(indices)}")
    bad = [i for i in indices if not 0 <= i < n_vertices]
    if bad:
        raise InputError(f"cannot read {path}: face {index} refers to vertex {bad[0]} of {n_vertices}")
    return indices
