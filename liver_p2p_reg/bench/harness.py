"""Runs registration methods on benchmark cases through the public Registrar API; resumable CSV output."""

from __future__ import annotations

import csv
import json
import logging
import math
import multiprocessing
import os
import time
from collections.abc import Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from liver_p2p_reg.bench.cases import CaseInfo, add_target_noise, case_seed, first_per_bin, read_case, sensor_origin_mm
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.metrics import rms_tre_mm, tre_mm
from liver_p2p_reg.registration.registrar import Registrar, available_methods

log = logging.getLogger(__name__)

CASES_CSV = "cases.csv"
SETTINGS_JSON = "settings.json"
ORACLE = "procrustes"
# Columns before the per-stage runtimes / after them; per-stage columns are `runtime_<stage>_ms`.
HEAD_COLUMNS = (
    "case_id",
    "method",
    "base_method",
    "variant",
    "visibility",
    "noise_mm",
    "added_noise_mm",
    "crop_mode",
    "density",
    "deformation_rms_mm",
    "rms_tre_mm",
    "max_tre_mm",
    "initial_rms_tre_mm",
    "residual_mm",
    "runtime_ms",
)
TAIL_COLUMNS = (
    "chosen_candidate",
    "n_candidates",
    "n_matches",
    "method_visibility",
    "failed",
    "reason",
    "ambiguous",
    "uncertainty_mm",
    "free_space_violation",
    "seed",
)
FLOAT_COLUMNS = {
    "visibility",
    "noise_mm",
    "added_noise_mm",
    "deformation_rms_mm",
    "rms_tre_mm",
    "max_tre_mm",
    "initial_rms_tre_mm",
    "residual_mm",
    "runtime_ms",
    "method_visibility",
    "uncertainty_mm",
    "free_space_violation",
}
INT_COLUMNS = {"n_candidates", "n_matches", "seed"}
BOOL_COLUMNS = {"failed", "ambiguous"}
ABLATION_K = tuple(range(1, 9))  # the paper's Fig. 8: K = 1 ... 8
ABLATION_CASES_PER_BIN = 10
# Settings that may differ between runs into one OUT: they add rows and never change existing ones.
ADDITIVE_SETTINGS = ("noise_levels_mm", "ablation_cases_per_bin", "sensor_aware")
SENSOR_AWARE_TAG = "[fs]"  # label suffix of the rows registered with the case's sensor origin (free space)


@dataclass(frozen=True)
class Variant:
    """One way of running a method: its name plus Config overrides (empty for the main run), and
    whether the case's sensor origin is given (a main run of its own, labelled `method[fs]`)."""

    method: str
    overrides: tuple[tuple[str, Any], ...] = ()
    sensor_aware: bool = False
    # A named main-table method built on `method` (e.g. `prepared`: per-liver prepared weights in
    # `overrides`); its rows count as a method of their own, not as an ablation variant.
    tag: str = ""

    @property
    def label(self) -> str:
        base = self.method + SENSOR_AWARE_TAG if self.sensor_aware else self.method
        if self.tag:
            return f"{base}[{self.tag}]"
        if not self.overrides:
            return base
        return f"{base}[{self.variant}]"

    @property
    def variant(self) -> str:
        """The ablation's overrides ("" for a main run, with or without the sensor origin or a tag)."""
        return "" if self.tag else ",".join(f"{k}={v}" for k, v in self.overrides)


@dataclass
class BenchmarkSpec:
    """Everything that defines a benchmark run (the parts that must not change within one OUT)."""

    out: Path
    dataset_id: str
    cases: list[CaseInfo]
    methods: list[str]
    config: Config = field(default_factory=Config)
    preset: str = "full"
    limit: int | None = None
    ablations: bool = False
    ablation_cases_per_bin: int = ABLATION_CASES_PER_BIN
    workers: int = 1
    noise_levels_mm: tuple[float, ...] = ()
    noise_bins: str = "lowest"  # which cases get the noisy copies (cases.with_noise)
    # case_id -> patient-prepared weights of its liver (`--prepare-minutes`): adds `<method>[prepared]`
    # rows for the learned methods
    prepared: dict[str, str] = field(default_factory=dict)
    prepare_minutes: float = 0.0
    sensor_aware: bool = False  # also run every method with the case's sensor origin (`method[fs]` rows)

    def settings(self) -> dict[str, Any]:
        """The settings recorded in OUT/settings.json; a rerun must match them."""
        from liver_p2p_reg.bench.cases import fingerprint

        clean = [c for c in self.cases if c.added_noise_mm == 0]  # noisy copies are additive
        return {
            "dataset": self.dataset_id,
            "cases_fingerprint": fingerprint(clean),
            "n_cases": len(clean),
            "preset": self.preset,
            "limit": self.limit,
            "ablation_cases_per_bin": self.ablation_cases_per_bin,
            "noise_levels_mm": list(self.noise_levels_mm),
            "noise_bins": self.noise_bins,
            "prepare_minutes": self.prepare_minutes,
            "sensor_aware": self.sensor_aware,
            "config": self.config.to_dict(),
        }


