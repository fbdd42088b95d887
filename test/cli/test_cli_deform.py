"""`liver-p2p register --deform` on a mesh file and `benchmark` rows `METHOD+deform`: the JSON block, --moved, the table."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from liver_p2p_reg.bench.cases_csv import read_rows
from liver_p2p_reg.cli import main
from liver_p2p_reg.cloud_io import load_points, save_points
from liver_p2p_reg.phantom.dataset import make_case
from liver_p2p_reg.phantom.simulate import simulate_liver


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> dict:
    tmp = tmp_path_factory.mktemp("deform")
    sim = simulate_liver(7, 1, target_tets=2000)
    c = make_case(sim, 0, 0.35, seed=1)
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(c["src_pcd"]), o3d.utility.Vector3iVector(c["src_triangles"])
    )
    o3d.io.write_triangle_mesh(str(tmp / "preop.ply"), mesh)
    save_points(tmp / "view.ply", c["tgt_pcd"])
    np.save(tmp / "fs.npy", c["src_marker"])
    np.save(tmp / "ft.npy", c["tgt_marker"])
    # a small elastic model keeps the test fast
    (tmp / "small.yaml").write_text("method: fpfh-ransac-icp\ndeform_modes: 12\ndeform_target_tets: 1500\n")
    (tmp / "cases").mkdir()
    np.savez(tmp / "cases" / "case.npz", **{k: v for k, v in c.items() if not isinstance(v, dict)})
    return {"dir": tmp, "case": c}


def test_register_deform_writes_the_block_and_the_deformed_surface(case: dict) -> None:
    d = case["dir"]
    args = [str(d / "preop.ply"), str(d / "view.ply"), "--deform", "--config", str(d / "small.yaml")]
    args += ["--source-fiducials", str(d / "fs.npy"), "--target-fiducials", str(d / "ft.npy")]
    args += ["--output", str(d / "out.json"), "--moved", str(d / "moved.ply"), "-q"]
    assert main(["register", *args]) == 0
    payload = json.loads((d / "out.json").read_text())
    block = payload["deformation"]
    assert set(block) >= {"applied", "reason", "rms_displacement_mm", "max_displacement_mm", "strain_energy_mj"}
    assert block["iterations"] >= 1 and block["n_modes"] == 12 and block["model_build_ms"] > 0
    if block["applied"]:  # the fiducials' error where the deformation puts them; a stage not applied moved nothing
        assert isinstance(payload["deformed_rms_tre_mm"], float)
    else:
        assert "deformed_rms_tre_mm" not in payload
    moved = load_points(d / "moved.ply")
    rigid = load_points(d / "preop.ply") @ np.asarray(payload["transform"])[:3, :3].T  # the registered samples
    rigid += np.asarray(payload["transform"])[:3, 3]
    shift = np.linalg.norm(moved - rigid, axis=1)
    if block["applied"]:  # --moved is the deformed surface, not the rigidly moved one
        assert shift.max() > 0.01
    else:
        assert block["reason"] and np.allclose(shift, 0, atol=1e-3)


def test_benchmark_deform_rows_keep_their_rigid_error(case: dict, tmp_path: Path) -> None:
    d = case["dir"]
    args = ["benchmark", "--dataset", str(d / "cases"), "--out", str(tmp_path / "b"), "--config", str(d / "small.yaml")]
    assert main(["-q", *args, "--methods", "fpfh-ransac-icp,fpfh-ransac-icp+deform"]) == 0
    rows = {r["method"]: r for r in read_rows(tmp_path / "b" / "cases.csv")}
    rigid, deformed = rows["fpfh-ransac-icp"], rows["fpfh-ransac-icp+deform"]
    assert deformed["rigid_rms_tre_mm"] == pytest.approx(rigid["rms_tre_mm"])  # the same rigid pose first
    assert deformed["deform_applied"] or deformed["deform_reason"]
    assert np.isnan(rigid["rigid_rms_tre_mm"]) and not rigid["deform_applied"]
    summary = (tmp_path / "b" / "summary.md").read_text()
    assert "The non-rigid stage" in summary and "| fpfh-ransac-icp+deform | [0.30,0.40) | 1 |" in summary
    assert main(["-q", *args, "--methods", "fpfh-ransac-icp+nothing"]) == 2


def test_register_deform_sends_the_deformed_model_to_slicer(case: dict, tmp_path: Path) -> None:
    from igtl_support import SlicerServerStandIn

    from liver_p2p_reg.cloud_io import load_mesh

    d = case["dir"]
    config = tmp_path / "applied.yaml"  # a small gain: this liver deforms little, the stage is applied
    config.write_text((d / "small.yaml").read_text() + "deform_min_gain: 0.0\n")
    slicer = SlicerServerStandIn()
    try:
        args = [str(d / "preop.ply"), str(d / "view.ply"), "--deform", "--config", str(config), "-q"]
        args += ["--output", str(tmp_path / "out.json"), "--slicer", f"127.0.0.1:{slicer.port}"]
        assert main(["register", *args]) == 0
        payload = json.loads((tmp_path / "out.json").read_text())
        assert payload["deformation"]["applied"], payload["deformation"]["reason"]
        model = slicer.wait_connected().wait_for("DeformedModel")[0].value
        vertices, triangles = load_mesh(d / "preop.ply")
        assert len(model.points) == len(vertices) and len(model.polygons) == len(triangles)  # on the file's mesh
        rigid = vertices @ np.asarray(payload["transform"])[:3, :3].T + np.asarray(payload["transform"])[:3, 3]
        shift = np.linalg.norm(np.asarray(model.points, float) - rigid, axis=1)  # sensor frame, like the cloud
        assert 0.01 < shift.max() < 25.0  # the deformed model, not the rigidly moved one
    finally:
        slicer.close()


def test_an_npz_mesh_gives_the_stage_its_triangles(case: dict, tmp_path: Path) -> None:
    from liver_p2p_reg.cli.register_outputs import source_mesh

    c = case["case"]
    path = tmp_path / "preop.npz"
    np.savez(path, vertices=c["src_pcd"], triangles=c["src_triangles"])  # they used to be ignored
    vertices, triangles = source_mesh(path)
    np.testing.assert_array_equal(vertices, c["src_pcd"])
    np.testing.assert_array_equal(triangles, c["src_triangles"])
    np.savez(path, vertices=c["src_pcd"])  # no triangles: a cloud, the surface rebuilt from its points
    assert source_mesh(path) is None


def test_a_register_deform_recording_rechecks_the_deformed_surface(case: dict, tmp_path: Path, capsys) -> None:
    d = case["dir"]
    record = tmp_path / "deform.mcap"
    src = case["case"]["src_pcd"]
    np.save(tmp_path / "tumour.npy", 0.5 * (src[:25] + src.mean(axis=0)))  # inside the liver
    args = [str(d / "preop.ply"), str(d / "view.ply"), "--deform", "--config", str(d / "small.yaml")]
    args += ["--structures", f"{tmp_path / 'tumour.npy'}:tumour"]
    assert main(["register", *args, "--output", str(tmp_path / "out.json"), "--record", str(record), "-q"]) == 0
    written = json.loads((tmp_path / "out.json").read_text())
    assert written["deformation"]["applied"] and written["structures"][0]["deformed_position_mm"]
    capsys.readouterr()
    assert main(["replay", str(record)]) == 0  # on the recorded mesh, as the command ran the stage
    out = capsys.readouterr().out
    assert "1 of 1 deformed preop surfaces bitwise identical" in out
    assert "1 of 1 placements of structures bitwise identical" in out  # its deformed positions, placed again
