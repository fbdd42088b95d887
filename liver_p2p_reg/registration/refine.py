"""Robust (trimmed) point-to-plane ICP refinement of a rigid transform, source -> partial target."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from liver_p2p_reg.registration.context import remember_latest
from liver_p2p_reg.registration.features.fpfh import outward_normals
from liver_p2p_reg.registration.nearest import NearestIndex

if TYPE_CHECKING:
    from liver_p2p_reg.config import Config
    from liver_p2p_reg.registration.preprocess import PreprocessedPair


def axis_angle_rotation(omega: np.ndarray) -> np.ndarray:
    """Rotation matrix of the axis-angle vector omega (Rodrigues)."""
    angle = float(np.linalg.norm(omega))
    if angle < 1e-12:
        return np.eye(3)
    return rotation_about(omega / angle, angle)


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """The rotation by `angle` (radians) about the unit `axis` (Rodrigues)."""
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b of (k, 3) arrays: np.cross's products and differences, in its order (the same bits).

    Why not np.cross: its axis handling costs ~4x the arithmetic on the few hundred rows ICP has,
    and ICP runs ~100 iterations per registration.
    """
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    out = np.empty_like(a)
    out[:, 0] = a1 * b2 - a2 * b1
    out[:, 1] = a2 * b0 - a0 * b2
    out[:, 2] = a0 * b1 - a1 * b0
    return out


def source_search_index(source: np.ndarray, normal_radius: float) -> tuple[NearestIndex, np.ndarray]:
    """The closest-point index and outward normals of the source: built once per preoperative model."""
    return NearestIndex(source), outward_normals(source, normal_radius)


def trimmed_icp(T_init: np.ndarray, source: np.ndarray, target: np.ndarray, **options: Any) -> np.ndarray:
    """`trimmed_icp_many` from one start (its keyword options)."""
    return trimmed_icp_many([T_init], source, target, **options)[0]


def trimmed_icp_many(
    T_inits: list[np.ndarray],
    source: np.ndarray,
    target: np.ndarray,
    *,
    max_iterations: int = 50,
    max_corr: float = 0.1,
    trim_ratio: float = 0.8,
    normal_radius: float = 0.1,
    max_target_points: int = 4000,
    tol: float = 1e-3,
    source_index: tuple[NearestIndex, np.ndarray] | None = None,
) -> list[np.ndarray]:
    """Refine each start T (source -> target) by point-to-plane ICP that keeps the best `trim_ratio` pairs.

    Pairs go from each target point to its closest source point: the target is partial, so
    every target point has a counterpart on the complete source but not the other way round.
    The source k-d tree and normals are built once; target points are moved into the source
    frame instead. Units are whatever the clouds use (normalized in the pipelines). It stops
    when a step moves less than `tol` (1e-3 normalized, ~0.1 mm / 0.06 deg): the trimmed pair set
    keeps changing below that, so a tighter tol mostly runs to `max_iterations` for nothing.

    Several starts run together, each result bitwise the one its start gives alone. Why: screening runs ~6 short
    ICPs on the same clouds; each iteration's closest-point search is asked once for the moved targets of every
    start still running (one k-d tree call of a few thousand points instead of one per start; each point's closest
    point does not depend on the others in the call); the rest of each step is each start's own arithmetic.
    """
    if len(target) > max_target_points:  # even subsample keeps the cost bounded
        target = target[:: int(np.ceil(len(target) / max_target_points))]
    tree, normals = source_index if source_index is not None else source_search_index(source, normal_radius)
    T_invs = [np.linalg.inv(np.asarray(T, dtype=np.float64)) for T in T_inits]
    running = list(range(len(T_invs)))
    for _ in range(max_iterations):
        if not running:
            break
        # target in each running start's source frame
        queries = [target @ T_invs[c][:3, :3].T + T_invs[c][:3, 3] for c in running]
        # The bound prunes the tree search; pairs beyond it are dropped anyway (dist = inf).
        dist_all, idx_all = tree.query(np.concatenate(queries), distance_upper_bound=max_corr)
        still = []
        for j, (c, q) in enumerate(zip(running, queries, strict=True)):
            rows = slice(j * len(target), (j + 1) * len(target))
            step = icp_step(q, dist_all[rows], idx_all[rows], source, normals, max_corr, trim_ratio)
            if step is None:
                continue
            T_invs[c] = step[0] @ T_invs[c]
            if not step[1] < tol:  # (a NaN step keeps running, as the single-start loop did)
                still.append(c)
        running = still
    return [np.linalg.inv(T_inv) for T_inv in T_invs]