def is_p2p(method: str) -> bool:
    """Methods whose P2P module the ablations vary (plain `X-p2p`, not the refined `X-p2p-icp`)."""
    return method.endswith("-p2p")


def build_jobs(spec: BenchmarkSpec) -> list[tuple[CaseInfo, Variant]]:
    """All (case, variant) pairs of the run, cases outermost so partial runs cover whole cases."""
    main = [Variant(m) for m in spec.methods]
    if spec.sensor_aware:  # the same cases with the sensor origin, next to each method's plain run
        main += [Variant(m, sensor_aware=True) for m in spec.methods if m != ORACLE]  # the oracle ignores it
    ablation: list[Variant] = []
    if spec.ablations:
        cfg = spec.config
        for m in spec.methods:
            if m.endswith("-p2p-icp"):  # the ICP screening of the candidates, on or off
                ablation.append(Variant(m, (("refine_candidates", 1 if cfg.refine_candidates > 1 else 6),)))
            if not is_p2p(m):
                continue
            ablation += [Variant(m, (("k", k),)) for k in ABLATION_K if k != cfg.k]
            other_rule = "inlier-count" if cfg.selection == "closest-point" else "closest-point"
            ablation.append(Variant(m, (("selection", other_rule),)))
            ablation.append(Variant(m, (("candidate_proposal", not cfg.candidate_proposal),)))
            # this project's additions to the paper's module: row-best matches, the robust re-fit
            # and the consensus-started twin candidates
            ablation.append(Variant(m, (("mutual_only", not cfg.mutual_only),)))
            ablation.append(Variant(m, (("refit_iterations", 0 if cfg.refit_iterations else 6),)))
            ablation.append(Variant(m, (("consensus_seeds", 0 if cfg.consensus_seeds else 64),)))
    clean = [c for c in spec.cases if c.added_noise_mm == 0]  # ablations run on the noise-free cases
    ablation_ids = {c.case_id for c in first_per_bin(clean, spec.ablation_cases_per_bin)}
    jobs = []
    for case in spec.cases:
        jobs += [(case, v) for v in main]
        weights = spec.prepared.get(case.case_id.split("+")[0])  # noisy copies share their case's liver
        if weights:
            jobs += [
                (case, Variant(m, (("weights_path", weights),), tag="prepared"))
                for m in spec.methods
                if m.startswith("learned")
            ]
        if case.case_id in ablation_ids:
            jobs += [(case, v) for v in ablation]
    return jobs


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
        result = registrar.register(
            data["src_pcd"],
            add_target_noise(np.asarray(data["tgt_pcd"], float), case),
            method=variant.method,
            source_fiducials_mm=src_marker,
            target_fiducials_mm=tgt_marker,
            sensor_origin_mm=origin,
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
    )
    for stage, ms in result.runtime_ms.items():
        if stage != "total":
            row[f"runtime_{stage}_ms"] = float(ms)
    return row


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
    }


