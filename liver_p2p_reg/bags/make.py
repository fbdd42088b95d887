"""Build rosbag2 (MCAP) bags of a registration case: preop model + fiducials, intraop frames with sensor motion."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from liver_p2p_reg.bags.io import MARKER, POINTCLOUD2, BagWriter, rosbags_types
from liver_p2p_reg.bags.mesh import MAX_MESH_TRIANGLES, decimated_mesh, preop_mesh_marker
from liver_p2p_reg.cloud_io import as_float_array, clean_points, require_plausible_extent
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.ros.pointcloud2 import M_PER_MM, points_to_cloud
from liver_p2p_reg.ros.topics import (
    TOPIC_INTRAOP,
    TOPIC_INTRAOP_FIDUCIALS,
    TOPIC_PREOP,
    TOPIC_PREOP_FIDUCIALS,
    TOPIC_PREOP_MESH,
)

CASE_KEY = "liver_p2p_reg.case"  # metadata.yaml custom_data key holding the case description (JSON)
START_NS = 1_700_000_000 * 1_000_000_000  # fixed start time: identical bags for identical inputs
# Intraop points in all frames of one made bag: 5e7 is ~1.2 GB of clouds in memory and ~0.6 GB of bag (10 Hz of
# 20,000-point frames for 40 minutes); --frames 100000000 built motions for minutes, then would fill the disk.
MAX_BAG_POINTS = 50_000_000
Mesh = tuple[np.ndarray, np.ndarray]  # (vertices mm, triangles)


def subsample(points: np.ndarray, max_points: int, rng: np.random.Generator) -> np.ndarray:
    """At most max_points rows, chosen uniformly without replacement (order kept)."""
    if len(points) <= max_points:
        return points
    return points[np.sort(rng.choice(len(points), size=max_points, replace=False))]


def sensor_motion(n_frames: int, motion_mm: float, motion_deg: float, rng: np.random.Generator) -> list[np.ndarray]:
    """Small rigid motions of the sensor, one 4x4 per frame (the first is the identity)."""
    motions = [np.eye(4)]
    for k in range(1, n_frames):
        T = np.eye(4)
        axis = rng.normal(size=3)
        T[:3, :3] = Rotation.from_rotvec(
            axis / np.linalg.norm(axis) * np.radians(motion_deg) * k / n_frames
        ).as_matrix()
        T[:3, 3] = rng.normal(size=3) / np.sqrt(3) * motion_mm * k / n_frames
        motions.append(T)
    return motions


def make_case_bag(
    out: str | Path,
    source_mm: np.ndarray,
    target_mm: np.ndarray,
    *,
    source_fiducials_mm: np.ndarray | None = None,
    target_fiducials_mm: np.ndarray | None = None,
    source_triangles: np.ndarray | None = None,
    max_mesh_triangles: int = MAX_MESH_TRIANGLES,
    n_frames: int = 5,
    frame_id: str = "camera",
    preop_frame: str = "ct",
    motion_mm: float = 1.5,
    motion_deg: float = 1.0,
    frame_period_s: float = 0.5,
    max_preop_points: int = 6000,
    max_intraop_points: int = 8000,
    seed: int = 0,
    info: dict[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write one case as a rosbag2 directory; clouds in metres (float32), timestamps from START_NS.

    The intraop cloud of frame k is the target moved by a small sensor motion T_k and freshly
    subsampled; the ground-truth fiducials of that frame are moved by the same T_k and carry
    the cloud's header stamp. source_triangles (indices into source_mm as given): the preop mesh,
    written on /preop/mesh decimated to at most max_mesh_triangles.
    """
    _check_frame_ids(frame_id, preop_frame)
    mesh = _mesh(source_mm, source_triangles, max_mesh_triangles)
    source_mm = _points(source_mm, "source")
    target_mm = _points(target_mm, "target")
    if (source_fiducials_mm is None) != (target_fiducials_mm is None):
        raise InputError("give both source and target fiducials, or neither")
    if source_fiducials_mm is not None:
        source_fiducials_mm = _points(source_fiducials_mm, "source fiducials", paired=True)
        target_fiducials_mm = _points(target_fiducials_mm, "target fiducials", paired=True)
        if source_fiducials_mm.shape != target_fiducials_mm.shape:
            raise InputError(
                f"fiducial pairs differ in shape: {source_fiducials_mm.shape} vs {target_fiducials_mm.shape}"
            )
    if n_frames < 1:
        raise InputError(f"n_frames must be >= 1, got {n_frames}")
    total_points = n_frames * min(len(target_mm), max(max_intraop_points, 1))
    if total_points > MAX_BAG_POINTS:  # every frame is built in memory first, then written
        raise InputError(
            f"{n_frames} frames of {total_points // n_frames} points is {total_points:.3g} points in all, above the "
            f"{MAX_BAG_POINTS:.0e} a bag is made of; give fewer --frames or a smaller --max-intraop-points"
        )
    if not frame_period_s > 0:
        raise InputError(f"the frame period must be > 0 s, got {frame_period_s}")
    if not (np.isfinite(motion_mm) and np.isfinite(motion_deg)):
        raise InputError(f"sensor motion must be finite, got {motion_mm} mm and {motion_deg} deg")
    if min(max_preop_points, max_intraop_points) < 1:
        raise InputError(
            f"point limits must be >= 1, got {max_preop_points} (preop) and {max_intraop_points} (intraop)"
        )
    # A bag whose clouds the node would refuse (wrong units) is refused now, with the same words.
    defaults = Config()
    for cloud, what in ((source_mm, "source"), (target_mm, "target")):
        require_plausible_extent(
            cloud,
            what,
            defaults.expected_extent_min_mm,
            defaults.expected_extent_max_mm,
            "bag inputs are read as millimetres",
        )
    rng = np.random.default_rng(seed)
    description = {
        "frames": n_frames,
        "frame_id": frame_id,
        "preop_points": min(len(source_mm), max_preop_points),
        "motion_mm": motion_mm,
        "motion_deg": motion_deg,
        **(info or {}),
    }
    # The random draws in their historical order (preop, motions, then each frame's subsample):
    # bags of unchanged cases stay byte-identical.
    preop = subsample(source_mm, max_preop_points, rng)
    frames, frame_fiducials = [], []
    for T in sensor_motion(n_frames, motion_mm, motion_deg, rng):
        if target_fiducials_mm is not None:
            frame_fiducials.append(transform_points(T, target_fiducials_mm))
        frames.append(transform_points(T, subsample(target_mm, max_intraop_points, rng)))
    return write_frames(
        out,
        preop,
        frames,
        source_fiducials_mm=source_fiducials_mm,
        frame_fiducials_mm=frame_fiducials if target_fiducials_mm is not None else None,
        mesh=mesh,
        frame_period_s=frame_period_s,
        frame_id=frame_id,
        preop_frame=preop_frame,
        description=description,
        overwrite=overwrite,
    )


