"""Cloud/mesh reading and cleaning: formats, NaN handling, clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from liver_p2p_reg.cloud_io import clean_points, extent_mm, implausible_extent, load_points, save_points
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
    np.testing.assert_array_equal(load_points(path), pts)
    np.testing.assert_array_equal(load_points(path, key="tgt_pcd"), pts[:100])
    with pytest.raises(InputError, match="no array named"):
        load_points(path, key="nope")


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