def _format(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ("nan" if math.isnan(value) else repr(value))
    return "" if value is None else str(value)


def _parse(column: str, text: str) -> Any:
    if column in BOOL_COLUMNS:
        return text == "true"
    if column in INT_COLUMNS:
        return int(text) if text else 0
    if column in FLOAT_COLUMNS or (column.startswith("runtime_") and column.endswith("_ms")):
        return float(text) if text else math.nan
    return text


def columns_for(rows: Iterable[dict[str, Any]]) -> list[str]:
    """Fixed columns plus one `runtime_<stage>_ms` column per stage seen in any row (sorted)."""
    stages = sorted({k for r in rows for k in r if k.startswith("runtime_") and k != "runtime_ms"})
    return [*HEAD_COLUMNS, *stages, *TAIL_COLUMNS]


def read_rows(path: Path) -> list[dict[str, Any]]:
    """Rows of a cases.csv with typed values (floats, ints, bools)."""
    with open(path, newline="") as fh:
        return [{k: _parse(k, v) for k, v in row.items() if v is not None} for row in csv.DictReader(fh)]


def write_rows(path: Path, rows: list[dict[str, Any]]) -> None:
    """Write all rows sorted by (case_id, method), atomically."""
    rows = sorted(rows, key=lambda r: (r["case_id"], r["method"]))
    header = columns_for(rows)
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        for row in rows:
            writer.writerow([_format(row.get(col, math.nan if col.startswith("runtime_") else "")) for col in header])
    os.replace(tmp, path)


class _CsvLog:
    """Append-only cases.csv that survives interruption; rewritten only when a new stage column appears."""

    def __init__(self, path: Path, rows: list[dict[str, Any]]) -> None:
        self.path = path
        self.rows = list(rows)
        self.header = columns_for(self.rows)
        write_rows(path, self.rows)

    def add(self, row: dict[str, Any]) -> None:
        self.rows.append(row)
        if any(k not in self.header for k in row):
            self.header = columns_for(self.rows)
            write_rows(self.path, self.rows)
            return
        with open(self.path, "a", newline="") as fh:
            csv.writer(fh).writerow(
                [_format(row.get(c, math.nan if c.startswith("runtime_") else "")) for c in self.header]
            )


def check_settings(out: Path, settings: dict[str, Any]) -> None:
    """Refuse to mix runs with different settings in one OUT; record the settings of a new OUT."""
    path = out / SETTINGS_JSON
    if path.exists():
        old = json.loads(path.read_text())
        diffs = _diff(old, settings)
        if diffs:
            raise InputError(
                f"{out} holds a run with other settings ({'; '.join(diffs[:3])}); use a new --out or delete it"
            )
        for key in ADDITIVE_SETTINGS:  # record what was added (union of noise levels, largest ablation set)
            if key == "noise_levels_mm":
                settings[key] = sorted(set(old.get(key, [])) | set(settings[key]))
            elif key == "sensor_aware":
                settings[key] = bool(old.get(key, False) or settings[key])
            else:
                settings[key] = max(old.get(key, 0), settings[key])
        path.write_text(json.dumps(settings, indent=2, sort_keys=True) + "\n")
        return
    if (out / CASES_CSV).exists():
        raise InputError(f"{out / CASES_CSV} exists without {SETTINGS_JSON}; use a new --out")
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(settings, indent=2, sort_keys=True) + "\n")


def _diff(old: Any, new: Any, prefix: str = "") -> list[str]:
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for key in sorted(set(old) | set(new)):
            if prefix == "config." and (key not in old or key not in new):
                continue  # a Config field added or removed since: the rows' settings did not change
            if not prefix and key in ADDITIVE_SETTINGS:
                continue  # these only add rows (noisy copies, ablation cases); existing rows stay valid
            out += _diff(old.get(key), new.get(key), f"{prefix}{key}.")
        return out
    return [] if old == new else [f"{prefix.rstrip('.')}: {old!r} then, {new!r} now"]


def _init_worker(num_threads: int) -> None:
    try:
        import torch

        torch.set_num_threads(max(1, num_threads))
    except ImportError:
        pass


def run_benchmark(spec: BenchmarkSpec, progress: bool = True) -> list[dict[str, Any]]:
    """Run every (case, variant) not yet in OUT/cases.csv; return all rows of OUT (old and new)."""
    known = set(available_methods())
    unknown = [m for m in spec.methods if m not in known]
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
    store = _CsvLog(csv_path, done_rows)
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


def _run_parallel(spec: BenchmarkSpec, todo: list, config_dict: dict, store: _CsvLog, bar: tqdm) -> None:
    # Spawned workers each get 1 torch / BLAS thread so W workers use W cores, not W x cores.
    threads = spec.config.num_threads or 1
    saved = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = str(threads)
    try:
        ctx = multiprocessing.get_context("spawn")
        pool = ProcessPoolExecutor(spec.workers, mp_context=ctx, initializer=_init_worker, initargs=(threads,))
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
    finally:
        if saved is None:
            os.environ.pop("OMP_NUM_THREADS", None)
        else:
            os.environ["OMP_NUM_THREADS"] = saved
