"""The closest-point index of the ICP loops: pykdtree's answers equal scipy's, and the ICP pose is the same bits."""

from __future__ import annotations

import os
import pickle
import signal
import time

import numpy as np
import pytest
from scipy.spatial import cKDTree
from synthetic_cases import partial_case

from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.registration import nearest
from liver_p2p_reg.registration.features.fpfh import outward_normals
from liver_p2p_reg.registration.nearest import NearestIndex
from liver_p2p_reg.registration.refine import axis_angle_rotation, trimmed_icp, trimmed_icp_many


def test_the_required_fast_backend_is_installed() -> None:
    # setup.py requires pykdtree; without it every registration silently takes the slower path
    assert nearest.BACKEND == "pykdtree"
    assert NearestIndex(np.zeros((1, 3))).backend == "pykdtree"


@pytest.mark.parametrize("bound", [np.inf, 0.05])
def test_distances_and_indices_equal_scipy_bit_for_bit(rng: np.random.Generator, bound: float) -> None:
    cloud = rng.normal(size=(4000, 3))
    queries = 1.2 * rng.normal(size=(2500, 3))
    dist, idx = NearestIndex(cloud).query(queries, distance_upper_bound=bound)
    want_dist, want_idx = cKDTree(cloud).query(queries, k=1, distance_upper_bound=bound)
    assert idx.dtype == np.intp
    np.testing.assert_array_equal(dist, want_dist)
    np.testing.assert_array_equal(idx, want_idx)
    if np.isfinite(bound):  # beyond the bound: inf and one past the last point, as scipy says
        far = dist > bound
        assert far.any() and np.isinf(dist[far]).all() and (idx[far] == len(cloud)).all()


@pytest.mark.parametrize("backend", ["pykdtree", "scipy"])
def test_k_nearest_distances_equal_scipy_bit_for_bit(rng: np.random.Generator, backend: str) -> None:
    cloud = rng.normal(size=(3000, 3))
    dist, idx = NearestIndex(cloud, backend=backend).query_k(cloud[:700], 21)
    want_dist, want_idx = cKDTree(cloud).query(cloud[:700], k=21)
    assert dist.shape == idx.shape == (700, 21) and idx.dtype == np.intp
    np.testing.assert_array_equal(dist, want_dist)  # what the outlier filter and the descriptors average
    np.testing.assert_array_equal(idx, want_idx)  # no exactly equidistant points in a random cloud
    np.testing.assert_array_equal(idx[:, 0], np.arange(700))  # each cloud point is its own nearest
    one_dist, one_idx = NearestIndex(cloud, backend=backend).query_k(cloud[:5] + 0.01, 1)
    assert one_dist.shape == one_idx.shape == (5, 1)
    for bad_k in (0, 3001):
        with pytest.raises(ValueError, match="1 <= k <= 3000"):
            NearestIndex(cloud, backend=backend).query_k(cloud[:5], bad_k)


def test_scipy_backend_and_edge_cases(rng: np.random.Generator) -> None:
    cloud = rng.normal(size=(50, 3))
    index = NearestIndex(cloud, backend="scipy")
    assert index.backend == "scipy" and len(index) == 50
    dist, idx = index.query(cloud[:3])
    np.testing.assert_array_equal(idx, [0, 1, 2])
    np.testing.assert_array_equal(dist, [0.0, 0.0, 0.0])
    empty_dist, empty_idx = NearestIndex(cloud).query(np.zeros((0, 3)))
    assert empty_dist.shape == (0,) and empty_idx.shape == (0,)
    for bad in (np.zeros((0, 3)), np.zeros((5, 2)), np.zeros(3)):
        with pytest.raises(ValueError, match="non-empty"):
            NearestIndex(bad)
    with pytest.raises(ValueError, match="not available"):
        NearestIndex(cloud, backend="flann")


