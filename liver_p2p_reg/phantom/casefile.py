"""A registration case on disk: the NPZ's keys, writing and reading it (ours or the public P2P layout), its sensor origin."""

from __future__ import annotations

import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from liver_p2p_reg.errors import InputError

# The keys of a case the generator writes (make_case).
CASE_KEYS = (
    "src_pcd",
    "tgt_pcd",
    "src_marker",
    "tgt_marker",
    "R_gt",
    "t_gt",
    "visibility",
    "visibility_requested",
    "deformation_rms_mm",
    "deformation_max_mm",
    "noise_mm",
    "crop_mode",
    "liver_id",
    "deformation_id",
    "target_id",
    "seed",
    "generator_version",
)
# Optional keys: camera crops also store where the camera stood (the eye), in the target frame.
# Case files made before it existed lack it: their sensor origin is unknown.
SENSOR_ORIGIN_KEY = "sensor_origin_mm"
# Optional: the preop surface's triangles (indices into src_pcd), for the non-rigid stage's closed solid.
TRIANGLES_KEY = "src_triangles"


def sensor_origin_mm(case: dict) -> np.ndarray | None:
    """The camera position of a case (mm, target frame), or None when unknown (random crops, older files)."""
    value = case.get(SENSOR_ORIGIN_KEY)
    if value is None:
        return None
    origin = np.asarray(value, dtype=np.float64).reshape(-1)
    return origin if origin.shape == (3,) and np.isfinite(origin).all() else None


def source_triangles(case: dict) -> np.ndarray | None:
    """The preop triangles of a case (F, 3) int64, or None when it stores points only (older files, P2P's)."""
    value = case.get(TRIANGLES_KEY)
    if value is None:
        return None
    tris = np.asarray(value, dtype=np.int64)
    n = len(case["src_pcd"])
    return tris if tris.ndim == 2 and tris.shape[1] == 3 and len(tris) and 0 <= tris.min() and tris.max() < n else None


def write_case(path: str | Path, case: dict) -> Path:
    """Write a case as a compressed NPZ without pickled objects (clouds stored as float32)."""
    path = Path(path)
    missing = [k for k in ("src_pcd", "tgt_pcd", "src_marker", "tgt_marker", "R_gt", "t_gt") if k not in case]
    if missing:
        raise InputError(f"case lacks {', '.join(missing)}")
    arrays = {}
    for key, value in case.items():
        if key in ("src_pcd", "tgt_pcd"):
            arrays[key] = np.asarray(value, dtype=np.float32)  # 1e-5 mm precision; halves the size
        elif isinstance(value, str):
            arrays[key] = np.str_(value)
        elif isinstance(value, dict):
            continue
        else:
            arrays[key] = np.asarray(value)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)  # atomic: a half-written file never looks finished
    return path


def read_case(path: str | Path) -> dict:
    """Read a case NPZ (ours or the public P2P layout): float arrays as float64, scalars as Python values."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such case file")
    if not zipfile.is_zipfile(path):  # np.load would read a .npy array or guess "pickled data"
        raise InputError(f"{path}: not an NPZ archive (a case file holds src_pcd, tgt_pcd, ... arrays)")
    try:
        with np.load(path, allow_pickle=False) as data:
            raw = {k: data[k] for k in data.files}
    # BadZipFile: a bad CRC or a cut archive; zlib.error / EOFError: a damaged compressed member
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise InputError(f"{path}: not a readable case NPZ ({exc})") from exc
    for key in ("src_pcd", "tgt_pcd"):
        if key not in raw:
            raise InputError(f"{path}: missing key {key!r}")
    case: dict = {}
    for key, value in raw.items():
        if value.dtype.kind == "U":
            case[key] = str(value)
        elif value.ndim == 0:
            case[key] = value.item()
        elif value.dtype.kind == "f":
            case[key] = value.astype(np.float64)
        else:
            case[key] = value
    # The public P2P dataset names the fiducials src_vol / tgt_vol and stores t_gt as (3, 1).
    for ours, theirs in (("src_marker", "src_vol"), ("tgt_marker", "tgt_vol")):
        if ours not in case and theirs in case:
            case[ours] = case[theirs]
    if "t_gt" in case and np.size(case["t_gt"]) == 3:
        case["t_gt"] = np.asarray(case["t_gt"], dtype=np.float64).reshape(3)
    _check_markers(path, case)
    _check_visibility(path, case)
    return case


def _check_markers(path: Path, case: dict) -> None:
    """Source and target markers pair up, one (x, y, z) each: else every error computed from them is wrong."""
    if "src_marker" not in case or "tgt_marker" not in case:
        return  # the readers that need them say so
    src, tgt = np.shape(case["src_marker"]), np.shape(case["tgt_marker"])
    if len(src) != 2 or src[1] != 3 or src != tgt:
        raise InputError(f"{path}: src_marker {src} and tgt_marker {tgt} must both be (N, 3) with the same N")


def _check_visibility(path: Path, case: dict) -> None:
    """A stored visibility is a share of the surface; NaN stays allowed (unknown, as when the key is absent)."""
    value = case.get("visibility")
    if value is None:
        return
    try:
        share = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{path}: visibility must be a number in [0, 1], got {value!r}") from None
    if not (np.isnan(share) or 0 <= share <= 1):
        raise InputError(f"{path}: visibility must lie in [0, 1], got {share:g}")
