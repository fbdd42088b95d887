"""Registers benchmark cases and keeps, per interior marker, the error-bound features and the true error, and per
pose the features over the interior's stand-in (where the pose-level bound is taken)."""

from __future__ import annotations

import logging
import os
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from liver_p2p_reg.bench.cases import CaseInfo, case_info, list_case_paths
from liver_p2p_reg.bench.cases import sensor_origin_mm as case_origin
from liver_p2p_reg.bench.harness import omp_threads
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.pools import spawn_pool
from liver_p2p_reg.registration.error_bound import FEATURES

log = logging.getLogger(__name__)

# Verdict reasons recorded per pose besides the bound itself (which the calibration decides afterwards).
OTHER_REASONS = ("residual", "ambiguous", "uncertainty", "free_space")
# Per-pose arrays of a collection besides the per-marker `errors` and `features` and the per-point
# `interior_features` of the interior's stand-in where the pose-level bound is taken (stack_rows).
POSE_KEYS = ("liver_id", "visibility", "method_visibility", "rms_mm", "ok", "reasons", "bound_ms", "deform_applied")
CACHE_KEYS = (
    "set",
    "case_id",
    "noise_mm",
    "count",
    "errors",
    "features",
    "interior_count",
    "interior_features",
    *POSE_KEYS,
)


def collect_set(folder: Path, noise_mm: float, config: Config, workers: int, progress: bool = True) -> dict:
    """Register every case of a set (its target with `noise_mm` of the benchmark's noise) with the
    configured method; arrays per pose and, flattened with pose offsets, per marker."""
    paths = list_case_paths(folder)
    if not paths:
        raise InputError(f"no case files (case_*.npz) in {folder}")
    infos = [_noisy(case_info(p), noise_mm) for p in paths]
    config_dict = config.to_dict()
    bar = tqdm(total=len(infos), desc=f"bound data {folder.name}", unit="case", disable=not progress)
    rows: list[dict[str, Any]] = []
    if workers <= 1:
        for info in infos:
            rows.append(collect_case(info, config_dict))
            bar.update()
    else:
        with omp_threads(1), spawn_pool(workers) as pool:
            for row in pool.map(collect_case, infos, [config_dict] * len(infos), chunksize=4):
                rows.append(row)
                bar.update()
    bar.close()
    return stack_rows(rows, folder.name, noise_mm)


def _noisy(info: CaseInfo, noise_mm: float) -> CaseInfo:
    import dataclasses

    if noise_mm <= 0:
        return info
    return dataclasses.replace(info, noise_mm=info.noise_mm + noise_mm, added_noise_mm=noise_mm)


def collect_case(info: CaseInfo, config_dict: dict[str, Any]) -> dict[str, Any]:
    """One case: the pose, its verdict reasons, and per marker the bound's features and the true error; with
    `deform` on, the error of the positions the non-rigid stage gives (the pose's where it was not applied)."""
    from liver_p2p_reg.bench.case_runs import case_registrar
    from liver_p2p_reg.phantom.casefile import source_triangles
    from liver_p2p_reg.registration.confidence import result_warnings

    # the benchmark's registrar: the worker's cache shared across cases, so a liver's model (and the non-rigid stage's
    # elastic model) is built once, not once per case
    data, target, registrar = case_registrar(info, config_dict)
    config = registrar.config
    src, tgt = np.asarray(data["src_marker"], float), np.asarray(data["tgt_marker"], float)
    row: dict[str, Any] = {"case_id": info.case_id, "liver_id": int(data.get("liver_id", -1))}
    row["visibility"] = info.visibility
    row["deform_applied"] = False
    try:
        result = registrar.register(
            data["src_pcd"],
            target,
            source_fiducials_mm=src,
            target_fiducials_mm=tgt,
            sensor_origin_mm=case_origin(data),
            source_triangles=source_triangles(data),  # the registrar reads them only for the stage or the judge
        )
        ok = bool(result.ok and result.error_model is not None)
    except LiverP2PError:
        result, ok = None, False
    if not ok:  # a failed registration leaves the organ where it was: unbounded, warned
        err = np.linalg.norm(src - tgt, axis=1)
        return {
            **row,
            "method_visibility": np.nan,
            "ok": False,
            "reasons": "failed",
            "bound_ms": np.nan,
            "errors": err,
            "features": np.full((len(src), len(FEATURES)), np.nan),
            "interior_features": np.zeros((0, len(FEATURES))),
            "rms_mm": _rms(err),
        }
    deformation = result.deformation
    row["deform_applied"] = bool(deformation is not None and deformation.applied)
    moved = (
        deformation.deformed_position_mm(src)
        if row["deform_applied"]
        else transform_points(result.T_target_source, src)
    )
    err = np.linalg.norm(moved - tgt, axis=1)
    reasons = [r for r in result_warnings(result, config) if r in OTHER_REASONS]
    return {
        **row,
        "method_visibility": float(result.visibility),
        "ok": True,
        "reasons": ",".join(reasons),
        "bound_ms": float(result.runtime_ms.get("error_bound", np.nan)),
        "errors": err,
        "features": result.error_model.evidence.features(src),
        "interior_features": interior_features(result.error_model.evidence),
        "rms_mm": _rms(err),
    }


