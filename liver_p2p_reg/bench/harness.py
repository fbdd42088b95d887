"""Runs registration methods on benchmark cases through the public Registrar API; resumable CSV output."""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Iterator
from concurrent.futures import as_completed
from contextlib import contextmanager
from typing import Any

import numpy as np
from tqdm import tqdm

from liver_p2p_reg.bench.cases import CaseInfo, add_target_noise, case_seed, read_case, sensor_origin_mm
from liver_p2p_reg.bench.cases_csv import CASES_CSV, CsvLog, read_rows, write_rows
from liver_p2p_reg.bench.jobs import (
    BOUND,
    DEFORM_SUFFIX,
    BenchmarkSpec,
    Variant,
    benchmark_methods,
    build_jobs,
    check_settings,
)
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.metrics import rms_tre_mm, tre_mm
from liver_p2p_reg.pools import spawn_pool
from liver_p2p_reg.registration.registrar import Registrar

log = logging.getLogger(__name__)


# Registrar caches (loaded models, cached features) per variant label, for this process's lifetime.
_CACHES: dict[str, dict[str, Any]] = {}


def run_one(case: CaseInfo, variant: Variant, config_dict: dict[str, Any]) -> dict[str, Any]:
    """Register one case with one method variant through `Registrar.register`; never raises for method failures."""
    data = read_case(case.path)
    src_marker = np.asarray(data["src_marker"], float)
    tgt_marker = np.asarray(data["tgt_marker"], float)
    seed = case_seed(int(config_dict.get("seed", 0)), case)
    config = Config.from_dict({**config_dict, **dict(variant.overrides), "seed": seed})
    registrar = Registrar(config)
    # Share one cache per variant across cases, as the ROS node shares one Registrar across frames.
    registrar.cache = _CACHES.setdefault(variant.label, {})
    initial_rms = rms_tre_mm(np.eye(4), src_marker, tgt_marker)
    initial_max = float(np.max(tre_mm(np.eye(4), src_marker, tgt_marker)))
    row: dict[str, Any] = {
        "case_id": case.case_id,
        "method": variant.label,
        "base_method": variant.method,
        "variant": variant.variant,
        "visibility": case.visibility,
        "noise_mm": case.noise_mm,
        "added_noise_mm": case.added_noise_mm,
        "crop_mode": case.crop_mode,
        "density": case.density,
        "deformation_rms_mm": case.deformation_rms_mm,
        "initial_rms_tre_mm": initial_rms,
        "seed": seed,
    }
    start = time.perf_counter()
    try:
        origin = sensor_origin_mm(data) if variant.sensor_aware else None
        if variant.sensor_aware and origin is None:
            raise InputError(f"case {case.case_id} stores no sensor origin (only camera crops do)")
        method, initial = variant.method, None
        if method == BOUND:  # the configured refinement from the true pose
            method, initial = "track", true_pose_mm(data, case)
        result = registrar.register(
            data["src_pcd"],
            add_target_noise(np.asarray(data["tgt_pcd"], float), case),
            method=method,
            source_fiducials_mm=src_marker,
            target_fiducials_mm=tgt_marker,
            sensor_origin_mm=origin,
            initial_T_mm=initial,
            source_triangles=data.get("src_triangles"),  # the preop mesh, for the non-rigid stage
        )
    except LiverP2PError as exc:
        return {**row, **_failed(initial_rms, initial_max, f"{type(exc).__name__}: {exc}", start)}
    except Exception as exc:  # a bug in one method must not end a 30-minute run; it is recorded
        log.warning("%s on %s: %s: %s", variant.label, case.case_id, type(exc).__name__, exc)
        return {**row, **_failed(initial_rms, initial_max, f"internal {type(exc).__name__}: {exc}", start)}
    T = np.asarray(result.T_target_source, float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return {**row, **_failed(initial_rms, initial_max, "non-finite transform", start)}
    chosen = ""
    if result.chosen is not None and 0 <= result.chosen < len(result.candidates):
        chosen = result.candidates[result.chosen].name
    row.update(
        rms_tre_mm=float(result.rms_tre_mm),
        max_tre_mm=float(result.max_tre_mm),
        residual_mm=float(result.residual_mm),
        runtime_ms=float(result.runtime_ms.get("total", (time.perf_counter() - start) * 1e3)),
        chosen_candidate=chosen,
        n_candidates=len(result.candidates),
        n_matches=int(result.n_matches),
        method_visibility=float(result.visibility),
        failed=not result.ok,
        reason="" if result.ok else (result.message or "method reported failure"),
        ambiguous=bool(result.ambiguous),
        uncertainty_mm=float(result.uncertainty_mm),
        free_space_violation=float(result.free_space_violation),
        error_bound_mm=float(result.error_bound_mm),
        # the share of interior markers within their per-point bound (error_bound.py)
        bound_coverage=float(np.mean(tre_mm(T, src_marker, tgt_marker) <= result.error_bound_at(src_marker))),
    )
    if result.deformation is not None:  # `METHOD+deform`: the error where the deformed model puts the markers
        moved = result.deformation.deformed_position_mm(src_marker)
        errors = np.linalg.norm(moved - tgt_marker, axis=1)
        row.update(
            rigid_rms_tre_mm=row["rms_tre_mm"],
            # computed here: the result carries deformed_rms_tre_mm only when the stage was applied
            rms_tre_mm=float(np.sqrt(np.mean(np.sum((moved - tgt_marker) ** 2, axis=1)))),
            max_tre_mm=float(errors.max()),
            deform_applied=bool(result.deformation.applied),
            deform_reason=result.deformation.reason,
            bound_coverage=float(np.mean(errors <= result.error_bound_at(src_marker))),
        )
    for stage, ms in result.runtime_ms.items():
        if stage != "total":
            row[f"runtime_{stage}_ms"] = float(ms)
    return row


def true_pose_mm(data: dict[str, Any], case: CaseInfo) -> np.ndarray:
    """The case's ground-truth T_target_source (4x4, mm) from its R_gt, t_gt; InputError without them."""
    if "R_gt" not in data or "t_gt" not in data:
        raise InputError(f"case {case.case_id} stores no true pose (R_gt, t_gt): no bound row for it")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = np.asarray(data["R_gt"], float), np.asarray(data["t_gt"], float).reshape(3)
    return T


def _failed(initial_rms: float, initial_max: float, reason: str, start: float) -> dict[str, Any]:
    # Failure rule: a method that raises leaves the case where it started, so its error is the
    # initial (identity) TRE; it also counts as a failure in every success rate.
    return {
        "rms_tre_mm": initial_rms,
        "max_tre_mm": initial_max,
        "residual_mm": math.nan,
        "runtime_ms": (time.perf_counter() - start) * 1e3,
        "chosen_candidate": "",
        "n_candidates": 0,
        "n_matches": 0,
        "method_visibility": math.nan,
        "failed": True,
        "reason": reason.splitlines()[0] if reason else "failed",
        "ambiguous": False,
        "uncertainty_mm": math.nan,
        "free_space_violation": math.nan,
        "error_bound_mm": math.nan,
        "bound_coverage": math.nan,
    }


def _init_worker(num_threads: int) -> None:
    try:
        import torch

        torch.set_num_threads(max(1, num_threads))
    except ImportError:
        pass


def run_benchmark(spec: BenchmarkSpec, progress: bool = True) -> list[dict[str, Any]]:
    """Run every (case, variant) not yet in OUT/cases.csv; return all rows of OUT (old and new)."""
    known = set(benchmark_methods())
    unknown = [m for m in spec.methods if m.removesuffix(DEFORM_SUFFIX) not in known]
    if unknown:
        raise InputError(f"unknown method(s) {', '.join(unknown)}; choose from: {', '.join(sorted(known))}")
    if spec.workers < 1:
        raise InputError(f"--workers must be >= 1, got {spec.workers}")
    check_settings(spec.out, spec.settings())
    csv_path = spec.out / CASES_CSV
    done_rows = read_rows(csv_path) if csv_path.exists() else []
    done = {(r["case_id"], r["method"]) for r in done_rows}
    todo = [(c, v) for c, v in build_jobs(spec) if (c.case_id, v.label) not in done]
    log.info("%d (case, method) rows done, %d to run", len(done), len(todo))
    store = CsvLog(csv_path, done_rows)
    config_dict = spec.config.to_dict()
    bar = tqdm(total=len(todo), desc="benchmark", unit="run", disable=not progress or not todo, dynamic_ncols=True)
    try:
        if spec.workers == 1:
            for case, variant in todo:
                bar.set_postfix_str(f"{variant.label} {case.case_id}", refresh=False)
                store.add(run_one(case, variant, config_dict))
                bar.update()
        else:
            _run_parallel(spec, todo, config_dict, store, bar)
    finally:
        bar.close()
    write_rows(csv_path, store.rows)  # final sorted file: identical for identical runs
    return read_rows(csv_path)


@contextmanager
def omp_threads(threads: int) -> Iterator[None]:
    """OMP_NUM_THREADS for the spawned workers of this block (W workers use W cores, not W x cores), then as before."""
    saved = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = str(threads)
    try:
        yield
    finally:
        if saved is None:
            os.environ.pop("OMP_NUM_THREADS", None)
        else:
            os.environ["OMP_NUM_THREADS"] = saved


def _run_parallel(spec: BenchmarkSpec, todo: list, config_dict: dict, store: CsvLog, bar: tqdm) -> None:
    # Spawned workers each get 1 torch / BLAS thread so W workers use W cores, not W x cores.
    threads = spec.config.num_threads or 1
    with omp_threads(threads):
        pool = spawn_pool(spec.workers, initializer=_init_worker, initargs=(threads,))
        try:
            futures = [pool.submit(run_one, case, variant, config_dict) for case, variant in todo]
            for fut in as_completed(futures):
                store.add(fut.result())
                bar.update()
        except BaseException:
            # Ctrl-C or a crashed worker: drop the queue now (finished rows are already in cases.csv).
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        pool.shutdown()
