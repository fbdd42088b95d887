"""The preop solid of the non-rigid stage: coarse closed meshes, repeated points, separate parts, honest reasons."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from synthetic_cases import blob_mm

from liver_p2p_reg import Config
from liver_p2p_reg.cloud_io import sample_mesh_surface
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration import deform
from liver_p2p_reg.registration.mechanics import solid as solid_module
from liver_p2p_reg.registration.mechanics.modes import build_elastic_model
from liver_p2p_reg.registration.mechanics.solid import closed_solid, dense_surface_samples_mm
from liver_p2p_reg.registration.mechanics.surface import mesh_volume_mm3
from liver_p2p_reg.result import RegistrationResult

SMALL = dict(n_modes=12, target_tets=1500)  # a small elastic model keeps these fast


def box_mm(size=(100.0, 80.0, 60.0), at=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """A closed box of 12 outward triangles, its longest edge ~120 voxel half-steps: far beyond the first pass."""
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * size + at
    f = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1),
         (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]  # fmt: skip
    return v, np.array(f, np.int64)


def tetrahedron_mm(edge: float, at=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[0, 0, 0], [edge, 0, 0], [0, edge, 0], [0, 0, edge]], float) + at
    return v, np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int64)


def ellipsoid_mm(n_lat: int = 60, n_lon: int = 120) -> tuple[np.ndarray, np.ndarray]:
    """A closed, finely triangulated ellipsoid (edges of a few mm: the first pass samples it densely enough)."""
    lat = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    ring = np.stack([np.sin(la) * np.cos(lo), np.sin(la) * np.sin(lo), np.cos(la)], axis=-1).reshape(-1, 3)
    v = np.vstack([[0, 0, 1], ring, [0, 0, -1]]) * [100.0, 70.0, 50.0]
    tris = []
    idx = lambda i, j: 1 + i * n_lon + j % n_lon  # noqa: E731
    for j in range(n_lon):
        tris.append((0, idx(0, j), idx(0, j + 1)))
        tris.append((len(v) - 1, idx(n_lat - 2, j + 1), idx(n_lat - 2, j)))
        for i in range(n_lat - 2):
            tris += [(idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)), (idx(i, j), idx(i + 1, j + 1), idx(i, j + 1))]
    return v, np.array(tris, np.int64)


@pytest.mark.parametrize("shape", ["box", "tetrahedron"])
def test_coarse_closed_meshes_enclose_their_volume(shape: str) -> None:
    vertices, triangles = box_mm() if shape == "box" else tetrahedron_mm(120.0)
    solid = closed_solid(vertices, triangles)  # refused as "open or too sparse" when each triangle had 16 steps
    exact = abs(mesh_volume_mm3(vertices, triangles))
    assert exact < solid.volume_mm3 < 1.12 * exact  # a voxel shell: slightly inflated
    assert solid.implicit_mm(vertices.mean(axis=0, keepdims=True))[0] < -10.0  # the middle is deep inside


def test_a_mesh_the_first_pass_closes_never_reaches_the_retry(monkeypatch: pytest.MonkeyPatch) -> None:
    # what keeps every mesh that worked before bitwise the same: the retry runs only where the first pass failed
    vertices, triangles = ellipsoid_mm()
    assert dense_surface_samples_mm(vertices, triangles, 1.0) is None  # no triangle needs more than 16 steps
    monkeypatch.setattr(solid_module, "dense_surface_samples_mm", lambda *a: pytest.fail("retried"))
    solid = closed_solid(vertices, triangles)
    assert abs(solid.volume_mm3 / abs(mesh_volume_mm3(vertices, triangles)) - 1) < 0.12


def test_the_reason_says_what_was_found() -> None:
    vertices, triangles = box_mm()
    with pytest.raises(InputError, match=r"preop mesh does not enclose a volume: it is open \(3 edges border only"):
        closed_solid(vertices, triangles[1:])  # a triangle missing: a 100 mm hole
    sheet, sheet_triangles = box_mm(size=(150.0, 150.0, 0.5))
    with pytest.raises(InputError, match="preop mesh is closed but encloses no volume its 1.6 mm voxels resolve"):
        closed_solid(sheet, sheet_triangles)
    cap = blob_mm(np.random.default_rng(1))
    with pytest.raises(InputError, match=r"preop points do not enclose a volume \(an open or too sparse surface\)"):
        closed_solid(cap[cap[:, 2] > np.percentile(cap[:, 2], 70)], None)


def test_exact_repeats_leave_a_cloud_s_solid_as_it_was() -> None:
    points = blob_mm(np.random.default_rng(2), 8000)
    alone = closed_solid(points, None)
    repeated = closed_solid(np.vstack([points, points[:5000], points[:5000]]), None)  # the median spacing was 0
    assert repeated.voxel_mm == alone.voxel_mm
    assert np.array_equal(repeated.sdf_mm, alone.sdf_mm)


def test_two_separate_solids_are_refused_with_the_count() -> None:
    a, fa = box_mm()
    b, fb = box_mm(at=(200.0, 0.0, 0.0))
    vertices, triangles = np.vstack([a, b]), np.vstack([fa, fb + len(a)])
    normals = np.zeros_like(vertices)
    with pytest.raises(InputError, match=r"preop solid has 2 separate parts \(the largest holds \d\d% of its volume\)"):
        build_elastic_model(vertices, normals, triangles, **SMALL)
    # through the stage: the rigid result stands, with that reason in one line
    view = sample_mesh_surface(a, fa)
    result = RegistrationResult(T_target_source=np.eye(4), method="test", residual_mm=1.0, ok=True)
    out = deform.deform_result(result, vertices, view, Config(deform=True, deform_modes=12), {}, triangles)
    assert not out.applied and "2 separate parts" in out.reason and "\n" not in out.reason
    assert np.array_equal(out.T_target_source, np.eye(4))


def test_a_speck_beside_the_solid_is_dropped_and_said(caplog: pytest.LogCaptureFixture) -> None:
    a, fa = box_mm()
    speck, fs = tetrahedron_mm(2.0, at=(130.0, 40.0, 30.0))  # 30 mm beside the box: its own cube of the mesh
    vertices, triangles = np.vstack([a, speck]), np.vstack([fa, fs + len(a)])
    with caplog.at_level(logging.WARNING, logger="liver_p2p_reg"):
        model = build_elastic_model(vertices, np.zeros_like(vertices), triangles, **SMALL)
    assert any("small piece(s) joined to the rest by no cube face" in r.getMessage() for r in caplog.records)
    alone = build_elastic_model(a, np.zeros_like(a), fa, **SMALL)
    # with the speck kept its free motions were the "softest deformations" (energy ~1e-14, ratios ~1e14)
    assert model.energy_mj_per_mm2 == pytest.approx(alone.energy_mj_per_mm2, rel=0.1)
    assert model.stiffness_ratio.max() < 20
    assert np.all(model.source_weights.sum(axis=1) == pytest.approx(1.0))  # the speck's points follow a node


@pytest.mark.parametrize("bag", ["phantom_sim_02_vis0.36", "insilico_L9000000_D00_T000_camera"])
def test_the_bundled_livers_are_one_body_at_the_default_and_the_smallest_mesh(bag, caplog) -> None:
    """A guard of the one-body rule: a real liver's lobe or tip joined to the rest only by a cube's edge would be
    dropped (other numbers) or, from 1 % of the volume, refused; the bundled livers are one face-connected body."""
    from pathlib import Path

    from liver_p2p_reg.bags.io import read_messages
    from liver_p2p_reg.ros.messages import mesh_marker_mm
    from liver_p2p_reg.ros.topics import TOPIC_PREOP_MESH

    path = Path(__file__).resolve().parents[2] / "bags" / bag
    vertices, triangles = mesh_marker_mm(next(iter(read_messages(path, [TOPIC_PREOP_MESH]))).msg)
    for tets in (Config().deform_target_tets, 500):
        with caplog.at_level(logging.WARNING, logger="liver_p2p_reg"):
            build_elastic_model(vertices, np.zeros_like(vertices), triangles, n_modes=12, target_tets=tets)
        assert not [r for r in caplog.records if "small piece" in r.getMessage()], (bag, tets)
