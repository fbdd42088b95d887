"""Real anatomy: livers from mesh files, the fixed split, realistic target density, the real store and sets.

Everything here runs without ../shared (a procedural liver's surface stands in for a file);
the tests that need the real CT livers skip with one line when they are absent.
"""

from __future__ import annotations

import numpy as np
import pytest

from liver_p2p_reg import Config, Registrar
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.metrics import rms_tre_mm
from liver_p2p_reg.phantom.anatomy import make_liver
from liver_p2p_reg.phantom.artifacts import Artifacts
from liver_p2p_reg.phantom.crop import make_target
from liver_p2p_reg.phantom.real import (
    liver_from_surface,
    missing_real_livers_message,
    read_obj,
    real_liver_id,
    real_livers_dir,
    real_split,
    weld_vertices,
)
from liver_p2p_reg.phantom.simulate import simulate_liver
from liver_p2p_reg.registration.mechanics.surface import is_watertight, mesh_volume_mm3
from liver_p2p_reg.registration.visibility import VisibilityMeter

needs_real = pytest.mark.skipif(real_livers_dir() is None, reason=missing_real_livers_message())


@pytest.fixture(scope="module")
def file_liver():
    """A procedural liver's surface, decimated by taking every 3rd face's fan, read back as a file mesh."""
    proc = make_liver(4)
    return liver_from_surface(proc.vertices_mm, proc.triangles, liver_id=123, name="proc-4")


def test_split_is_fixed_disjoint_and_large_enough() -> None:
    split = real_split()
    names = [n for part in split.values() for n in part]
    assert len(names) == len(set(names)) == 60  # no liver in two parts
    assert len(split["train"]) >= 40 and len(split["val"]) + len(split["test"]) >= 12
    assert len({real_liver_id(n) for n in names}) == 60


def test_file_mesh_is_remeshed_closed_with_its_volume(file_liver) -> None:
    proc = make_liver(4)
    assert is_watertight(file_liver.triangles)
    volume, original = (
        mesh_volume_mm3(file_liver.vertices_mm, file_liver.triangles),
        mesh_volume_mm3(proc.vertices_mm, proc.triangles),
    )
    assert volume == pytest.approx(original, rel=0.02)
    # The SDF is negative inside: the centroid of a liver is inside, a point far away is not.
    assert file_liver.implicit_mm(np.array([[0.0, 0.0, 0.0], [500.0, 0.0, 0.0]]))[1] > 0
    assert np.all(np.isfinite(file_liver.implicit_mm(file_liver.vertices_mm)))
    assert np.max(np.abs(file_liver.implicit_mm(file_liver.vertices_mm))) < 2.0  # vertices on the zero level


def test_file_liver_deforms_and_keeps_its_coarse_vertices(file_liver) -> None:
    sim = simulate_liver(123, 2, target_tets=1500, liver=file_liver)
    assert len(sim.fiducials_mm) >= 3
    for d in sim.deformations:
        assert d.coarse_mm.shape == file_liver.coarse_vertices_mm.shape
        assert 0.3 < d.rms_mm < 12.0
        # The coarse vertices move with the surface: close to the deformed dense surface.
        from scipy.spatial import cKDTree

        gap, _ = cKDTree(d.surface_mm).query(d.coarse_mm)
        assert np.percentile(gap, 95) < 2.5


@pytest.mark.parametrize(
    "mutate, words",
    [
        (lambda v, f: (v, f[:-3]), "open mesh"),
        (lambda v, f: (v / 1000.0, f), "metres?"),
        (lambda v, f: (v, np.concatenate([f, f[:1]])), "non-manifold"),
        (lambda v, f: (v, f[:2]), "not a triangle mesh"),
    ],
)
def test_bad_meshes_get_one_line(mutate, words) -> None:
    proc = make_liver(4)
    v, f = mutate(proc.vertices_mm, proc.triangles)
    with pytest.raises(InputError, match=words) as info:
        liver_from_surface(v, f, name="bad.obj")
    assert "\n" not in str(info.value)


def test_a_triangle_soup_is_welded_into_the_closed_surface_it_is() -> None:
    proc = make_liver(4)
    soup = proc.vertices_mm[proc.triangles].reshape(-1, 3)  # STL: three corners per triangle
    v, f = weld_vertices(soup, np.arange(len(soup)).reshape(-1, 3))
    assert len(v) == len(proc.vertices_mm) and is_watertight(f)
    assert mesh_volume_mm3(v, f) == pytest.approx(mesh_volume_mm3(proc.vertices_mm, proc.triangles))


def test_obj_reader_fans_polygons_and_rejects_bad_indices(tmp_path) -> None:
    path = tmp_path / "quad.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1//1 2//1 3//1 4//1\n")
    v, f = read_obj(path)
    assert v.shape == (4, 3) and f.tolist() == [[0, 1, 2], [0, 2, 3]]
    path.write_text("v 0 0 0\nf 1 2 3\n")
    with pytest.raises(InputError, match="does not exist"):
        read_obj(path)


