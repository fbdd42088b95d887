"""Real liver surfaces from mesh files: the fixed split of ../shared/data/livers and generator-ready livers.

A mesh read from a file (a CT segmentation, a patient's preoperative model) becomes a `LiverMesh`
the generator can deform: its signed distance is sampled on a regular grid (distance to dense
surface samples, sign from the nearest face's normal near the surface and from a flood fill
further away), and the zero level is re-meshed by marching cubes + Taubin smoothing at the
procedural livers' 2.2 mm spacing, so real and procedural livers have the same point density.
The original vertices are kept (`coarse_vertices_mm`): a decimated clinical mesh has the
non-uniform density of its vertices, which the density-variant targets reproduce.

The real livers themselves (CC BY-SA 4.0, see their README) are never part of this project:
they are read at run time from $LIVER_P2P_REAL_LIVERS or ../shared/data/livers beside the
repository, and everything built from them is skipped with one line when they are absent.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom.anatomy import GridSDF, LiverMesh, surface_from_grid
from liver_p2p_reg.phantom.dataset import MAX_LIVERS_PER_SEED, REAL_LIVER_SEED
from liver_p2p_reg.registration.mechanics.surface import edge_face_counts, mesh_volume_mm3

ENV_REAL_LIVERS = "LIVER_P2P_REAL_LIVERS"
SPLIT_PATH = Path(__file__).resolve().parent.parent / "data" / "real_livers_split.json"
SPLITS = ("train", "train_dev", "val", "test")
# Liver ids of real livers: REAL_LIVER_SEED * 10_000 + the file's LiTS volume number (procedural
# ids are seed * 10_000 + index; the generator refuses that seed).
REAL_ID_BASE = REAL_LIVER_SEED * MAX_LIVERS_PER_SEED
REMESH_SPACING_MM = 2.2  # the procedural livers' marching-cubes grid (anatomy.MESH_SPACING_MM)
SMOOTH_ITERATIONS = 10
SURFACE_SAMPLES_PER_MM2 = 4.0  # distance queries against ~0.5 mm-spaced surface samples


def real_livers_dir() -> Path | None:
    """The folder of real liver meshes, or None when it is not on this machine."""
    env = os.environ.get(ENV_REAL_LIVERS)
    candidates = [Path(env)] if env else []
    candidates.append(Path(__file__).resolve().parents[3] / "shared" / "data" / "livers")
    candidates.append(Path.cwd().parent / "shared" / "data" / "livers")
    for path in candidates:
        if path.is_dir() and any(path.glob("*.obj")):
            return path
    return None


def missing_real_livers_message() -> str:
    """The one line printed wherever real-anatomy work is skipped."""
    return (
        f"real liver meshes not found (set ${ENV_REAL_LIVERS} or place them in ../shared/data/livers): "
        "real-anatomy sets skipped"
    )


def require_real_livers() -> Path:
    """The real liver folder, or InputError with the one-line reason."""
    path = real_livers_dir()
    if path is None:
        raise InputError(missing_real_livers_message())
    return path


def real_split() -> dict[str, list[str]]:
    """The fixed split of the real livers by file stem (liver_p2p_reg/data/real_livers_split.json)."""
    data = json.loads(SPLIT_PATH.read_text())
    return {name: list(data[name]) for name in SPLITS}


def real_liver_id(stem: str) -> int:
    """Liver id of a real liver file `LiTS-<n>`: REAL_ID_BASE + n."""
    match = re.fullmatch(r"LiTS-(\d+)", stem)
    if match is None:
        raise InputError(f"not a real liver name (LiTS-<number>): {stem!r}")
    return REAL_ID_BASE + int(match.group(1))


def read_obj(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and triangles (F, 3) of a Wavefront OBJ (polygons fanned into triangles)."""
    verts, faces = [], []
    try:
        text = Path(path).read_text(errors="replace")
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror or exc}") from None
    for line in text.splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v" and len(parts) >= 4:
            verts.append([float(x) for x in parts[1:4]])
        elif parts[0] == "f" and len(parts) >= 4:
            idx = [int(p.split("/")[0]) for p in parts[1:]]
            idx = [i - 1 if i > 0 else len(verts) + i for i in idx]  # 1-based, negatives count back
            faces += [[idx[0], idx[i], idx[i + 1]] for i in range(1, len(idx) - 1)]
    v = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise InputError(f"{path}: a face refers to a vertex that does not exist")
    return v, f


