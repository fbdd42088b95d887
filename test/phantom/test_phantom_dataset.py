"""In silico cases: visibility crops, ground-truth pose, NPZ files, deterministic generation, CLI errors."""

from __future__ import annotations

import argparse
import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

from liver_p2p_reg import pools
from liver_p2p_reg.cli import dataset_cmd
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom.casefile import read_case, write_case
from liver_p2p_reg.phantom.dataset import DatasetSpec, generate_dataset, make_case
from liver_p2p_reg.phantom.loader import PairSampler, build_store
from liver_p2p_reg.phantom.manifest import read_manifest
from liver_p2p_reg.phantom.simulate import simulate_liver
from liver_p2p_reg.registration.visibility import VisibilityMeter


@pytest.fixture(scope="module")
def sim():
    return simulate_liver(21, 2, target_tets=2000)


@pytest.mark.parametrize(
    ("mode", "visibility"),
    [("random", 0.22), ("random", 0.5), ("random", 0.95), ("camera", 0.25), ("camera", 0.4)],
)
def test_crop_visibility_and_ground_truth(sim, mode: str, visibility: float) -> None:
    case = make_case(sim, 1, visibility, crop_mode=mode, noise_mm=2.0, seed=3)
    meter = VisibilityMeter(case["src_pcd"])
    assert abs(meter(case["tgt_pcd"]) - visibility) <= 0.03
    assert case["visibility"] == pytest.approx(meter(case["tgt_pcd"]))
    R, t = case["R_gt"], case["t_gt"]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) == pytest.approx(1.0)
    assert np.all(np.abs(t) <= 100.0)
    assert np.allclose(sim.deformations[1].fiducials_mm @ R.T + t, case["tgt_marker"])
    # Target points lie on the moved deformed surface up to the noise (|noise| <= 1 mm per axis).
    moved_back = (case["tgt_pcd"] - t) @ R
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(sim.deformations[1].surface_mm).query(moved_back)
    assert dist.max() < 1.8 + 2.5  # noise diagonal + sample-to-vertex gap on ~2 mm triangles


def test_camera_crop_sees_the_anterior_side(sim) -> None:
    case = make_case(sim, 0, 0.3, crop_mode="camera", seed=5)
    back = (case["tgt_pcd"] - case["t_gt"]) @ case["R_gt"]
    assert np.median(back[:, 1]) > np.median(sim.vertices_mm[:, 1])  # +y is anterior


def test_case_round_trip_without_pickle(sim, tmp_path) -> None:
    case = make_case(sim, 0, 0.6, seed=1)
    path = write_case(tmp_path / "c.npz", case)
    with np.load(path, allow_pickle=False) as data:
        assert {"src_pcd", "tgt_pcd", "src_marker", "tgt_marker", "R_gt", "t_gt", "crop_mode"} <= set(data.files)
    back = read_case(path)
    assert back["crop_mode"] == "random" and back["liver_id"] == 21
    # Clouds are float32 on disk and were float32-exact already: the stored visibility reproduces.
    assert np.array_equal(back["tgt_pcd"], case["tgt_pcd"]) and np.array_equal(back["src_pcd"], case["src_pcd"])
    assert VisibilityMeter(back["src_pcd"])(back["tgt_pcd"]) == back["visibility"]
    assert np.array_equal(back["tgt_marker"], case["tgt_marker"])


