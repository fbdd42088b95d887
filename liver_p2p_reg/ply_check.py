"""PLY body checks before any reader runs: a body shorter than its header declares, vertices without x, y or z,
faces that are no polygons of the file's vertices.

Open3D's PLY reader fills a truncated file's missing points with zeros, leaves an absent z uninitialized and
crashes the process (segmentation fault) on a face of no index; so every PLY, whichever reader will read it,
is checked here first.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from liver_p2p_reg.errors import InputError

FACE_LISTS = ("vertex_indices", "vertex_index")


class _Truncated(Exception):
    """The body ends inside row `index` of element `name` (of `count` declared)."""

    def __init__(self, name: str, count: int, index: int) -> None:
        super().__init__(name, count, index)
        self.name, self.count, self.index = name, count, index


def check_ply_body(path: Path, elements: list, body: bytes, order: str | None) -> None:
    """InputError unless the vertices have scalar x, y, z and the body holds every declared row.

    `elements`: the header's [(name, count, [(kind, name, dtype[, count dtype]), ...]), ...]; `order`: the
    binary byte order ("<" or ">"), None for ASCII.
    """
    vertex = next((e for e in elements if e[0] == "vertex"), None)
    if vertex is None:
        raise InputError(f"cannot read {path}: its PLY header declares no vertex element")
    scalars = [p[1] for p in vertex[2] if p[0] == "scalar"]
    for axis in "xyz":
        if axis not in scalars:
            raise InputError(f"cannot read {path}: its vertices have no {axis!r} property (x, y and z are needed)")
    for name, count, _ in elements:
        if count < 0:
            raise InputError(f"cannot read {path}: its PLY header declares {count} {name} elements")
    try:
        if order is None:
            _ascii_rows_end(body.split(), elements, vertex[1])
        else:
            _binary_rows_end(body, elements, order, vertex[1])
    except _Truncated as cut:
        raise InputError(
            f"cannot read {path}: truncated: its header declares {cut.count} {cut.name} elements, "
            f"the file ends in {cut.name} {cut.index}"
        ) from None
    except (ValueError, OverflowError) as exc:  # a bad list length or face: Open3D crashes on some
        raise InputError(f"cannot read {path}: malformed PLY body ({exc})") from None


def _check_faces(name: str, prop: tuple[str, ...], first: int, indices: np.ndarray, n_vertices: int) -> None:
    """ValueError unless these faces (rows from `first`) have >= 3 indices, each of an existing vertex.

    Open3D's reader crashes the process (segmentation fault) on a face of no index.
    """
    if name != "face" or prop[1] not in FACE_LISTS:
        return
    if indices.shape[-1] < 3:
        raise ValueError(f"face {first} has {indices.shape[-1]} vertex indices, a face needs 3 or more")
    bad = (indices < 0) | (indices >= n_vertices)
    if bad.any():
        row = int(np.argmax(bad.any(axis=-1)))
        raise ValueError(f"face {first + row} refers to vertex {indices[row][bad[row]][0]} of {n_vertices}")


def _binary_rows_end(body: bytes, elements: list, order: str, n_vertices: int) -> int:
    """Byte offset where the declared rows of all elements end; _Truncated if the body ends before."""
    offset = 0
    for name, count, props in elements:
        start, index = offset, 0
        if all(p[0] == "scalar" for p in props):  # fixed-size rows: no walk needed
            size = np.dtype([(f"p{i}", order + p[2]) for i, p in enumerate(props)]).itemsize
            offset += count * size
            if offset > len(body):
                raise _Truncated(name, count, (len(body) - start) // max(size, 1))
            continue
        # Rows with lists: read as one record type while the lists keep one row's lengths (all
        # triangles, all quads), so only a change of length costs a step. Each step looks at twice
        # the last run's rows at most: mixed polygons stay linear.
        limit = count
        while index < count:
            row_type = _binary_row_type(body, offset, props, order, name, count, index)
            fit = min(count - index, (len(body) - offset) // row_type.itemsize, limit)
            table = np.frombuffer(body, dtype=row_type, count=fit, offset=offset)
            same = np.ones(fit, bool)
            for i, p in enumerate(props):
                if p[0] == "list":
                    same &= table[f"n{i}"] == table[f"n{i}"][:1]
            run = fit if same.all() else int(np.argmin(same))  # row 0 always matches itself: run >= 1
            for i, p in enumerate(props):
                if p[0] == "list":
                    _check_faces(name, p, index, table[f"v{i}"][:run], n_vertices)
            index, offset = index + run, offset + run * row_type.itemsize
            limit = max(2 * run, 16)
    return offset


def _binary_row_type(body: bytes, offset: int, props: list, order: str, name: str, count: int, index: int) -> np.dtype:
    """The record type of the row at `offset` (its lists' lengths read from it); _Truncated if it does not fit."""
    fields, end = [], offset
    for i, p in enumerate(props):
        if p[0] == "scalar":
            fields.append((f"p{i}", order + p[2]))
            end += np.dtype(p[2]).itemsize
            continue
        count_type = np.dtype(order + p[3])
        if end + count_type.itemsize > len(body):
            raise _Truncated(name, count, index)
        length = int(np.frombuffer(body, dtype=count_type, count=1, offset=end)[0])
        if length < 0:
            raise ValueError(f"{name} {index} has a list of length {length}")
        fields += [(f"n{i}", count_type), (f"v{i}", order + p[2], (length,))]
        end += count_type.itemsize + length * np.dtype(p[2]).itemsize
    if end > len(body):
        raise _Truncated(name, count, index)
    return np.dtype(fields)


def _ascii_rows_end(words: list[bytes], elements: list, n_vertices: int) -> int:
    """Word index where the declared rows of all elements end; _Truncated if the body ends before."""
    position = 0
    for name, count, props in elements:
        start = position
        if all(p[0] == "scalar" for p in props):
            position += count * len(props)
            if position > len(words):
                raise _Truncated(name, count, (len(words) - start) // max(len(props), 1))
            continue
        uniform = _ascii_uniform_rows(words, position, name, count, props, n_vertices)
        if uniform is not None:
            position = uniform
            continue
        for index in range(count):  # mixed list lengths: row by row
            for p in props:
                if p[0] == "list":
                    if position >= len(words):
                        raise _Truncated(name, count, index)
                    length = int(float(words[position]))
                    if length < 0:
                        raise ValueError(f"{name} {index} has a list of length {length}")
                    if position + 1 + length > len(words):
                        raise _Truncated(name, count, index)
                    if name == "face" and p[1] in FACE_LISTS:
                        row = [int(float(w)) for w in words[position + 1 : position + 1 + length]]
                        _check_faces(name, p, index, np.array([row], np.int64), n_vertices)
                    position += length
                position += 1
            if position > len(words):
                raise _Truncated(name, count, index)
    return position


def _ascii_uniform_rows(
    words: list[bytes], position: int, name: str, count: int, props: list, n_vertices: int
) -> int | None:
    """Where an element's rows end when its one list has the same length in every row (all triangles), checked
    as one array; None when it does not (or it has several lists): the row walk then decides.

    Row by row, a face's indices cost a Python loop each: 2 s more for a 360k-face ASCII mesh.
    """
    lists = [i for i, p in enumerate(props) if p[0] == "list"]
    if count == 0 or len(lists) != 1 or position + lists[0] >= len(words):
        return None
    at = lists[0]
    try:
        length = int(float(words[position + at]))
    except ValueError:
        return None
    width = len(props) + length
    end = position + count * width
    if length < 0 or end > len(words):
        return None
    try:
        rows = np.array(words[position:end], dtype="S").astype(np.float64).reshape(count, width)
    except ValueError:
        return None
    if not (rows[:, at] == length).all():  # another length somewhere: the walk finds where
        return None
    _check_faces(name, props[at], 0, rows[:, at + 1 : at + 1 + length].astype(np.int64), n_vertices)
    return end