@pytest.mark.parametrize("density", ["mesh-vertices", "depth-falloff"])
def test_density_twins_share_crop_pose_and_differ_in_sampling(file_liver, density) -> None:
    sim = simulate_liver(123, 1, target_tets=1500, liver=file_liver)
    deformed = sim.deformations[0]
    meter = VisibilityMeter(sim.vertices_mm)

    def target(dens: str) -> dict:
        rng = np.random.default_rng(5)
        return make_target(
            sim.vertices_mm, deformed.surface_mm, sim.triangles, 0.35, "camera", 0.0, rng, meter=meter,
            density=dens, coarse_mm=deformed.coarse_mm,
        )  # fmt: skip

    uniform, twin = target("uniform"), target(density)
    np.testing.assert_array_equal(uniform["R_gt"], twin["R_gt"])
    assert twin["visibility_uniform"] == pytest.approx(uniform["visibility"])
    from scipy.spatial import cKDTree

    moved_back = (twin["tgt_pcd"] - twin["t_gt"]) @ twin["R_gt"]
    if density == "mesh-vertices":  # exactly the file's own vertices, deformed with the liver
        gap, _ = cKDTree(deformed.coarse_mm).query(moved_back)
        assert gap.max() < 1e-3
    else:  # a thinned subset of the same sampling
        assert len(twin["tgt_pcd"]) < len(uniform["tgt_pcd"])
    # Every twin point lies in the region the uniform view covers.
    gap, _ = cKDTree(uniform["tgt_pcd"]).query(twin["tgt_pcd"])
    assert np.percentile(gap, 90) < 4.0


def test_artifacts_add_outliers_and_background(file_liver) -> None:
    sim = simulate_liver(123, 1, target_tets=1500, liver=file_liver)
    deformed = sim.deformations[0]
    args = (sim.vertices_mm, deformed.surface_mm, sim.triangles, 0.4, "random", 0.0)
    clean = make_target(*args, np.random.default_rng(3))
    dirty = make_target(*args, np.random.default_rng(3), artifacts=Artifacts(1.0, 0.05, 0.1))
    R, t = clean["R_gt"], clean["t_gt"]
    from scipy.spatial import cKDTree

    surface = cKDTree(deformed.surface_mm @ R.T + t)
    off = surface.query(dirty["tgt_pcd"])[0] > 3.0
    assert 0.02 < off.mean() < 0.3  # flying pixels and background points, a minority
    assert surface.query(clean["tgt_pcd"])[0].max() < 3.0


def test_full_view_slightly_larger_than_the_source_registers_and_swaps_are_refused(file_liver) -> None:
    rng = np.random.default_rng(0)
    src = file_liver.vertices_mm
    # A noisy full view: every surface point seen twice with 3 mm noise voxelizes a little larger.
    tgt = np.concatenate([src, src]) + rng.uniform(-1.5, 1.5, size=(2 * len(src), 3))
    tgt = tgt @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).T + [10.0, -20.0, 5.0]
    registrar = Registrar(Config(method="fpfh-ransac-icp"))
    prep_ratio = registrar.register(src, tgt).visibility
    assert prep_ratio > 1.0  # more than 1.25x the source after voxelization: accepted
    partial = src[src[:, 0] > np.percentile(src[:, 0], 70)]
    with pytest.raises(InputError, match="SOURCE and the partial view as TARGET"):
        registrar.register(partial, src)


def test_full_view_registers_accurately() -> None:
    proc = make_liver(6)
    sim = simulate_liver(6, 1, target_tets=1500, liver=proc)
    rng = np.random.default_rng(1)
    tgt = make_target(sim.vertices_mm, sim.deformations[0].surface_mm, sim.triangles, 0.95, "random", 2.0, rng)
    result = Registrar(Config(method="fpfh-ransac-icp")).register(sim.vertices_mm, tgt["tgt_pcd"])
    truth = sim.deformations[0].fiducials_mm @ tgt["R_gt"].T + tgt["t_gt"]
    assert rms_tre_mm(result.T_target_source, sim.fiducials_mm, truth) < 10.0


@needs_real
def test_real_liver_loads_and_a_real_store_trains(tmp_path) -> None:
    from liver_p2p_reg.phantom.real import load_real_liver
    from liver_p2p_reg.training.train import train
    from liver_p2p_reg.training.train_config import TrainConfig

    liver = load_real_liver(real_split()["train"][0])
    assert is_watertight(liver.triangles) and len(liver.vertices_mm) > 5000
    cfg = TrainConfig(
        store_dir=str(tmp_path / "proc"), store_livers=2, store_deformations=1, store_tets=1500, val_livers=1,
        val_pairs=1, steps=3, val_every=3, checkpoint_every=3, real_store_dir=str(tmp_path / "real"),
        real_deformations=1, real_fraction=1.0, real_val_pairs=1, real_livers_limit=1,
        density_modes=["uniform", "mesh-vertices"], hole_probability=0.5, outlier_fraction=0.02,
        model={"width": 32, "layers": 1, "out_dim": 16, "max_nodes": 64},
    )  # fmt: skip
    state = train(cfg, tmp_path / "run", progress=False)
    assert state["step"] == 3 and np.isfinite(state["best_metrics"]["val_real_p2p_mm"])
    assert len(list((tmp_path / "real").glob("liver_*.npz"))) == 2  # one train, one train_dev liver
