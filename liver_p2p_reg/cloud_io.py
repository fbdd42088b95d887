"""Read and write point clouds and meshes (PLY/PCD/XYZ/STL/OBJ/NPY/NPZ) in millimetres."""

from __future__ import annotations

import logging
import warnings
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.o3d import o3d_module
from liver_p2p_reg.off_io import read_off
from liver_p2p_reg.ply_pcd import read_pcd, read_ply, write_pcd, write_ply

LOG = logging.getLogger("liver_p2p_reg")

# What `load_points` reads (the README's "Inputs are ..." sentence lists exactly these; a test checks).
POINT_FORMATS = (".ply", ".pcd", ".xyz", ".xyzn", ".pts", ".stl", ".obj", ".off", ".npy", ".npz")
MESH_FORMATS = (".stl", ".obj", ".off", ".ply", ".npz")  # .npz: `vertices` with `triangles` (or `faces`)
TEXT_FORMATS = (".xyz", ".xyzn", ".pts")  # x y z [more columns] per line; .pts may start with a point count
# The NPZ arrays read when the caller names none (the first present); without them an NPZ must hold
# one (N, 3) array of coordinates. A dataset case holds two (src_pcd, tgt_pcd): picking one by a
# list of names read the complete surface where the partial view was meant, so it is refused instead.
NPZ_POINT_KEYS = ("points", "xyz", "vertices")
NPZ_POINTS_KEY = NPZ_POINT_KEYS[0]
NPZ_TRIANGLE_KEYS = ("triangles", "faces")  # beside `vertices` (and no key named): a mesh, read like a PLY's faces
MESH_SAMPLES_PER_MM2 = 0.5  # surface sampling density for meshes (about 1.4 mm spacing)
MAX_MESH_SAMPLES = 200_000


