"""PLY and PCD reading/writing in numpy: the values Open3D's readers give, without importing Open3D.

Open3D's own PLY (rply) and PCD readers hand every coordinate over as a float64: binary
float32 values widened, ASCII words parsed as doubles whatever the declared type. These
readers do the same, so a cloud loads to the same bits with or without Open3D. Layouts they do
not cover (polygons other than triangles, list properties on vertices, compressed PCD, ...)
return None, and the caller falls back to Open3D. A file that cannot hold what its header declares
(truncated, or a point without x, y or z) is refused with an InputError before either reader runs
(`ply_check` for PLY, `_check_pcd` for PCD): Open3D would fill the missing values with zeros or leave them
uninitialized.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.ply_check import FACE_LISTS, check_ply_body

PLY_SCALARS = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
MAX_HEADER_BYTES = 1 << 16


class _Unsupported(Exception):
    """A layout these readers leave to Open3D."""


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices (V, 3) float64, triangles (F, 3) int64) of a PLY file; None: let Open3D read it.

    Raises InputError for a file whose body is shorter than its header declares or whose
    vertices lack x, y or z, whichever reader would have read it.
    """
    data = path.read_bytes()
    # A header this reader cannot parse is refused, not handed to Open3D: its reader fills a truncated body with
    # zeros and crashes the process on some malformed files, and only a parsed header lets ply_check see them.
    try:
        header, body = _split_header(data, b"end_header")
        fmt, elements = _ply_elements(header)
    except (_Unsupported, ValueError, IndexError, KeyError) as exc:
        raise InputError(f"cannot read {path}: malformed PLY header ({str(exc) or type(exc).__name__})") from None
    check_ply_body(path, elements, body, PLY_FORMATS[fmt])
    try:
        _check_supported(elements)
        if fmt == "ascii":
            return _ply_ascii(body, elements)
        return _ply_binary(body, elements, PLY_FORMATS[fmt])
    except (_Unsupported, ValueError, IndexError, KeyError):
        return None


def _split_header(data: bytes, end: bytes) -> tuple[list[str], bytes]:
    """The header's lines and the body: the header ends at the first line that is `end` alone (a comment may hold
    the word), within MAX_HEADER_BYTES. Latin-1 decodes any byte: a stray non-ASCII comment is still parsed."""
    # any line ending (rply reads CR-only files too), blanks around the word
    pattern = rb"(?:^|[\r\n])[ \t]*" + re.escape(end) + rb"[ \t]*(?:\r\n|\n|\r)"
    match = re.search(pattern, data[: MAX_HEADER_BYTES + len(end) + 8])
    if match is None:
        raise _Unsupported(f"no '{end.decode()}' line within the first {MAX_HEADER_BYTES // 1024} KiB")
    lines = data[: match.start() + 1].decode("latin-1").splitlines()
    return lines, data[match.end() :]


def _ply_elements(lines: list[str]) -> tuple[str, list[tuple[str, int, list[tuple[str, ...]]]]]:
    """Format and [(element, count, [(kind, name, dtype[, count dtype]), ...]), ...] of any PLY header."""
    if not lines or lines[0].strip() != "ply":
        raise _Unsupported("not a PLY header")
    fmt = ""
    elements: list[tuple[str, int, list[tuple[str, ...]]]] = []
    for line in lines[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1]
            if fmt not in PLY_FORMATS:
                raise _Unsupported(fmt)
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            if words[1] == "list":
                elements[-1][2].append(("list", words[4], PLY_SCALARS[words[3]], PLY_SCALARS[words[2]]))
            else:
                elements[-1][2].append(("scalar", words[2], PLY_SCALARS[words[1]]))
        else:
            raise _Unsupported(line)
    if not fmt:
        raise _Unsupported("no format line")
    return fmt, elements


def _check_supported(elements: list) -> None:
    """_Unsupported unless the layout is one vertex element (scalars) and at most one triangle-list face element."""
    names = [e[0] for e in elements]
    if names[:1] != ["vertex"] or any(n not in ("vertex", "face") for n in names) or len(set(names)) < len(names):
        raise _Unsupported("elements other than one vertex and one face element")
    vertex_props = elements[0][2]
    axes = [p[1] for p in vertex_props if p[1] in ("x", "y", "z")]
    if any(p[0] != "scalar" for p in vertex_props) or axes != ["x", "y", "z"]:
        raise _Unsupported("vertex without scalar x, y, z in this order")
    if len(elements) == 2:
        face_props = elements[1][2]
        if len(face_props) != 1 or face_props[0][0] != "list" or face_props[0][1] not in FACE_LISTS:
            raise _Unsupported("face element other than one vertex index list")


def _xyz_columns(props: list[tuple[str, ...]]) -> list[int]:
    names = [p[1] for p in props]
    return [names.index("x"), names.index("y"), names.index("z")]


def _ply_ascii(body: bytes, elements: list) -> tuple[np.ndarray, np.ndarray]:
    lines = body.decode("ascii").splitlines()
    _, n_vertices, props = elements[0]
    rows = [line.split() for line in lines[:n_vertices]]
    if len(rows) != n_vertices or any(len(r) != len(props) for r in rows):
        raise _Unsupported("vertex rows do not match the header")
    # float() parses like rply's strtod: the nearest double, whatever the declared type.
    vertices = np.array([[float(r[i]) for i in _xyz_columns(props)] for r in rows], dtype=np.float64).reshape(-1, 3)
    triangles = np.zeros((0, 3), np.int64)
    if len(elements) == 2:
        n_faces = elements[1][1]
        faces = [line.split() for line in lines[n_vertices : n_vertices + n_faces]]
        if len(faces) != n_faces or any(len(f) != 4 or f[0] != "3" for f in faces):
            raise _Unsupported("faces other than triangles")
        triangles = np.array([[int(float(v)) for v in f[1:]] for f in faces], dtype=np.int64).reshape(-1, 3)
    return vertices, triangles