def interior_features(evidence: Any) -> np.ndarray:
    """The bound's features at the interior's stand-in of a pose (where its pose-level bound is taken)."""
    return evidence.features(evidence.interior_mm)


def _rms(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(err**2)))


def stack_rows(rows: list[dict[str, Any]], name: str, noise_mm: float) -> dict[str, np.ndarray]:
    """Per-pose arrays plus the markers' features and errors, flattened in pose order (`count` per pose), and the
    interior stand-in's features, flattened likewise (`interior_count` per pose)."""
    empty = np.zeros((0, len(FEATURES)))
    out: dict[str, np.ndarray] = {
        "set": np.array([name] * len(rows)),
        "case_id": np.array([r["case_id"] for r in rows]),
        "noise_mm": np.full(len(rows), float(noise_mm)),
        "count": np.asarray([len(r["errors"]) for r in rows], np.int64),
        "errors": np.concatenate([r["errors"] for r in rows]) if rows else np.zeros(0),
        "features": np.concatenate([r["features"] for r in rows]) if rows else empty,
        "interior_count": np.asarray([len(r["interior_features"]) for r in rows], np.int64),
        "interior_features": np.concatenate([r["interior_features"] for r in rows]) if rows else empty,
    }
    for key in POSE_KEYS:
        out[key] = np.array([r[key] for r in rows])
    return out


def concat(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Several collections as one."""
    keys = [k for k in parts[0] if k != "start"]  # caches written before `start` was dropped still hold it
    return {k: np.concatenate([p[k] for p in parts]) for k in keys}


def pose_index(data: dict[str, np.ndarray], count: str = "count") -> np.ndarray:
    """Per marker (`count`; `interior_count`: per interior stand-in point), the index of its pose."""
    return np.repeat(np.arange(len(data[count])), data[count])


def subset(data: dict[str, np.ndarray], poses: np.ndarray) -> dict[str, np.ndarray]:
    """The collection restricted to the poses where `poses` (a boolean mask) is true."""
    marker, interior = poses[pose_index(data)], poses[pose_index(data, "interior_count")]
    per_point = {"errors": marker, "features": marker, "interior_features": interior}
    return {k: v[per_point.get(k, poses)] for k, v in data.items() if k != "start"}


def save(path: Path, data: dict[str, np.ndarray]) -> Path:
    """Write a collection as a compressed NPZ (no pickled objects), atomically: a run cut short leaves no
    half-written cache that a later run would take for a finished one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:  # a file object: np.savez would append .npz to a name
        np.savez_compressed(fh, **data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return path


def load(path: Path) -> dict[str, np.ndarray]:
    """Read a collection written by `save`."""
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def load_cached(path: Path) -> dict[str, np.ndarray] | None:
    """A cached collection, or None (one warning line) when it is damaged: the set is then collected again."""
    try:
        data = load(path)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        log.warning("%s: unreadable cache (%s); collecting the set again", path, exc)
        return None
    missing = [k for k in CACHE_KEYS if k not in data]
    if missing:
        log.warning("%s: cache lacks %s; collecting the set again", path, ", ".join(missing))
        return None
    if data["features"].ndim != 2 or data["features"].shape[1] != len(FEATURES):  # made before a feature was added
        log.warning("%s: cache holds other features; collecting the set again", path)
        return None
    return data