def weld_vertices(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices with identical coordinates (STL stores every triangle's corners separately)
    and drop the faces that collapse; a mesh that is welded already is returned unchanged."""
    unique, inverse = np.unique(vertices, axis=0, return_inverse=True)
    if len(unique) == len(vertices):
        return vertices, triangles
    faces = inverse.reshape(-1)[triangles]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return unique, faces[keep]


def check_closed_surface(vertices: np.ndarray, triangles: np.ndarray, name: str) -> None:
    """InputError (one line) unless the mesh is a closed, manifold surface of plausible liver size in mm."""
    if len(triangles) < 4:
        raise InputError(f"{name}: not a triangle mesh (no faces); a closed surface mesh is needed")
    if not np.all(np.isfinite(vertices)):
        raise InputError(f"{name}: vertices contain NaN or inf")
    counts = edge_face_counts(triangles)
    if np.any(counts > 2):
        raise InputError(f"{name}: non-manifold mesh ({int(np.sum(counts > 2))} edges shared by more than 2 faces)")
    if np.any(counts < 2):
        raise InputError(f"{name}: open mesh ({int(np.sum(counts < 2))} boundary edges); a closed surface is needed")
    extent = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    if not 50.0 <= extent <= 600.0:
        hint = "metres? the mesh must be in mm" if extent < 50.0 else "wrong units? the mesh must be in mm"
        raise InputError(f"{name}: mesh extent {extent:.3g} mm is not a liver's (50-600 mm; {hint})")
    if abs(mesh_volume_mm3(vertices, triangles)) < 1e4:
        raise InputError(f"{name}: enclosed volume below 10 ml: not a liver surface")


@dataclass
class SurfaceSamples:
    """Dense area-uniform samples of a mesh with the normal of the face each lies on."""

    points_mm: np.ndarray
    normals: np.ndarray


def surface_samples(vertices: np.ndarray, triangles: np.ndarray, rng: np.random.Generator) -> SurfaceSamples:
    """~SURFACE_SAMPLES_PER_MM2 samples per mm^2 plus every face centroid (no face goes unsampled)."""
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    cross = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normals = cross / np.maximum(2.0 * area, 1e-12)[:, None]
    n = int(max(1000, area.sum() * SURFACE_SAMPLES_PER_MM2))
    face = rng.choice(len(triangles), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    pts = (1 - s)[:, None] * a[face] + (s * (1 - r2))[:, None] * b[face] + (s * r2)[:, None] * c[face]
    pts = np.concatenate([pts, (a + b + c) / 3.0])
    return SurfaceSamples(pts, np.concatenate([normals[face], normals]))


def sampled_sdf(vertices: np.ndarray, triangles: np.ndarray, spacing_mm: float, seed: int = 0) -> GridSDF:
    """Signed distance of a closed mesh on a grid with `spacing_mm` (3 cells of margin)."""
    from scipy.ndimage import binary_fill_holes, distance_transform_edt
    from scipy.spatial import cKDTree

    samples = surface_samples(vertices, triangles, np.random.default_rng([int(seed), 7]))
    lo = vertices.min(axis=0) - 3 * spacing_mm
    shape = tuple(np.ceil((vertices.max(axis=0) + 3 * spacing_mm - lo) / spacing_mm).astype(np.int64) + 1)
    axes = [lo[i] + spacing_mm * np.arange(shape[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    # Exact-enough distances only near the surface (a k-d query far from it is slow); further
    # away the grid's own Euclidean distance transform of the near-surface shell suffices.
    band = 2.0 * spacing_mm
    dist, idx = cKDTree(samples.points_mm).query(grid, k=1, distance_upper_bound=band, workers=-1)
    near = np.isfinite(dist)
    shell = (dist < spacing_mm).reshape(shape)
    far_dist = (distance_transform_edt(~shell) * spacing_mm + spacing_mm).ravel()
    dist = np.where(near, dist, np.maximum(far_dist, band))
    # Near the surface the nearest face's normal tells inside from outside; further away a
    # flood fill of the shell does (robust in the narrow gaps between lobes).
    idx = np.where(near, idx, 0)
    side = np.einsum("ij,ij->i", grid - samples.points_mm[idx], samples.normals[idx])
    inside_far = (binary_fill_holes(shell) & ~shell).ravel()
    sign = np.where(shell.ravel(), np.where(side < 0, -1.0, 1.0), np.where(inside_far, -1.0, 1.0))
    return GridSDF(origin_mm=lo, spacing_mm=float(spacing_mm), values=(sign * dist).reshape(shape))


@dataclass
class FileLiver(LiverMesh):
    """A LiverMesh re-meshed from a file, with the file's own vertices kept for density variants."""

    coarse_vertices_mm: np.ndarray | None = None  # the file's vertices (same frame as vertices_mm)
    name: str = ""


def liver_from_surface(
    vertices_mm: np.ndarray,
    triangles: np.ndarray,
    liver_id: int = 0,
    name: str = "mesh",
    spacing_mm: float = REMESH_SPACING_MM,
    smooth_iterations: int = SMOOTH_ITERATIONS,
) -> FileLiver:
    """A generator-ready liver from a closed surface mesh in mm (kept in its own frame, not re-centred)."""
    vertices_mm, triangles = weld_vertices(
        np.asarray(vertices_mm, dtype=np.float64), np.asarray(triangles, dtype=np.int64)
    )
    check_closed_surface(vertices_mm, triangles, name)
    if mesh_volume_mm3(vertices_mm, triangles) < 0:  # inward-facing file: flip once
        triangles = triangles[:, ::-1].copy()
    sdf = sampled_sdf(vertices_mm, triangles, spacing_mm, seed=liver_id)
    verts, faces = surface_from_grid(sdf.values, sdf.origin_mm, spacing_mm, smooth_iterations)
    return FileLiver(
        vertices_mm=verts,
        triangles=faces,
        seed=int(liver_id),
        sdf=sdf,
        coarse_vertices_mm=vertices_mm,
        name=name,
    )


def load_real_liver(stem: str, folder: Path | None = None) -> FileLiver:
    """Real liver `stem` (e.g. `LiTS-13`) from the real liver folder, ready for the generator."""
    folder = folder if folder is not None else require_real_livers()
    path = folder / f"{stem}.obj"
    if not path.is_file():
        raise InputError(f"real liver {stem} not found in {folder}")
    v, f = read_obj(path)
    return liver_from_surface(v, f, liver_id=real_liver_id(stem), name=stem)