def load_points(path: str | Path, *, key: str | None = None, seed: int = 0, sample_meshes: bool = True) -> np.ndarray:
    """Load an (N, 3) float64 array in mm from a cloud or mesh file.

    Meshes (files with triangles) are sampled uniformly over their surface, together with
    their vertices, so coarse meshes still give a dense surface (sample_meshes=False: the
    vertices only). An NPZ gives its array `key`, else its array 'points', else its one (N, 3)
    array of coordinates; with several it raises InputError naming them. Raises InputError.
    """
    path = check_point_file(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".npz" and key is None and (mesh := _npz_mesh(path)) is not None:
            vertices, triangles = finite_mesh(*mesh, path)
            points = sample_mesh_surface(vertices, triangles, seed=seed) if sample_meshes else vertices
        elif suffix in (".npy", ".npz"):
            points = _load_numpy(path, key)
        elif suffix in TEXT_FORMATS:
            points = _load_text(path)
        else:
            if suffix == ".ply":
                with path.open("rb") as f:
                    magic = f.read(3)
                if magic != b"ply":  # checked here: Open3D's reader would print its own complaint to stderr
                    raise InputError(f"cannot read {path}: not a PLY file (it does not start with 'ply')")
            vertices, triangles = load_mesh(path)  # non-finite vertices dropped there, with their triangles
            sample = sample_meshes and len(triangles) > 0
            points = sample_mesh_surface(vertices, triangles, seed=seed) if sample else vertices
    except InputError:
        raise
    except Exception as exc:  # any parser failure becomes one readable line
        raise InputError(
            f"cannot read {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
        ) from None
    points = np.asarray(points, dtype=np.float64)
    if points.size == 0:
        raise InputError(f"{path}: no points in the file")
    if points.ndim != 2 or points.shape[1] < 3:
        raise InputError(f"{path}: expected an (N, 3) array of points, got shape {points.shape}")
    return points[:, :3]


def check_point_file(path: str | Path) -> Path:
    """The path, if it names an existing file of a format `load_points` reads; else InputError (reads nothing)."""
    path = require_regular_file(path)
    suffix = path.suffix.lower()
    if suffix not in POINT_FORMATS:
        raise InputError(f"unsupported format {suffix or '(none)'!r} for {path}; use one of {', '.join(POINT_FORMATS)}")
    return path


def require_regular_file(path: str | Path) -> Path:
    """The path, if it names an existing regular file (or a link to one); else InputError (opens nothing)."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"file not found: {path}")
    if path.is_dir():
        raise InputError(f"expected a file, got a directory: {path}")
    if not path.is_file():  # opening a named pipe blocks until a writer comes; a device may never end
        raise InputError(f"not a regular file: {path} (a pipe, socket or device cannot be read as points)")
    return path


def load_mesh(path: str | Path, *, warn: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Load vertices (V, 3) and triangles (F, 3); a point-cloud file gives F = 0.

    PLY and PCD are read in numpy (the same values Open3D gives, without its import), OFF too (checked, in full
    precision), an NPZ's `vertices` and `triangles` (checked the same way); STL, OBJ and PLY/PCD layouts those readers
    leave out are read by Open3D. Vertices with NaN/inf coordinates are dropped with the triangles that use them
    (`warn`: with one warning saying how many; False where the caller has read the file once already).
    """
    path = require_regular_file(path)
    vertices, triangles = _read_mesh(path)
    return finite_mesh(vertices, triangles, path, warn=warn)


def _read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The file's vertices and triangles as its reader gives them (load_mesh)."""
    suffix = path.suffix.lower()
    if suffix == ".ply" and (mesh := read_ply(path)) is not None and len(mesh[0]) > 0:
        return mesh
    if suffix == ".pcd" and (cloud := read_pcd(path)) is not None and len(cloud) > 0:
        return cloud, np.zeros((0, 3), np.int64)
    if suffix == ".off":  # read here, checked: Open3D's reader crashes the process on some malformed files
        return read_off(path)
    if suffix in (".npy", ".npz"):
        try:  # a cut or damaged archive: one line, as load_points says it (prepare and the loader read meshes here)
            mesh = _npz_mesh(path) if suffix == ".npz" else None
            cloud = None if mesh is not None else np.asarray(_load_numpy(path, None), dtype=np.float64)
        except InputError:
            raise
        except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as exc:
            raise InputError(f"cannot read {path}: {type(exc).__name__}: {exc}") from None
        return mesh if mesh is not None else (cloud, np.zeros((0, 3), np.int64))
    o3d = o3d_module()  # heavy import, only for the formats above
    if suffix in MESH_FORMATS:
        mesh = o3d.io.read_triangle_mesh(str(path))
        if len(mesh.triangles) > 0:
            return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)
        if len(mesh.vertices) > 0:
            return np.asarray(mesh.vertices, dtype=np.float64), np.zeros((0, 3), np.int64)
    if suffix in (".ply", ".pcd", ".xyz", ".pts"):
        cloud = o3d.io.read_point_cloud(str(path))
        if len(cloud.points) > 0:
            return np.asarray(cloud.points, dtype=np.float64), np.zeros((0, 3), np.int64)
    if suffix == ".obj":  # Open3D gives nothing for vertices alone, and nothing (without a reason) for a bad face
        vertices, n_faces, problem = _scan_obj(path)
        if problem or n_faces:  # a mesh Open3D could not read is no cloud of its vertices
            raise InputError(f"cannot read {path}: {problem or f'Open3D could not read its {n_faces} faces'}")
        if len(vertices):
            return vertices, np.zeros((0, 3), np.int64)
    raise InputError(f"cannot read {path}: no points found (empty or unreadable {suffix} file)")


