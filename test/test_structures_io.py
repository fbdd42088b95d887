"""Structure files (`FILE[:LABEL]`, mm, preop frame): what is read, what is refused in one line, and where a pose puts them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from synthetic_cases import partial_case

from liver_p2p_reg.cloud_io import save_points
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.registration.registrar import Registrar
from liver_p2p_reg.structures_io import (
    Structure,
    load_structures,
    parse_spec,
    place_structures,
    read_structures,
    structure_bounds,
)

ASCII_CUBE_PLY = """ply
format ascii 1.0
element vertex 4
property float x
property float y
property float z
element face 2
property list uchar int vertex_indices
end_header
100 -200 40
130 -200 40
100 -170 40
100 -200 70
3 0 1 2
3 0 1 3
"""


def tumour_mm(rng: np.random.Generator, centre=(10.0, -200.0, 40.0), radius_mm: float = 2.5) -> np.ndarray:
    """A 5 mm tumour (a ball of points) placed inside a liver about 200 mm from the CT origin."""
    d = rng.normal(size=(40, 3))
    return np.asarray(centre) + d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0, radius_mm, (40, 1))


def test_specs_label_defaults_to_the_stem_and_a_colon_in_a_folder_is_no_label(tmp_path: Path) -> None:
    assert parse_spec("/data/tumour_a.ply") == (Path("/data/tumour_a.ply"), "tumour_a")
    assert parse_spec("/data/t.ply:Segment VIII") == (Path("/data/t.ply"), "Segment VIII")
    assert parse_spec("/mnt/c:d/t.ply") == (Path("/mnt/c:d/t.ply"), "t")  # the text after ':' holds a '/'
    odd = tmp_path / "a:b.xyz"  # an existing file whose name holds a colon is that file
    odd.write_text("1 2 3\n")
    assert parse_spec(str(odd)) == (odd, "a:b")
    for bad in ("t.ply:", "t.ply: padded", ":tumour"):
        with pytest.raises(InputError, match="structure"):
            parse_spec(bad)


def test_formats_a_mesh_gives_its_vertices_and_a_small_tumour_far_from_the_origin_is_accepted(
    tmp_path: Path, rng: np.random.Generator
) -> None:
    tumour = tumour_mm(rng)
    for name in ("t.xyz", "t.npy", "t.ply", "t.pcd"):
        save_points(tmp_path / name, tumour)
    (tmp_path / "mesh.ply").write_text(ASCII_CUBE_PLY)
    specs = [str(tmp_path / n) for n in ("t.xyz", "t.npy", "t.ply", "t.pcd")]
    specs = [f"{spec}:{i}" for i, spec in enumerate(specs)] + [str(tmp_path / "mesh.ply")]
    structures = load_structures(specs)
    assert [s.label for s in structures] == ["0", "1", "2", "3", "mesh"]
    assert [s.label_id for s in structures] == [0, 1, 2, 3, 4]
    for s in structures[:4]:
        np.testing.assert_allclose(s.points_mm, tumour, atol=1e-4)  # float32 in PLY/PCD
    np.testing.assert_array_equal(structures[4].points_mm[:, 0], [100, 130, 100, 100])  # vertices, not a sampling
    one = tmp_path / "centre.xyz"  # a single point (a tumour's centre) is a structure too
    one.write_text("12.5 -180 33\n")
    assert load_structures([str(one)])[0].points_mm.shape == (1, 3)
    scaled = load_structures([f"{tmp_path / 't.npy'}:m"], to_mm=10.0)[0]  # the loader's units=m path
    np.testing.assert_allclose(scaled.points_mm, tumour * 10.0)


def test_bad_files_are_one_line_naming_the_file(tmp_path: Path, rng: np.random.Generator) -> None:
    tumour = tumour_mm(rng)
    (tmp_path / "empty.xyz").write_text("")
    with_nan = tumour.copy()
    with_nan[3, 1] = np.nan
    np.save(tmp_path / "nan.npy", with_nan)
    np.save(tmp_path / "metres.npy", tumour / 1000.0)  # a 5 mm tumour at 0.2 m: every |coordinate| < 1
    far_metres = tumour / 1000.0 + [0.0, 0.0, -1.5]  # a CT table 1.5 m away: caught by the extent instead
    np.save(tmp_path / "far_metres.npy", far_metres)
    np.save(tmp_path / "huge.npy", tumour * 1000.0)  # micrometres
    (tmp_path / "notes.txt").write_text("1 2 3\n")
    cases = {
        "missing.ply": "not found",
        "empty.xyz": "no points",
        "nan.npy": "NaN or infinite",
        "metres.npy": "metres",
        "far_metres.npy": "below 1 mm",
        "huge.npy": "exceeds",
        "notes.txt": "unsupported format",
    }
    good, bad = read_structures([str(tmp_path / name) for name in cases])
    assert good == []
    assert [spec for spec, _ in bad] == [str(tmp_path / name) for name in cases]
    for (_, reason), (name, words) in zip(bad, cases.items(), strict=True):
        assert "\n" not in reason and name in reason and words in reason, reason
        assert reason.startswith(f"structure '{Path(name).stem}'")
    with pytest.raises(InputError, match="metres"):
        load_structures([str(tmp_path / "metres.npy")])


def test_a_label_given_twice_is_refused_the_second_time(tmp_path: Path, rng: np.random.Generator) -> None:
    save_points(tmp_path / "a.xyz", tumour_mm(rng))
    save_points(tmp_path / "b.xyz", tumour_mm(rng, centre=(30.0, -190.0, 50.0)))
    good, bad = read_structures(
        [f"{tmp_path / 'a.xyz'}:tumour", f"{tmp_path / 'b.xyz'}:tumour", str(tmp_path / "b.xyz")]
    )
    assert [(s.label, s.label_id) for s in good] == [("tumour", 0), ("b", 1)]  # ids stay dense
    assert len(bad) == 1 and "given twice" in bad[0][1] and "a.xyz" in bad[0][1]
    with pytest.raises(InputError, match="given twice"):
        load_structures([f"{tmp_path / 'a.xyz'}:tumour", f"{tmp_path / 'b.xyz'}:tumour"])


def test_placed_structures_are_moved_by_the_pose_with_the_results_bounds(rng: np.random.Generator) -> None:
    source, target, T, fid_s, fid_t = partial_case(rng)
    result = Registrar(Config(method="procrustes")).register(
        source, target, source_fiducials_mm=fid_s, target_fiducials_mm=fid_t
    )
    inside = source.mean(axis=0)
    near, deep = tumour_mm(rng, centre=source[0] * 0.9 + 0.1 * inside), tumour_mm(rng, centre=inside)
    placed = place_structures(result, [Structure("near", near), Structure("deep", deep, label_id=1)])
    assert [(p.label, p.label_id) for p in placed] == [("near", 0), ("deep", 1)]
    for p, points in zip(placed, (near, deep), strict=True):
        np.testing.assert_allclose(p.position_mm, transform_points(result.T_target_source, points), atol=1e-9)
        np.testing.assert_array_equal(p.error_bound_mm, result.error_bound_at(points))
        assert np.isfinite(p.error_bound_mm).all() and (p.error_bound_mm > 0).all()
        assert p.coverage == result.error_coverage and p.deformed_position_mm is None
    entry = placed[0].to_json_dict()
    assert entry["label"] == "near" and len(entry["position_mm"]) == len(near) == len(entry["error_bound_mm"])
    assert entry["max_error_bound_mm"] == pytest.approx(max(entry["error_bound_mm"]))
    assert "deformed_position_mm" not in entry  # only once the non-rigid stage sets it
    assert set(structure_bounds(placed)) == {"near", "deep"}
    T2 = np.eye(4)
    T2[:3, 3] = [1.0, 2.0, 3.0]  # an explicit pose (the node's published one) wins over the result's
    np.testing.assert_allclose(place_structures(result, [Structure("near", near)], T2)[0].position_mm, near + [1, 2, 3])


def test_no_error_model_gives_nan_bounds_and_null_in_json(rng: np.random.Generator) -> None:
    from liver_p2p_reg.result import RegistrationResult

    result = RegistrationResult(T_target_source=np.eye(4), method="x", residual_mm=1.0)
    (placed,) = place_structures(result, [Structure("t", tumour_mm(rng))])
    assert np.isnan(placed.error_bound_mm).all()
    assert (
        set(placed.to_json_dict()["error_bound_mm"]) == {None} and placed.to_json_dict()["max_error_bound_mm"] is None
    )


def test_an_stl_mesh_gives_each_vertex_once(tmp_path: Path) -> None:
    from liver_p2p_reg.o3d import o3d_module

    o3d = o3d_module()
    vertices = np.array([[100.0, -200, 40], [130, -200, 40], [100, -170, 40], [100, -200, 70]])
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector([[0, 1, 2], [0, 1, 3], [0, 2, 3]])
    )
    mesh.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(tmp_path / "t.stl"), mesh)  # STL stores 3 vertices per triangle
    (structure,) = load_structures([str(tmp_path / "t.stl")])
    np.testing.assert_allclose(structure.points_mm, vertices, atol=1e-4)


def test_a_structure_of_more_points_than_the_cap_is_refused_in_one_line(tmp_path: Path) -> None:
    from liver_p2p_reg.structures_io import MAX_STRUCTURE_POINTS

    grid = np.stack(np.meshgrid(*[np.arange(60.0)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)  # 216,000 points
    assert len(grid) > MAX_STRUCTURE_POINTS
    np.save(tmp_path / "vessels.npy", grid)
    np.save(tmp_path / "at_cap.npy", grid[:MAX_STRUCTURE_POINTS])
    with pytest.raises(InputError) as info:
        load_structures([str(tmp_path / "vessels.npy")])
    assert str(info.value) == (
        f"structure 'vessels': {tmp_path / 'vessels.npy'}: 216000 points, more than the 200000 a structure may "
        "have: decimate it (a structure's points are reported one by one)"
    )
    assert len(load_structures([str(tmp_path / "at_cap.npy")])[0].points_mm) == MAX_STRUCTURE_POINTS