def make_sweep_bag(
    out: str | Path,
    source_mm: np.ndarray,
    frames_mm: list[np.ndarray],
    *,
    source_fiducials_mm: np.ndarray | None = None,
    frame_fiducials_mm: list[np.ndarray] | None = None,
    source_triangles: np.ndarray | None = None,
    max_mesh_triangles: int = MAX_MESH_TRIANGLES,
    frame_period_s: float = 0.2,
    frame_id: str = "camera",
    preop_frame: str = "ct",
    max_preop_points: int = 20_000,
    seed: int = 0,
    info: dict[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a moving sensor's frames (each in the sensor's frame at that moment, mm) as a rosbag2 directory.

    Frame k is stamped START_NS + (k + 1) x period; its ground-truth fiducials (same frame) carry its stamp.
    source_triangles: the preop mesh, as in make_case_bag.
    """
    _check_frame_ids(frame_id, preop_frame)
    mesh = _mesh(source_mm, source_triangles, max_mesh_triangles)
    source_mm = _points(source_mm, "source")
    frames = [_points(f, f"frame {k}") for k, f in enumerate(frames_mm)]
    if not frames:
        raise InputError("a sweep needs at least one frame")
    if (source_fiducials_mm is None) != (frame_fiducials_mm is None):
        raise InputError("give both source and per-frame fiducials, or neither")
    if frame_fiducials_mm is not None:
        source_fiducials_mm = _points(source_fiducials_mm, "source fiducials", paired=True)
        frame_fiducials_mm = [_points(f, "frame fiducials", paired=True) for f in frame_fiducials_mm]
        if len(frame_fiducials_mm) != len(frames) or any(
            f.shape != source_fiducials_mm.shape for f in frame_fiducials_mm
        ):
            raise InputError("per-frame fiducials must match the frames in number and the source fiducials in shape")
    if not frame_period_s > 0:
        raise InputError(f"the frame period must be > 0 s, got {frame_period_s}")
    rng = np.random.default_rng(seed)
    description = {"frames": len(frames), "frame_id": frame_id, "frame_period_s": frame_period_s, **(info or {})}
    return write_frames(
        out,
        subsample(source_mm, max_preop_points, rng),
        frames,
        source_fiducials_mm=source_fiducials_mm,
        frame_fiducials_mm=frame_fiducials_mm,
        mesh=mesh,
        frame_period_s=frame_period_s,
        frame_id=frame_id,
        preop_frame=preop_frame,
        description=description,
        overwrite=overwrite,
    )


def write_frames(
    out: str | Path,
    preop_mm: np.ndarray,
    frames_mm: list[np.ndarray],
    *,
    source_fiducials_mm: np.ndarray | None,
    frame_fiducials_mm: list[np.ndarray] | None,
    frame_period_s: float,
    frame_id: str,
    preop_frame: str,
    description: dict[str, Any],
    overwrite: bool,
    mesh: Mesh | None = None,
) -> Path:
    """The bag itself: preop mesh, model and fiducials (latched), then each frame's fiducials and cloud, in metres.

    The mesh carries the model's frame and stamp (the node pairs them by it) and is logged just before the
    model, so the model's warm-up builds the elastic model on it."""
    types = rosbags_types()
    period_ns = int(frame_period_s * 1e9)
    if mesh is not None:
        description = {**description, "preop_mesh_triangles": len(mesh[1])}
    with BagWriter(out, overwrite=overwrite, custom_data={CASE_KEY: json.dumps(description, sort_keys=True)}) as bag:
        if mesh is not None:
            bag.write(TOPIC_PREOP_MESH, MARKER, START_NS - 1000, preop_mesh_marker(*mesh, preop_frame, START_NS))
        bag.write(
            TOPIC_PREOP,
            POINTCLOUD2,
            START_NS,
            points_to_cloud(preop_mm * M_PER_MM, types, frame_id=preop_frame, stamp_ns=START_NS),
        )
        if source_fiducials_mm is not None:
            msg = points_to_cloud(source_fiducials_mm * M_PER_MM, types, frame_id=preop_frame, stamp_ns=START_NS)
            bag.write(TOPIC_PREOP_FIDUCIALS, POINTCLOUD2, START_NS, msg)
        for k, frame in enumerate(frames_mm):
            stamp = START_NS + (k + 1) * period_ns
            if frame_fiducials_mm is not None:  # logged just before its cloud so replay pairs them
                fid = frame_fiducials_mm[k] * M_PER_MM
                bag.write(
                    TOPIC_INTRAOP_FIDUCIALS,
                    POINTCLOUD2,
                    stamp - 1000,
                    points_to_cloud(fid, types, frame_id=frame_id, stamp_ns=stamp),
                )
            cloud = points_to_cloud(frame * M_PER_MM, types, frame_id=frame_id, stamp_ns=stamp)
            bag.write(TOPIC_INTRAOP, POINTCLOUD2, stamp, cloud)
    return Path(out)


def load_case_npz(path: str | Path) -> dict[str, Any]:
    """A case NPZ (ours or the public P2P layout: src_pcd, tgt_pcd, src_marker|src_vol, tgt_marker|tgt_vol), mm."""
    from liver_p2p_reg.phantom.casefile import read_case  # the one reader of case files

    path = Path(path)
    if not path.is_file():
        raise InputError(f"case file not found: {path}")
    raw = read_case(path)
    case: dict[str, Any] = {"source_mm": raw["src_pcd"], "target_mm": raw["tgt_pcd"], "info": {"case": path.stem}}
    triangles = _case_triangles(raw, path)
    if triangles is not None:  # a generated case's preop mesh
        case["source_triangles"] = triangles
    if "src_marker" in raw and "tgt_marker" in raw:
        case["source_fiducials_mm"] = raw["src_marker"]
        case["target_fiducials_mm"] = raw["tgt_marker"]
    for key in ("visibility", "noise_mm", "crop_mode", "deformation_rms_mm", "deformation_max_mm"):
        if key in raw and isinstance(raw[key], (int, float, str)):
            case["info"][key] = raw[key]
    return case


def _case_triangles(raw: dict[str, Any], path: Path) -> np.ndarray | None:
    """The case's preop triangles, None when it stores none; InputError when they do not index src_pcd.

    casefile.source_triangles reads a bad mesh as no mesh; a bag would then lack /preop/mesh without a word.
    """
    from liver_p2p_reg.phantom.casefile import TRIANGLES_KEY, source_triangles

    stored = raw.get(TRIANGLES_KEY)
    if stored is None or np.size(stored) == 0:
        return None
    try:
        triangles = source_triangles(raw)
    except (TypeError, ValueError):  # not numbers at all: the shape message below
        triangles = None
    if triangles is not None:
        return triangles
    tris = np.asarray(stored)
    if tris.ndim != 2 or tris.shape[1] != 3 or tris.dtype.kind not in "iuf":
        raise InputError(f"{path}: {TRIANGLES_KEY} must be an (F, 3) index array, got shape {tris.shape} {tris.dtype}")
    n_vertices = len(raw["src_pcd"])
    raise InputError(
        f"{path}: {TRIANGLES_KEY} index vertices {tris.min()}..{tris.max()}, "
        f"but src_pcd has {n_vertices} (valid: 0..{n_vertices - 1})"
    )


def _check_frame_ids(frame_id: str, preop_frame: str) -> None:
    """InputError unless both are frame ids the node and tf2 accept: the node refuses every intraop cloud
    without one, so a bag with an empty id would replay as nothing but errors."""
    for what, value in (("frame id", frame_id), ("preop frame id", preop_frame)):
        if not isinstance(value, str) or not value or value.startswith("/") or not _is_plain(value):
            raise InputError(f"{what} {value!r} is not a ROS frame id (non-empty, no spaces, no leading '/')")


def _is_plain(text: str) -> bool:
    """Printable, without whitespace."""
    return text.isprintable() and not any(c.isspace() for c in text)


def _mesh(source_mm: np.ndarray, triangles: np.ndarray | None, max_triangles: int) -> Mesh | None:
    """The bag's preop mesh: the source (as given) and its triangles, decimated; None without triangles."""
    if triangles is None:
        return None
    return decimated_mesh(as_float_array(source_mm, "source")[:, :3], triangles, max_triangles)


def _points(points: np.ndarray, what: str, *, paired: bool = False) -> np.ndarray:
    """(N, 3) finite float64 points; NaN rows are dropped, except in fiducial pairs (refused)."""
    points = as_float_array(points, what)
    if points.ndim != 2 or points.shape[1] < 3 or len(points) == 0:
        raise InputError(f"{what}: expected a non-empty (N, 3) array, got shape {points.shape}")
    points = points[:, :3]
    if paired and not np.isfinite(points).all():
        raise InputError(f"{what} contain NaN or infinite coordinates")
    return clean_points(points, what)