def test_icp_on_either_backend_gives_the_same_pose_bits(rng: np.random.Generator) -> None:
    source, target, T_true, _, _ = partial_case(rng)
    source, target = source / 100.0, target / 100.0  # normalized-like units, as the pipelines run ICP
    T_true = T_true.copy()
    T_true[:3, 3] /= 100.0
    target = target + rng.normal(scale=0.01, size=target.shape)  # 1 mm of sensor noise
    start = T_true.copy()
    start[:3, :3] = T_true[:3, :3] @ axis_angle_rotation(np.array([0.03, -0.02, 0.04]))  # ~3 degrees off
    start[:3, 3] += 0.05  # and 5 mm: the basin the screening leaves ICP in
    normals = outward_normals(source, 0.1)
    poses = [
        trimmed_icp(start, source, target, max_corr=0.1, source_index=(NearestIndex(source, backend=backend), normals))
        for backend in ("pykdtree", "scipy")
    ]
    assert poses[0].tobytes() == poses[1].tobytes()

    # and ICP did its job: the organ lands within 2 mm of where it came from (it started ~7 mm off)
    def worst_mm(T: np.ndarray) -> float:
        return 100.0 * float(np.abs(transform_points(T, source) - transform_points(T_true, source)).max())

    assert worst_mm(start) > 6.0 and worst_mm(poses[0]) < 2.0


def test_a_forked_child_searches_without_blocking_and_gets_the_same_answers(rng: np.random.Generator) -> None:
    # pykdtree's libgomp is not fork-safe: after the parent's first query, a forked child's query
    # blocked forever (a DataLoader worker after a registration in the same process did, in CI)
    cloud = rng.normal(size=(20000, 3))
    queries = rng.normal(size=(5000, 3))
    inherited = NearestIndex(cloud)
    want_dist, want_idx = inherited.query_k(queries, 8)  # the parent's libgomp now has its threads
    pid = os.fork()
    if pid == 0:  # the child: an index it inherited, one it builds, both kinds of search
        ok = False
        try:
            fresh = NearestIndex(cloud)
            answers = []
            for index in (inherited, fresh):
                (dist, idx), (one_dist, one_idx) = index.query_k(queries, 8), index.query(queries)
                answers.append(
                    index.backend == "scipy"
                    and np.array_equal(dist, want_dist)
                    and np.array_equal(idx, want_idx)
                    and np.array_equal(one_dist, want_dist[:, 0])
                    and np.array_equal(one_idx, want_idx[:, 0])
                )
            ok = all(answers)
        finally:
            code = 0 if ok else 1
            os._exit(code)
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            assert os.waitstatus_to_exitcode(status) == 0, "the child's answers differ from the parent's"
            break
        time.sleep(0.05)
    else:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        pytest.fail("a forked child's nearest-point search blocked for 60 s")
    assert inherited.backend == "pykdtree"  # the parent keeps the fast path


@pytest.mark.parametrize("backend", ["pykdtree", "scipy"])
def test_an_index_pickles_as_its_cloud_and_answers_the_same(rng: np.random.Generator, backend: str) -> None:
    # what a spawned worker process receives: pykdtree's tree itself has no pickled form
    index = NearestIndex(rng.normal(size=(500, 3)), backend=backend)
    queries = rng.normal(size=(50, 3))
    again = pickle.loads(pickle.dumps(index))
    assert again.backend == backend and np.array_equal(again.points, index.points)
    for a, b in zip(again.query_k(queries, 4), index.query_k(queries, 4), strict=True):
        np.testing.assert_array_equal(a, b)


def test_icp_from_several_starts_at_once_gives_each_start_its_own_bits(rng: np.random.Generator) -> None:
    # screening runs its short ICPs together (one closest-point search per iteration for all starts); each pose must
    # be bitwise the one its start gives alone, whether it converges, runs out of iterations or loses its pairs
    source, target, T_true, _, _ = partial_case(rng)
    source, target = source / 100.0, target / 100.0
    T_true = T_true.copy()
    T_true[:3, 3] /= 100.0
    target = target + rng.normal(scale=0.01, size=target.shape)
    near = T_true.copy()
    near[:3, :3] = T_true[:3, :3] @ axis_angle_rotation(np.array([0.03, -0.02, 0.04]))
    near[:3, 3] += 0.05
    tilted = T_true.copy()
    tilted[:3, :3] = T_true[:3, :3] @ axis_angle_rotation(np.array([0.4, 0.2, -0.3]))
    lost = T_true.copy()
    lost[:3, 3] += 5.0  # every pair beyond the gate: stops at once, keeps its start
    starts = [near, tilted, lost, T_true]
    index = (NearestIndex(source), outward_normals(source, 0.1))
    for iterations in (3, 50):
        together = trimmed_icp_many(starts, source, target, max_iterations=iterations, source_index=index)
        alone = [trimmed_icp(T, source, target, max_iterations=iterations, source_index=index) for T in starts]
        assert [T.tobytes() for T in together] == [T.tobytes() for T in alone]
    np.testing.assert_allclose(together[2], lost, atol=1e-12)
    assert not np.allclose(together[0], near)  # the others moved