def finite_mesh(
    vertices: np.ndarray, triangles: np.ndarray, name: str | Path, *, warn: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """The mesh without its NaN/inf vertices and the triangles using them (re-indexed); a cloud as it is.

    Dropped, not refused, as `clean_points` drops a cloud's bad rows: one bad vertex from an exporter leaves the rest
    of the organ's surface good for sampling and registration, and the non-rigid stage's solid check still decides
    whether the surface with that hole encloses a volume. Refusing later, after the rigid registration (the indices
    no longer matching the cleaned points), lost the rigid pose; doing it here decides before any work.
    """
    if not len(triangles):  # a cloud: its NaN rows are the caller's to drop or refuse (clean_points, structures)
        return vertices, triangles
    finite = np.isfinite(vertices).all(axis=1)
    if finite.all():
        return vertices, triangles
    if not finite.any():
        raise InputError(f"{name}: all {len(vertices)} vertices are NaN or infinite")
    kept = finite[triangles].all(axis=1)
    new_index = np.cumsum(finite) - 1
    if warn:
        LOG.warning(
            "%s: dropped %d of %d vertices with NaN/inf coordinates and the %d of %d triangles using them",
            name,
            int((~finite).sum()),
            len(vertices),
            int((~kept).sum()),
            len(triangles),
        )
    return vertices[finite], new_index[triangles[kept]]


def _npz_mesh(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """An NPZ's `vertices` (V, 3) and triangles (`triangles` or `faces`, (F, 3) integers indexing them) when it has
    both and no `points`/`xyz` (which `load_points` would read first); None when it is no such mesh."""
    _require_numpy_magic(path)
    with np.load(path, allow_pickle=False) as data:
        if "vertices" not in data or any(k in data for k in NPZ_POINT_KEYS[:2]):
            return None
        key = next((k for k in NPZ_TRIANGLE_KEYS if k in data), None)
        if key is None:
            return None
        vertices = _numeric(data["vertices"], f"{path} (vertices)").astype(np.float64)
        triangles = _numeric(data[key], f"{path} ({key})")
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise InputError(f"{path}: vertices must be an (N, 3) array, got shape {vertices.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3 or triangles.dtype.kind not in "iu":
        raise InputError(
            f"{path}: {key} must be an (F, 3) integer array, got shape {triangles.shape} {triangles.dtype}"
        )
    bad = np.flatnonzero(((triangles < 0) | (triangles >= len(vertices))).any(axis=1))
    if len(bad):
        row = triangles[bad[0]]
        index = int(row[(row < 0) | (row >= len(vertices))][0])
        raise InputError(f"cannot read {path}: face {int(bad[0])} refers to vertex {index} of {len(vertices)}")
    return vertices, triangles.astype(np.int64)


def _scan_obj(path: Path) -> tuple[np.ndarray, int, str]:
    """An OBJ's `v x y z` rows (V, 3), its face count and what is wrong with it ("" when nothing is found): a vertex
    short of coordinates or not numbers, a face index that is not an integer, 0, or beyond the vertices (1-based;
    negative ones count back from the last vertex read)."""
    lines = path.read_bytes().decode("latin-1").splitlines()
    n_vertices = sum(1 for line in lines if line.split()[:1] == ["v"])
    rows: list[list[float]] = []
    face = 0
    for number, line in enumerate(lines, start=1):
        words = line.split()
        if words[:1] == ["v"]:
            try:
                rows.append([float(w) for w in words[1:4]])
            except ValueError:
                return np.zeros((0, 3)), face, f"vertex {len(rows) + 1} (line {number}) is not numbers"
            if len(rows[-1]) < 3:  # a vertex short of a coordinate: no cloud to guess from
                return np.zeros((0, 3)), face, f"vertex {len(rows)} (line {number}) has fewer than 3 coordinates"
        elif words[:1] == ["f"]:
            face += 1
            for word in words[1:]:
                try:
                    index = int(word.split("/")[0])
                except ValueError:
                    return np.zeros((0, 3)), face, f"face {face} (line {number}) is not integers: {word!r}"
                resolved = index - 1 if index > 0 else len(rows) + index
                if index == 0 or not 0 <= resolved < (n_vertices if index > 0 else len(rows)):
                    return (
                        np.zeros((0, 3)),
                        face,
                        f"face {face} (line {number}) refers to vertex {index} of {n_vertices}",
                    )
    return np.array(rows, dtype=np.float64).reshape(-1, 3), face, ""


def sample_mesh_surface(vertices: np.ndarray, triangles: np.ndarray, *, seed: int = 0) -> np.ndarray:
    """Area-uniform, deterministic surface samples plus the vertices (mm)."""
    tri = vertices[triangles]  # (F, 3, 3)
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = float(areas.sum())
    if not np.isfinite(total) or total <= 0:
        return vertices
    n = int(min(MAX_MESH_SAMPLES, max(1000, total * MESH_SAMPLES_PER_MM2)))
    rng = np.random.default_rng(seed)
    face = rng.choice(len(tri), size=n, p=areas / total)
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1  # fold the unit square onto the triangle
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[face]
    samples = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    return np.concatenate([vertices, samples], axis=0)


def as_float_array(values: Any, name: str) -> np.ndarray:
    """`values` as a float64 array; InputError (not a numpy ValueError/TypeError) if they are not real numbers."""
    if np.iscomplexobj(values):
        raise InputError(f"{name}: complex numbers are not coordinates")
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: not an array of numbers ({exc})") from None


def clean_points(points: np.ndarray, name: str, *, min_points: int = 3) -> np.ndarray:
    """Drop NaN/inf rows (with a warning); raise InputError if too few points remain."""
    points = as_float_array(points, name)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"{name}: expected an (N, 3) array of points, got shape {points.shape}")
    if len(points) == 0:
        raise InputError(f"{name}: the point cloud is empty")
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        dropped = int((~finite).sum())
        if dropped == len(points):
            raise InputError(f"{name}: all {dropped} points are NaN or infinite")
        LOG.warning("%s: dropped %d of %d points with NaN/inf coordinates", name, dropped, len(points))
        points = points[finite]
    if len(points) < min_points:
        raise InputError(f"{name}: only {len(points)} valid points, at least {min_points} are needed")
    return points


def extent_mm(points_mm: np.ndarray) -> float:
    """Size of a cloud: its bounding-box diagonal (mm)."""
    with np.errstate(over="ignore"):  # 1e200 mm coordinates: an inf extent, refused by the callers in one line
        return float(np.linalg.norm(points_mm.max(axis=0) - points_mm.min(axis=0)))


def implausible_extent(extent: float, name: str, min_mm: float, max_mm: float) -> str:
    """Why a cloud of this size (mm) is likely in other units; "" when min_mm <= extent <= max_mm.

    A liver is 50-300 mm across: a cloud given in metres is ~1000x too small and looks like a
    point, one in micrometres ~1000x too large; both would still "register" to a meaningless pose.
    """
    if extent > max_mm:
        return f"{name} extent {extent:.0f} mm exceeds {max_mm:.0f} mm: wrong units?"
    if extent < min_mm:
        return f"{name} extent {extent:.3g} mm is below {min_mm:.0f} mm: wrong units?"
    return ""


def require_plausible_extent(points_mm: np.ndarray, name: str, min_mm: float, max_mm: float, hint: str) -> None:
    """InputError ("<problem> (<hint>)") when `implausible_extent` objects to the cloud's size."""
    problem = implausible_extent(extent_mm(points_mm), name, min_mm, max_mm)
    if problem:
        raise InputError(f"{problem} ({hint})")


def save_points(path: str | Path, points: np.ndarray) -> None:
    """Write (N, 3) points to PLY/PCD/XYZ/NPY by extension."""
    path = Path(path)
    suffix = path.suffix.lower()
    points = np.asarray(points, dtype=np.float64)
    if suffix == ".npy":
        np.save(path, points)
    elif suffix in (".xyz", ".pts"):
        np.savetxt(path, points, fmt="%.6f")
    elif suffix == ".ply":
        write_ply(path, points)
    elif suffix == ".pcd":
        write_pcd(path, points)
    else:
        raise InputError(f"cannot write format {suffix!r}; use .ply, .pcd, .xyz or .npy")


def _load_text(path: Path) -> np.ndarray:
    """x y z (and ignored further columns) per line; a first line holding only a count is skipped (.pts)."""
    with warnings.catch_warnings():  # an empty file is reported by the caller, in one line
        warnings.simplefilter("ignore", UserWarning)
        with path.open("rb") as f:
            first = f.readline().split()
        skip = 1 if len(first) == 1 and first[0].isdigit() else 0
        return np.loadtxt(path, dtype=np.float64, ndmin=2, comments=("#", "//"), skiprows=skip)[:, :3]


def _load_numpy(path: Path, key: str | None) -> np.ndarray:
    """The array of an NPY file, or the named / first of `NPZ_POINT_KEYS` / only point array of an NPZ; numbers only."""
    _require_numpy_magic(path)
    if path.suffix.lower() == ".npy":
        return _numeric(np.load(path, allow_pickle=False), str(path))
    with np.load(path, allow_pickle=False) as data:
        if key is not None:
            if key not in data:
                raise InputError(f"{path}: no array named {key!r} (has: {', '.join(data.files)})")
            return _numeric(data[key], f"{path} ({key})")
        for name in NPZ_POINT_KEYS:  # a cloud saved with its normals, a mesh with its triangles
            if name in data:
                return _numeric(data[name], f"{path} ({name})")
        name, array = _only_point_array(path, data)
        return _numeric(array, f"{path} ({name})")


def _require_numpy_magic(path: Path) -> None:
    """InputError unless the file starts as an NPY (or, for .npz, a zip) file does."""
    with path.open("rb") as f:
        magic = f.read(6)
    # numpy calls any file without its magic "pickled data" and offers allow_pickle: for a damaged file, wrong advice
    wanted = b"\x93NUMPY" if path.suffix.lower() == ".npy" else b"PK\x03\x04"
    if magic[:4] != wanted[:4]:
        kind = "NumPy .npy" if path.suffix.lower() == ".npy" else "NumPy .npz (zip)"
        raise InputError(f"cannot read {path}: not a {kind} file (it does not start as one)")


def _only_point_array(path: Path, data: Any) -> tuple[str, np.ndarray]:
    """The one (N, 3) array of an NPZ; coordinates (floats) win over integer (F, 3) arrays, a mesh's triangles."""
    shaped: dict[str, np.ndarray] = {}
    for name in data.files:
        try:
            array = data[name]
        except ValueError:  # an object array: pickles are never loaded, and it holds no coordinates
            continue
        if array.ndim == 2 and array.shape[1] == 3 and len(array) > 3:  # (3, 3): a rotation, not a cloud
            shaped[name] = array
    floats = [name for name, array in shaped.items() if array.dtype.kind == "f"]
    choice = floats or list(shaped)
    if len(choice) == 1:
        return choice[0], shaped[choice[0]]
    if not choice:
        raise InputError(f"{path}: no (N, 3) array found (has: {', '.join(data.files) or 'none'})")
    raise InputError(
        f"{path} holds several point arrays ({', '.join(choice)}); save the one to read as "
        f"{NPZ_POINTS_KEY!r} or alone (a dataset case: `liver-p2p bag make --case`)"
    )


def _numeric(array: np.ndarray, name: str) -> np.ndarray:
    """`array` if it holds real numbers; InputError for complex, text, boolean or other values."""
    kind = array.dtype.kind
    if kind == "c":  # converting would drop the imaginary part with only a warning
        raise InputError(f"{name}: complex numbers are not coordinates")
    if kind not in "iuf":
        what = {"U": "text", "S": "bytes", "b": "true/false values", "M": "dates", "m": "time spans"}.get(
            kind, "records"
        )
        raise InputError(f"{name}: holds {what} ({array.dtype}), not coordinates")
    return array