def icp_step(
    q: np.ndarray,
    dist: np.ndarray,
    idx: np.ndarray,
    source: np.ndarray,
    normals: np.ndarray,
    max_corr: float,
    trim_ratio: float,
) -> tuple[np.ndarray, float] | None:
    """One trimmed point-to-plane step of the target points `q` (source frame) and their closest source points:
    (the 4x4 step, its size |x|), or None with fewer than 6 pairs within `max_corr` (ICP stops there)."""
    keep = np.flatnonzero(dist < max_corr)
    if len(keep) < 6:
        return None
    d_keep = dist[keep]
    # The trim_ratio quantile's pairs: linear interpolation puts the quantile between the
    # (lo)th and (lo+1)th smallest distance, so "<= quantile" keeps those up to the lo-th.
    lo = int(np.floor((len(d_keep) - 1) * trim_ratio))
    sel = keep[d_keep <= np.partition(d_keep, lo)[lo]]
    near = idx[sel]
    # take(): the same rows as fancy indexing at about half its cost on these few hundred rows
    p, s, n = np.take(q, sel, axis=0), np.take(source, near, axis=0), np.take(normals, near, axis=0)
    # Linearized: find small (omega, dt) moving q onto the source planes; solved by its
    # 6x6 normal equations (lstsq there too, so a degenerate fit cannot raise).
    A = np.empty((len(p), 6))
    A[:, :3] = cross_rows(p, n)
    A[:, 3:] = n
    b = -np.einsum("ij,ij->i", p - s, n)
    x, *_ = np.linalg.lstsq(A.T @ A, A.T @ b, rcond=None)
    step = np.eye(4)
    step[:3, :3] = axis_angle_rotation(x[:3])
    step[:3, 3] = x[3:]
    return step, float(np.linalg.norm(x))


def refine_pose(
    T_norm: np.ndarray,
    prep: PreprocessedPair,
    config: Config,
    cache: dict[str, Any],
    *,
    max_points: int | None = None,
    max_iterations: int | None = None,
) -> np.ndarray:
    """Trimmed point-to-plane ICP of a normalized pose on the full (un-voxelized) clouds of `prep`."""
    return refine_poses([T_norm], prep, config, cache, max_points=max_points, max_iterations=max_iterations)[0]


def refine_poses(
    poses_norm: list[np.ndarray],
    prep: PreprocessedPair,
    config: Config,
    cache: dict[str, Any],
    *,
    max_points: int | None = None,
    max_iterations: int | None = None,
) -> list[np.ndarray]:
    """`refine_pose` of several normalized poses at once (`trimmed_icp_many`: each bitwise as alone)."""
    # The preoperative source is the same frame after frame: reuse its k-d tree and normals.
    memo_key = f"icp-source-index:{config.normal_radius_norm!r}"
    index = prep.memo.get(memo_key)
    if index is None:
        index = prep.memo[memo_key] = remember_latest(
            cache,
            "icp-source-index",
            prep.source_full,
            (config.normal_radius_norm,),
            lambda: source_search_index(prep.source_full, config.normal_radius_norm),
        )
    return trimmed_icp_many(
        poses_norm,
        prep.source_full,
        prep.target_full,
        max_iterations=max_iterations or config.icp_max_iterations,
        max_corr=config.icp_max_corr_norm,
        trim_ratio=config.icp_trim_ratio,
        max_target_points=max_points or config.icp_max_points,
        normal_radius=config.normal_radius_norm,
        source_index=index,
    )
