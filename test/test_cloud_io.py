"""Cloud/mesh reading and cleaning: formats, NaN handling, clear errors."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import pytest

from liver_p2p_reg.cloud_io import (
    clean_points,
    extent_mm,
    implausible_extent,
    load_mesh,
    load_points,
    save_points,
)
from liver_p2p_reg.errors import InputError


def _blob(rng: np.random.Generator, n: int = 500) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return 80.0 * d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".xyz", ".npy"])
def test_round_trip(tmp_path: Path, rng: np.random.Generator, suffix: str) -> None:
    pts = _blob(rng)
    path = tmp_path / f"cloud{suffix}"
    save_points(path, pts)
    loaded = load_points(path)
    assert loaded.shape == pts.shape
    np.testing.assert_allclose(loaded, pts, atol=1e-4)


def test_npz_keys(tmp_path: Path, rng: np.random.Generator) -> None:
    pts = _blob(rng)
    path = tmp_path / "case.npz"
    np.savez(path, src_pcd=pts, tgt_pcd=pts[:100])
    # A dataset case holds the complete surface and the partial view: no array is picked by name
    # (the target used to be read as src_pcd, the complete surface), the choice is the user's.
    with pytest.raises(InputError, match=r"case.npz holds several point arrays \(src_pcd, tgt_pcd\)") as info:
        load_points(path)
    assert "\n" not in str(info.value)
    np.testing.assert_array_equal(load_points(path, key="tgt_pcd"), pts[:100])
    with pytest.raises(InputError, match="no array named"):
        load_points(path, key="nope")
    np.savez(path, src_pcd=pts, points=pts[:50])  # the documented key wins
    np.testing.assert_array_equal(load_points(path), pts[:50])
    np.savez(path, surface=pts[:70], labels=np.arange(70))  # the one (N, 3) array, whatever its name
    np.testing.assert_array_equal(load_points(path), pts[:70])
    np.savez(path, vertices=pts, triangles=np.zeros((9, 3), np.int32))  # a mesh of no area: its vertices only
    np.testing.assert_array_equal(load_points(path), pts)
    np.savez(path, xyz=pts[:60], normals=pts[:60] / 10)  # a cloud with its normals: the named coordinates
    np.testing.assert_array_equal(load_points(path), pts[:60])
    np.savez(path, surface=pts[:80], rotation=np.eye(3))  # a (3, 3) matrix is no cloud
    np.testing.assert_array_equal(load_points(path), pts[:80])


def test_mesh_is_sampled_over_its_surface(tmp_path: Path) -> None:
    # A 100 mm cube as an OBJ: 8 vertices only, so sampling must add surface points.
    v = np.array([[x, y, z] for x in (0, 100) for y in (0, 100) for z in (0, 100)], float)
    faces = [(1, 2, 4), (1, 4, 3), (5, 7, 8), (5, 8, 6), (1, 5, 6), (1, 6, 2),
             (3, 4, 8), (3, 8, 7), (1, 3, 7), (1, 7, 5), (2, 6, 8), (2, 8, 4)]  # fmt: skip
    path = tmp_path / "cube.obj"
    path.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in v) + "".join(f"f {a} {b} {c}\n" for a, b, c in faces))
    pts = load_points(path)
    assert len(pts) > 1000
    # Every sample lies on the cube's surface: one coordinate at 0 or 100.
    on_face = np.isclose(pts, 0, atol=1e-6) | np.isclose(pts, 100, atol=1e-6)
    assert on_face.any(axis=1).all()
    np.testing.assert_array_equal(load_points(path), pts)  # deterministic


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("missing.ply", None, "file not found"),
        ("cloud.abc", b"1 2 3", "unsupported format"),
        ("bad.npy", b"not numpy", "cannot read"),
        ("empty.ply", b"", "cannot read"),
        ("text.xyz", b"a b c\n", "cannot read"),
        ("empty.xyz", b"", "no points in the file"),
        ("garbage.ply", b"\x00\x01 not a ply file", "not a PLY file"),
    ],
)
def test_bad_files(
    tmp_path: Path, capfd: pytest.CaptureFixture, recwarn: pytest.WarningsRecorder, name: str, content, message: str
) -> None:
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputError, match=message):
        load_points(path)
    # The error is the only report: no Python warning, nothing printed by a C++ reader.
    assert len(recwarn) == 0 and capfd.readouterr().err == ""


def test_extent_says_when_units_look_wrong(rng: np.random.Generator) -> None:
    liver = _blob(rng)  # 160 mm across
    assert extent_mm(liver) == pytest.approx(np.linalg.norm(liver.max(0) - liver.min(0)))
    assert implausible_extent(extent_mm(liver), "target", 20.0, 600.0) == ""
    assert "below 20 mm: wrong units?" in implausible_extent(extent_mm(liver / 1000), "target", 20.0, 600.0)
    assert "exceeds 600 mm: wrong units?" in implausible_extent(extent_mm(liver * 1000), "target", 20.0, 600.0)


def test_clean_points_drops_nan_and_refuses_empty(rng: np.random.Generator) -> None:
    pts = _blob(rng, 50)
    pts[3] = np.nan
    pts[7, 1] = np.inf
    cleaned = clean_points(pts, "target")
    assert len(cleaned) == 48 and np.isfinite(cleaned).all()
    with pytest.raises(InputError, match="all 4 points are NaN"):
        clean_points(np.full((4, 3), np.nan), "target")
    with pytest.raises(InputError, match="empty"):
        clean_points(np.zeros((0, 3)), "target")
    with pytest.raises(InputError, match="at least 100"):
        clean_points(pts[:10], "target", min_points=100)
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        clean_points(np.zeros((5, 2)), "target")


def _ply(path: Path, fmt: str, vtype: str, vertices: np.ndarray, faces: np.ndarray | None, extra: bool) -> Path:
    """A PLY file written by hand (not by either reader under test)."""
    header = ["ply", f"format {fmt} 1.0", "comment hand-made", f"element vertex {len(vertices)}"]
    header += [f"property {vtype} {a}" for a in "xyz"] + (["property uchar red", "property float nx"] if extra else [])
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    text = "\n".join([*header, "end_header"]) + "\n"
    if fmt == "ascii":
        rows = [" ".join([*(repr(float(x)) for x in v), *(["7", "0.25"] if extra else [])]) for v in vertices]
        rows += [] if faces is None else [f"3 {a} {b} {c}" for a, b, c in faces]
        path.write_text(text + "\n".join(rows) + "\n")
        return path
    order = "<" if fmt == "binary_little_endian" else ">"
    kind = order + {"float": "f4", "double": "f8"}[vtype]
    fields = [(a, kind) for a in "xyz"] + ([("red", "u1"), ("nx", order + "f4")] if extra else [])
    table = np.zeros(len(vertices), dtype=fields)
    for i, a in enumerate("xyz"):
        table[a] = vertices[:, i]
    body = table.tobytes()
    if faces is not None:
        face_table = np.zeros(len(faces), dtype=[("n", "u1"), ("v", order + "i4", (3,))])
        face_table["n"], face_table["v"] = 3, faces
        body += face_table.tobytes()
    path.write_bytes(text.encode() + body)
    return path


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("vtype", ["float", "double"])
@pytest.mark.parametrize(("with_faces", "extra"), [(True, False), (False, True)])
def test_ply_is_read_to_the_same_bits_as_open3d_reads_it(
    tmp_path: Path, rng: np.random.Generator, fmt: str, vtype: str, with_faces: bool, extra: bool
) -> None:
    """The numpy reader (no Open3D import) must not change a single input bit: results stay identical."""
    from liver_p2p_reg.o3d import o3d_module
    from liver_p2p_reg.ply_pcd import read_ply

    vertices = _blob(rng, 300) + rng.normal(size=(300, 3)) * 1e-7  # digits beyond float32
    faces = rng.integers(0, 300, size=(200, 3)) if with_faces else None
    path = _ply(tmp_path / "m.ply", fmt, vtype, vertices, faces, extra)
    mesh = o3d_module().io.read_triangle_mesh(str(path))
    ours = read_ply(path)
    assert ours is not None
    assert ours[0].tobytes() == np.asarray(mesh.vertices).tobytes()
    assert np.array_equal(ours[1], np.asarray(mesh.triangles).reshape(-1, 3))


@pytest.mark.parametrize("ascii", [True, False])
def test_pcd_is_read_to_the_same_bits_as_open3d_reads_it(tmp_path: Path, rng: np.random.Generator, ascii: bool) -> None:
    from liver_p2p_reg.o3d import o3d_module
    from liver_p2p_reg.ply_pcd import read_pcd

    o3d = o3d_module()
    path = str(tmp_path / "c.pcd")
    o3d.io.write_point_cloud(path, o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_blob(rng))), write_ascii=ascii)
    assert read_pcd(Path(path)).tobytes() == np.asarray(o3d.io.read_point_cloud(path).points).tobytes()


def test_layouts_the_numpy_reader_leaves_out_go_to_open3d_quietly(tmp_path: Path, capfd: pytest.CaptureFixture) -> None:
    from liver_p2p_reg.ply_pcd import read_ply

    # A quad mesh (Open3D triangulates polygons) and a vertex-only file Open3D reads with a warning.
    quad = tmp_path / "quad.ply"
    quad.write_text(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n100 0 0\n100 100 0\n0 100 0\n4 0 1 2 3\n"
    )
    assert read_ply(quad) is None
    points = load_points(quad)
    assert len(points) > 1000 and np.allclose(points[:, 2], 0)  # two triangles, sampled
    listed = tmp_path / "listed.ply"  # a list property on the vertices: also Open3D's job
    listed.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "property list uchar int tags\nend_header\n0 0 0 1 5\n50 0 0 1 5\n0 50 0 1 5\n"
    )
    assert read_ply(listed) is None
    assert load_points(listed).shape == (3, 3)
    assert capfd.readouterr().out == ""  # Open3D's coloured warnings stay silent


def test_pts_with_a_point_count_line(tmp_path: Path, rng: np.random.Generator) -> None:
    pts = _blob(rng, 50)
    path = tmp_path / "cloud.pts"
    path.write_text(f"{len(pts)}\n" + "".join(f"{x!r} {y!r} {z!r} 0.5\n" for x, y, z in pts.tolist()))
    np.testing.assert_array_equal(load_points(path), pts)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
@pytest.mark.parametrize("with_faces", [True, False])
def test_truncated_ply_is_refused_not_zero_filled(
    tmp_path: Path, rng: np.random.Generator, capfd: pytest.CaptureFixture, fmt: str, with_faces: bool
) -> None:
    """The first half of a PLY used to load with the missing points as (0, 0, 0) (Open3D's fallback)."""
    faces = rng.integers(0, 300, size=(400, 3)) if with_faces else None
    whole = _ply(tmp_path / "whole.ply", fmt, "float", _blob(rng, 300), faces, extra=False).read_bytes()
    half = tmp_path / "half.ply"
    half.write_bytes(whole[: len(whole) // 2])
    # ASCII vertices take more bytes than its faces: the half ends in the vertices there
    element = "400 face" if with_faces and fmt != "ascii" else "300 vertex"
    with pytest.raises(
        InputError, match=rf"cannot read .*half.ply: truncated: its header declares {element} elements"
    ) as info:
        load_points(half)
    assert "\n" not in str(info.value) and capfd.readouterr().err == ""


def test_ply_header_declaring_more_points_than_the_file_holds(tmp_path: Path, rng: np.random.Generator) -> None:
    whole = tmp_path / "cloud.ply"
    save_points(whole, _blob(rng, 200))
    more = tmp_path / "more.ply"
    more.write_bytes(whole.read_bytes().replace(b"element vertex 200", b"element vertex 300", 1))
    with pytest.raises(
        InputError, match="truncated: its header declares 300 vertex elements, the file ends in vertex 200"
    ):
        load_points(more)


def test_truncated_polygon_ply_left_to_open3d_is_refused_too(tmp_path: Path) -> None:
    """Layouts the numpy reader leaves to Open3D (quads here) are checked for truncation as well."""
    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
        "property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
    )
    vertices = np.array([[0, 0, 0], [100, 0, 0], [100, 100, 0], [0, 100, 0]], "<f4").tobytes()
    quads = np.array([(4, (0, 1, 2, 3))] * 2, dtype=[("n", "u1"), ("v", "<i4", (4,))]).tobytes()
    whole = tmp_path / "quads.ply"
    whole.write_bytes(header.encode() + vertices + quads)
    assert len(load_points(whole)) > 1000  # the whole file: Open3D triangulates the quads
    cut = tmp_path / "cut.ply"
    cut.write_bytes(whole.read_bytes()[:-5])
    with pytest.raises(InputError, match="truncated: its header declares 2 face elements, the file ends in face 1"):
        load_points(cut)


def test_ply_without_z_says_so(tmp_path: Path, rng: np.random.Generator) -> None:
    """x, y only: Open3D's fallback used to give uninitialized z values (4.7e-310 ...)."""
    xy = np.ascontiguousarray(_blob(rng, 100)[:, :2], "<f8")
    path = tmp_path / "xy.ply"
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty double x\nproperty double y\n"
    path.write_bytes((header + "end_header\n").encode() + xy.tobytes())
    with pytest.raises(InputError, match="its vertices have no 'z' property"):
        load_points(path)


@pytest.mark.parametrize("ascii", [True, False])
def test_truncated_pcd_is_refused(tmp_path: Path, rng: np.random.Generator, ascii: bool) -> None:
    from liver_p2p_reg.o3d import o3d_module

    o3d = o3d_module()
    whole = tmp_path / "whole.pcd"
    o3d.io.write_point_cloud(
        str(whole), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_blob(rng, 200))), write_ascii=ascii
    )
    half = tmp_path / "half.pcd"
    half.write_bytes(whole.read_bytes()[: -len(whole.read_bytes()) // 3])
    with pytest.raises(InputError, match=r"truncated: its header declares 200 points, the file holds \d+$"):
        load_points(half)


@pytest.mark.parametrize(
    ("values", "message"),
    [
        (np.ones((20, 3), complex), "complex numbers are not coordinates"),
        (np.array([["a", "b", "c"]] * 20), r"holds text \(<U1\), not coordinates"),
        (np.ones((20, 3), bool), "holds true/false values"),
    ],
)
def test_npy_of_other_than_real_numbers_is_refused(
    tmp_path: Path, recwarn: pytest.WarningsRecorder, values: np.ndarray, message: str
) -> None:
    """Complex values lost their imaginary part with a ComplexWarning; text was an internal ValueError."""
    path = tmp_path / "cloud.npy"
    np.save(path, values)
    with pytest.raises(InputError, match=message):
        load_points(path)
    np.savez(tmp_path / "cloud.npz", points=values)
    with pytest.raises(InputError, match=message):
        load_points(tmp_path / "cloud.npz")
    assert len(recwarn) == 0


def test_a_named_pipe_is_refused_without_opening_it(tmp_path: Path) -> None:
    """Opening a FIFO blocks until a writer comes: it used to hang `register` forever."""
    import os
    import signal

    from liver_p2p_reg.cloud_io import check_point_file, load_mesh

    fifo = tmp_path / "fifo.ply"
    os.mkfifo(fifo)

    def hang(*_: object) -> None:
        raise TimeoutError("blocked on the pipe")

    previous = signal.signal(signal.SIGALRM, hang)
    signal.alarm(10)
    try:
        for read in (load_points, load_mesh, check_point_file):
            with pytest.raises(InputError, match="not a regular file: .*fifo.ply"):
                read(fifo)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.mark.parametrize(
    ("faces", "message"),
    [
        ("0\n3 0 1 2\n", "face 0 has 0 vertex indices"),  # Open3D's reader crashed the process (SIGSEGV) on it
        ("3 0 1 2\n2 0 1\n", "face 1 has 2 vertex indices"),
        ("3 0 1 2\n3 0 1 7\n", "face 1 refers to vertex 7 of 3"),
    ],
)
def test_ply_faces_that_are_no_triangles_of_its_vertices_are_refused(tmp_path: Path, faces: str, message: str) -> None:
    header = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
    header += "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
    path = tmp_path / "faces.ply"
    path.write_text(header + "0 0 0\n100 0 0\n0 100 0\n" + faces)
    with pytest.raises(InputError, match=f"malformed PLY body \\({message}"):
        load_points(path)
    binary = tmp_path / "faces_binary.ply"  # the same faces in binary
    rows = [[int(w) for w in line.split()] for line in faces.splitlines()]
    body = np.array([[0, 0, 0], [100, 0, 0], [0, 100, 0]], "<f4").tobytes()
    body += b"".join(bytes([r[0]]) + np.array(r[1:], "<i4").tobytes() for r in rows)
    binary.write_bytes(header.replace("ascii", "binary_little_endian").encode() + body)
    with pytest.raises(InputError, match=f"malformed PLY body \\({message}"):
        load_points(binary)


def test_ply_header_quirks_are_parsed_or_refused_never_handed_to_open3d(
    tmp_path: Path, rng: np.random.Generator
) -> None:
    """A non-ASCII comment used to skip the checks (Open3D then zero-filled a truncated body or crashed the process
    on an empty face), a `comment end_header` line cut the header short, and a header over 64 KiB aborted Open3D."""
    points = _blob(rng, 200)
    whole = tmp_path / "cloud.ply"
    save_points(whole, points)
    data = whole.read_bytes()
    accented = tmp_path / "accented.ply"
    accented.write_bytes(data.replace(b"end_header\n", "comment café ü\nend_header\n".encode("latin-1"), 1))
    np.testing.assert_array_equal(load_points(accented), load_points(whole))
    cut = tmp_path / "accented_cut.ply"
    cut.write_bytes(accented.read_bytes()[: -len(data) // 3])
    with pytest.raises(InputError, match="truncated: its header declares 200 vertex elements"):
        load_points(cut)
    worded = tmp_path / "worded.ply"  # the word in a comment is no end of the header
    worded.write_bytes(data.replace(b"end_header\n", b"comment end_header here\nend_header\n", 1))
    np.testing.assert_array_equal(load_points(worded), load_points(whole))
    long = tmp_path / "long.ply"
    long.write_bytes(data.replace(b"end_header\n", b"comment " + b"x" * 70_000 + b"\nend_header\n", 1))
    with pytest.raises(InputError, match="malformed PLY header .no 'end_header' line within the first 64 KiB"):
        load_points(long)


def test_pcd_with_a_non_ascii_comment_is_still_checked(tmp_path: Path, rng: np.random.Generator) -> None:
    whole = tmp_path / "cloud.pcd"
    save_points(whole, _blob(rng, 100))
    data = whole.read_bytes().replace(b"VERSION", "# café\nVERSION".encode("latin-1"), 1)
    cut = tmp_path / "cut.pcd"
    cut.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(InputError, match="truncated: its header declares 100 points"):
        load_points(cut)


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("3 1 0\n0 0 0\n100 0 0\n0 100 0\n0\n", "face 0 has 0 vertex indices"),  # Open3D crashed (SIGSEGV) on it
        ("3 1 0\n0 0 0\n100 0 0\n0 100 0\n3 0 1 -1\n", "face 0 refers to vertex -1 of 3"),  # Open3D counted back
        ("3 1 0\n0 0 0\n100 0 0\n0 100 0\n3 0 1 3\n", "face 0 refers to vertex 3 of 3"),
        ("3 1 0\n0 0 0\n100 0 0\n0 100 0\n4 0 1 2\n", "face 0 declares 4 indices and holds 3"),
        ("5 1 0\n0 0 0\n100 0 0\n0 100 0\n3 0 1 2\n", "truncated: its header declares 5 vertices"),
        ("-3 1 0\n", "declares -3 vertices"),
    ],
)
def test_off_files_are_checked_before_open3d_reads_them(tmp_path: Path, body: str, message: str) -> None:
    path = tmp_path / "mesh.off"
    path.write_text("OFF\n" + body)
    with pytest.raises(InputError, match=message) as info:
        load_points(path)
    assert "\n" not in str(info.value)


def test_off_vertices_alone_are_a_cloud_and_a_good_mesh_still_loads(tmp_path: Path, rng: np.random.Generator) -> None:
    pts = _blob(rng, 50)
    cloud = tmp_path / "cloud.off"
    cloud.write_text("OFF\n# vertices only\n50 0 0\n" + "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in pts.tolist()))
    np.testing.assert_array_equal(load_points(cloud), pts)
    mesh = tmp_path / "mesh.off"  # counts on the OFF line (Open3D refused them), a quad, a face colour
    mesh.write_text("OFF 4 2 0\n0 0 0\n100 0 0\n100 100 0\n0 100 0\n3 0 1 2\n4 0 1 2 3 255 0 0\n")
    points = load_points(mesh)
    assert len(points) > 1000 and np.allclose(points[:, 2], 0)


def test_off_is_read_as_open3d_reads_it_in_full_precision(tmp_path: Path, rng: np.random.Generator) -> None:
    """The same triangles as Open3D's reader, and the vertices as written (Open3D parses them as float32). (Polygons
    are split into fans here; Open3D ear-clips them, which covers the same surface where a polygon is planar and
    convex, and fails on others.)"""
    from liver_p2p_reg.cloud_io import load_mesh

    o3d = pytest.importorskip("open3d")
    pts = _blob(rng, 300)
    faces = rng.integers(0, 300, size=(200, 3))
    path = tmp_path / "mesh.off"
    rows = [f"{x!r} {y!r} {z!r}" for x, y, z in pts.tolist()] + [f"3 {a} {b} {c}" for a, b, c in faces]
    path.write_text("OFF\n300 200 0\n" + "\n".join(rows) + "\n")
    vertices, triangles = load_mesh(path)
    theirs = o3d.io.read_triangle_mesh(str(path))
    assert vertices.tobytes() == pts.tobytes()  # repr() round-trips: the file's numbers exactly
    np.testing.assert_array_equal(vertices.astype(np.float32), np.asarray(theirs.vertices))
    np.testing.assert_array_equal(triangles, np.asarray(theirs.triangles))


@pytest.mark.parametrize("suffix", [".npy", ".npz"])
def test_a_damaged_numpy_file_is_not_called_pickled_data(tmp_path: Path, rng: np.random.Generator, suffix: str) -> None:
    path = tmp_path / f"damaged{suffix}"
    path.write_bytes(rng.integers(0, 256, 4000, dtype=np.uint8).tobytes())
    with pytest.raises(InputError, match=f"not a NumPy {suffix}") as info:
        load_points(path)
    assert "pickle" not in str(info.value)


def test_obj_vertices_alone_are_a_cloud(tmp_path: Path, rng: np.random.Generator) -> None:
    pts = _blob(rng, 40)
    path = tmp_path / "cloud.obj"
    path.write_text("# scanner export\n" + "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in pts.tolist()))
    np.testing.assert_array_equal(load_points(path), pts)
    short = tmp_path / "short.obj"
    short.write_text("v 1 2 3\nv 4 5\n")
    with pytest.raises(InputError, match=r"vertex 2 \(line 2\) has fewer than 3 coordinates"):
        load_points(short)


def test_ply_line_ending_quirks_rply_reads_are_read_too(tmp_path: Path) -> None:
    body = "0 0 0\n100 0 0\n0 100 0\n"
    header = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
    expected = np.array([[0, 0, 0], [100, 0, 0], [0, 100, 0]], float)
    for name, text in (("cr.ply", (header + "end_header\n" + body).replace("\n", "\r")),
                       ("blank.ply", header + "  end_header \n" + body)):  # fmt: skip
        path = tmp_path / name
        path.write_bytes(text.encode())
        np.testing.assert_array_equal(load_points(path), expected)


def test_pcd_with_the_word_data_in_a_comment_is_still_checked(tmp_path: Path, rng: np.random.Generator) -> None:
    whole = tmp_path / "cloud.pcd"
    save_points(whole, _blob(rng, 100))
    data = whole.read_bytes().replace(b"VERSION", b"# DATA from the scanner\nVERSION", 1)
    commented = tmp_path / "commented.pcd"
    commented.write_bytes(data)
    np.testing.assert_array_equal(load_points(commented), load_points(whole))
    cut = tmp_path / "cut.pcd"
    cut.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(InputError, match="truncated: its header declares 100 points"):
        load_points(cut)


@pytest.mark.parametrize(
    ("face", "message"),
    [
        ("f 1 2 9", "face 2 (line 6) refers to vertex 9 of 4"),  # a vertex that is not there
        ("f 0 1 2", "face 2 (line 6) refers to vertex 0 of 4"),  # OBJ counts from 1
        ("f 1 2 99999999999", "face 2 (line 6) refers to vertex 99999999999 of 4"),
        ("f -1 -2 -5", "face 2 (line 6) refers to vertex -5 of 4"),  # back from the last vertex read
        ("f 1 x 3", "face 2 (line 6) is not integers: 'x'"),
    ],
)
def test_an_obj_face_open3d_cannot_read_is_named(tmp_path: Path, face: str, message: str) -> None:
    path = tmp_path / "broken.obj"
    path.write_text(f"v 0 0 0\nv 100 0 0\nv 0 100 0\nv 0 0 100\nf 1 2 3\n{face}\n")
    with pytest.raises(InputError, match=re.escape(f"cannot read {path}: {message}")) as info:
        load_points(path)
    assert "\n" not in str(info.value)


def test_an_npz_mesh_is_read_like_a_ply(tmp_path: Path) -> None:
    vertices, triangles = _cube_mm()
    ply, npz = tmp_path / "cube.ply", tmp_path / "cube.npz"
    _write_ascii_ply(ply, vertices, triangles)
    np.savez(npz, vertices=vertices, triangles=triangles.astype(np.int32))
    for got, want in zip(load_mesh(npz), (vertices, triangles), strict=True):
        np.testing.assert_array_equal(got, want)
    assert load_mesh(npz)[1].dtype == np.int64
    np.testing.assert_array_equal(load_points(npz), load_points(ply))  # sampled over its surface, as the PLY
    assert len(load_points(npz)) > 1000
    np.testing.assert_array_equal(load_points(npz, sample_meshes=False), vertices)
    np.savez(npz, vertices=vertices, faces=triangles)  # trimesh's name for them
    np.testing.assert_array_equal(load_mesh(npz)[1], triangles)
    np.testing.assert_array_equal(load_points(npz, key="vertices"), vertices)  # a named array is that array
    for bad, message in (
        (np.vstack([triangles, [[0, 1, 8]]]), "face 12 refers to vertex 8 of 8"),
        (np.vstack([triangles, [[0, -1, 2]]]), "face 12 refers to vertex -1 of 8"),
        (triangles.astype(float), r"triangles must be an \(F, 3\) integer array"),
        (triangles[:, :2], r"triangles must be an \(F, 3\) integer array"),
    ):
        np.savez(npz, vertices=vertices, triangles=bad)
        with pytest.raises(InputError, match=message):
            load_points(npz)
        with pytest.raises(InputError, match=message):
            load_mesh(npz)


def test_a_non_finite_mesh_vertex_is_dropped_with_its_triangles(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    vertices, triangles = _cube_mm()
    vertices = np.vstack([vertices[:3], [[np.nan, 0.0, 0.0]], vertices[3:]])  # the NaN vertex is number 3
    triangles = np.where(triangles >= 3, triangles + 1, triangles)
    triangles = np.vstack([triangles, [[3, 0, 1]]])  # one more triangle uses it
    path = tmp_path / "nan.ply"
    _write_ascii_ply(path, vertices, triangles)
    with caplog.at_level(logging.WARNING, logger="liver_p2p_reg"):
        got_vertices, got_triangles = load_mesh(path)
    assert [r.getMessage() for r in caplog.records] == [
        f"{path}: dropped 1 of 9 vertices with NaN/inf coordinates and the 1 of 13 triangles using them"
    ]
    clean_vertices, clean_triangles = _cube_mm()
    np.testing.assert_array_equal(got_vertices, clean_vertices)  # the rest, re-indexed: the cube again
    np.testing.assert_array_equal(got_triangles, clean_triangles)
    points = load_points(path)  # sampled over the rest of the surface, not degraded to its vertices
    assert np.isfinite(points).all() and len(points) > 1000
    np.testing.assert_array_equal(load_mesh(path, warn=False)[1], clean_triangles)
    everything = tmp_path / "all_nan.ply"
    _write_ascii_ply(everything, np.full((3, 3), np.nan), np.array([[0, 1, 2]]))
    with pytest.raises(InputError, match="all 3 vertices are NaN or infinite"):
        load_points(everything)
    cloud = tmp_path / "cloud.ply"  # a cloud keeps its NaN rows: clean_points (or a structure's check) says so
    _write_ascii_ply(cloud, vertices, np.zeros((0, 3), int))
    assert np.isnan(load_points(cloud)).any()


def _cube_mm() -> tuple[np.ndarray, np.ndarray]:
    """A closed 100 mm cube: 8 vertices, 12 outward triangles."""
    v = np.array([[x, y, z] for x in (0, 100) for y in (0, 100) for z in (0, 100)], float)
    faces = [(1, 2, 4), (1, 4, 3), (5, 7, 8), (5, 8, 6), (1, 5, 6), (1, 6, 2),
             (3, 4, 8), (3, 8, 7), (1, 3, 7), (1, 7, 5), (2, 6, 8), (2, 8, 4)]  # fmt: skip
    return v, np.array(faces, np.int64) - 1


def _write_ascii_ply(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> None:
    header = (
        f"ply\nformat ascii 1.0\nelement vertex {len(vertices)}\nproperty double x\nproperty double y\n"
        f"property double z\nelement face {len(triangles)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    body = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in vertices.tolist())
    path.write_text(header + body + "".join(f"3 {a} {b} {c}\n" for a, b, c in triangles.tolist()))