def test_bad_case_arguments(sim, tmp_path) -> None:
    with pytest.raises(InputError):
        make_case(sim, 5, 0.5)
    with pytest.raises(InputError):
        make_case(sim, 0, 1.5)
    with pytest.raises(InputError):
        make_case(sim, 0, 0.5, crop_mode="sideways")
    with pytest.raises(InputError):
        read_case(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(InputError):
        read_case(tmp_path / "junk.npz")


def _record_start_methods(monkeypatch) -> list[str]:
    """Have the package's process pools note how they start their workers (then start them as asked)."""
    methods: list[str] = []

    class Recording(ProcessPoolExecutor):
        def __init__(self, *args, mp_context=None, **kwargs) -> None:
            methods.append(mp_context.get_start_method() if mp_context else multiprocessing.get_start_method())
            super().__init__(*args, mp_context=mp_context, **kwargs)

    monkeypatch.setattr(pools, "ProcessPoolExecutor", Recording)
    return methods


def test_generation_is_identical_for_any_worker_count_and_resumes(tmp_path, monkeypatch) -> None:
    spec = dict(livers=2, deformations=1, targets=2, seed=3, target_tets=1500)
    m1 = generate_dataset(tmp_path / "w1", DatasetSpec(**spec), workers=1, progress=False)
    methods = _record_start_methods(monkeypatch)
    m2 = generate_dataset(tmp_path / "w2", DatasetSpec(**spec), workers=2, progress=False)
    # spawned, never forked: a forked child blocks in its first OpenMP region once the parent has used it
    assert methods == ["spawn"]
    rows1, rows2 = read_manifest(m1.parent), read_manifest(m2.parent)
    assert rows1 == rows2 and len(rows1) == 4
    for row in rows1:
        a, b = read_case(m1.parent / row["file"]), read_case(m2.parent / row["file"])
        assert all(np.array_equal(np.asarray(a[k]), np.asarray(b[k])) for k in a)
    # Resume: a deleted case is regenerated identically, the others are kept.
    victim = m1.parent / rows1[0]["file"]
    before = read_case(victim)
    victim.unlink()
    generate_dataset(tmp_path / "w1", DatasetSpec(**spec), workers=1, progress=False)
    assert np.array_equal(read_case(victim)["tgt_pcd"], before["tgt_pcd"])
    with pytest.raises(InputError):  # same directory, different parameters
        generate_dataset(tmp_path / "w1", DatasetSpec(**{**spec, "targets": 3}), progress=False)


def test_pair_sampler_draws_valid_pairs(tmp_path) -> None:
    store = build_store(tmp_path / "store", livers=1, deformations=2, seed=4, target_tets=1500, progress=False)
    sampler = PairSampler(store, seed=0, visibility_range=(0.3, 0.6), noise_levels_mm=(0.0, 2.0))
    pairs = [sampler.sample() for _ in range(3)]
    for pair in pairs:
        assert 0.27 <= pair["visibility"] <= 0.63
        assert pair["tgt_marker"].shape == pair["src_marker"].shape
    again = PairSampler(store, seed=0, visibility_range=(0.3, 0.6), noise_levels_mm=(0.0, 2.0)).sample()
    assert np.array_equal(again["tgt_pcd"], pairs[0]["tgt_pcd"])
    sampler.reseed(0)
    assert np.array_equal(next(iter(sampler))["tgt_pcd"], pairs[0]["tgt_pcd"])
    sampler.reseed(1)
    assert not np.array_equal(sampler.sample()["tgt_pcd"][:10], pairs[0]["tgt_pcd"][:10])
    with pytest.raises(InputError):
        PairSampler(tmp_path / "nowhere", seed=0)


def test_a_store_built_by_worker_processes_equals_one_built_in_process(tmp_path, monkeypatch) -> None:
    kwargs = dict(livers=2, deformations=1, seed=5, target_tets=1500, progress=False)
    one = build_store(tmp_path / "one", workers=1, **kwargs)
    methods = _record_start_methods(monkeypatch)
    two = build_store(tmp_path / "two", workers=2, **kwargs)
    assert methods == ["spawn"]  # as generate_dataset's pool
    names = sorted(p.name for p in one.glob("liver_*.npz"))
    assert len(names) == 2 and names == sorted(p.name for p in two.glob("liver_*.npz"))
    for name in names:
        with np.load(one / name) as a, np.load(two / name) as b:
            assert sorted(a.files) == sorted(b.files)
            assert all(np.array_equal(a[k], b[k]) for k in a.files)


def _cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    dataset_cmd.add_parser(parser.add_subparsers())
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.mark.parametrize(
    "argv",
    [
        ["--livers", "0"],
        ["--crop", "sideways"],
        ["--noise", "-1"],
        ["--seed", "900"],
        ["--workers", "0"],
        ["--targets", "0"],
    ],
)
def test_cli_bad_arguments_are_input_errors(tmp_path, argv: list[str]) -> None:
    with pytest.raises(InputError):
        _cli(["dataset", "generate", "--out", str(tmp_path / "d"), *argv])


def test_cli_needs_exactly_one_destination_and_known_testset(tmp_path) -> None:
    with pytest.raises(InputError):
        _cli(["dataset", "generate"])
    with pytest.raises(InputError):
        _cli(["dataset", "generate", "--testset", "insilico-test-v0", "--out", str(tmp_path)])
    with pytest.raises(InputError):
        _cli(["dataset", "stats", str(tmp_path)])
    with pytest.raises(InputError, match="900-999"):  # training stores never use test livers
        _cli(["dataset", "generate", "--store", str(tmp_path / "s"), "--seed", "950"])
    with pytest.raises(InputError):
        _cli(["dataset", "generate", "--store", str(tmp_path / "s"), "--out", str(tmp_path / "o")])


def test_read_case_accepts_the_public_p2p_layout(tmp_path) -> None:
    rng = np.random.default_rng(0)
    src, tgt, vol = rng.normal(size=(50, 3)), rng.normal(size=(30, 3)), rng.normal(size=(10, 3))
    np.savez(
        tmp_path / "p2p.npz",
        src_pcd=src,
        tgt_pcd=tgt,
        src_vol=vol,
        tgt_vol=vol + 1,
        R_gt=np.eye(3),
        t_gt=np.ones((3, 1)),
    )
    case = read_case(tmp_path / "p2p.npz")
    assert np.array_equal(case["src_marker"], vol) and np.array_equal(case["tgt_marker"], vol + 1)
    assert case["t_gt"].shape == (3,)


def test_voxel_count_matches_the_pipelines_voxelization(rng) -> None:
    from liver_p2p_reg.registration.preprocess import voxel_downsample
    from liver_p2p_reg.registration.visibility import count_voxels

    for scale in (0.1, 1.0, 3.0):
        pts = rng.normal(size=(5000, 3)) * scale - 0.3
        assert count_voxels(pts, 0.04) == len(voxel_downsample(pts, 0.04))