def _ply_binary(body: bytes, elements: list, order: str) -> tuple[np.ndarray, np.ndarray]:
    _, n_vertices, props = elements[0]
    vertex_type = np.dtype([(f"p{i}", order + p[2]) for i, p in enumerate(props)])
    table = np.frombuffer(body, dtype=vertex_type, count=n_vertices)
    vertices = np.stack([table[f"p{i}"].astype(np.float64) for i in _xyz_columns(props)], axis=1)
    triangles = np.zeros((0, 3), np.int64)
    if len(elements) == 2:
        _, n_faces, ((_, _, index_type, count_type),) = elements[1]
        face_type = np.dtype([("n", order + count_type), ("v", order + index_type, (3,))])
        rest = body[n_vertices * vertex_type.itemsize :]
        if len(rest) < n_faces * face_type.itemsize:
            raise _Unsupported("truncated or non-triangle faces")
        faces = np.frombuffer(rest, dtype=face_type, count=n_faces)
        if n_faces and not (faces["n"] == 3).all():
            raise _Unsupported("faces other than triangles")
        triangles = faces["v"].astype(np.int64)
    return vertices, triangles


def read_pcd(path: Path) -> np.ndarray | None:
    """(N, 3) float64 x, y, z of an ASCII or binary PCD file; None: let Open3D read it.

    Raises InputError for a file without x, y or z fields or with fewer points than its header declares.
    """
    data = path.read_bytes()
    try:
        found = re.search(rb"(?:^|\n)DATA[ \t]", data[:MAX_HEADER_BYTES])  # the DATA line, not the word in a comment
        stop = -1 if found is None else found.end()
        newline = data.find(b"\n", stop)
        if stop < 0 or newline < 0:
            return None
        fields: dict[str, list[str]] = {}
        for line in data[:newline].decode("latin-1").splitlines():  # any byte: a non-ASCII comment still parses
            words = line.split()
            if words and not words[0].startswith("#"):
                fields[words[0].upper()] = words[1:]
        names, sizes, types = fields["FIELDS"], fields["SIZE"], fields["TYPE"]
        counts = fields.get("COUNT", ["1"] * len(names))
        n_points = (
            int(fields["POINTS"][0]) if "POINTS" in fields else int(fields["WIDTH"][0]) * int(fields["HEIGHT"][0])
        )
        body = data[newline + 1 :]
        record_bytes = sum(int(s) * int(c) for s, c in zip(sizes, counts, strict=True))
        words_per_point = sum(int(c) for c in counts)
        storage = fields["DATA"][0]
    except (ValueError, IndexError, KeyError, TypeError, UnicodeDecodeError):
        return None
    _check_pcd(path, names, n_points, storage, body, record_bytes, words_per_point)
    try:
        if any(c != "1" for c in counts) or [n for n in names if n in ("x", "y", "z")] != ["x", "y", "z"]:
            return None
        columns = [names.index(axis) for axis in "xyz"]
        if storage == "ascii":
            rows = [line.split() for line in body.decode("ascii").splitlines() if line.strip()][:n_points]
            if len(rows) != n_points or any(len(r) != len(names) for r in rows):
                return None
            return np.array([[float(r[i]) for i in columns] for r in rows], dtype=np.float64).reshape(-1, 3)
        if storage != "binary":
            return None  # binary_compressed (LZF)
        kinds = {"F": "f", "I": "i", "U": "u"}
        record = np.dtype([(f"p{i}", "<" + kinds[t] + s) for i, (t, s) in enumerate(zip(types, sizes, strict=True))])
        table = np.frombuffer(body, dtype=record, count=n_points)
        return np.stack([table[f"p{i}"].astype(np.float64) for i in columns], axis=1)
    except (ValueError, IndexError, KeyError, TypeError, UnicodeDecodeError):
        return None


def _check_pcd(
    path: Path, names: list[str], n_points: int, storage: str, body: bytes, record_bytes: int, words_per_point: int
) -> None:
    """InputError unless the points have x, y, z fields and the body holds the declared points (ASCII, binary)."""
    for axis in "xyz":
        if axis not in names:
            raise InputError(f"cannot read {path}: its points have no {axis!r} field (x, y and z are needed)")
    if n_points < 0:
        raise InputError(f"cannot read {path}: its PCD header declares {n_points} points")
    if storage == "binary":
        held = len(body) // max(record_bytes, 1)
    elif storage == "ascii":  # one point per line; a line cut short is no point
        held = sum(1 for line in body.splitlines() if len(line.split()) >= words_per_point)
    else:
        return  # binary_compressed: its own sizes are checked by Open3D's LZF reader
    if held < n_points:
        raise InputError(f"cannot read {path}: truncated: its header declares {n_points} points, the file holds {held}")


def write_ply(path: Path, points: np.ndarray) -> None:
    """Binary little-endian PLY of float64 x, y, z (what Open3D writes for a plain cloud)."""
    points = np.ascontiguousarray(points, dtype="<f8")
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by liver_p2p_reg\n"
        f"element vertex {len(points)}\nproperty double x\nproperty double y\nproperty double z\nend_header\n"
    )
    path.write_bytes(header.encode("ascii") + points.tobytes())


def write_pcd(path: Path, points: np.ndarray) -> None:
    """Binary PCD (v0.7) of float32 x, y, z, as Open3D writes it (Open3D reads 8-byte floats in PCD as zeros)."""
    points = np.ascontiguousarray(points, dtype="<f4")
    n = len(points)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n"
        f"COUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
    )
    path.write_bytes(header.encode("ascii") + points.tobytes())
