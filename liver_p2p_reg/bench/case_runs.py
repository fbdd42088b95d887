"""A per-case function over a named set's cases and their 2 mm noise copies, in a pool, kept as JSON by settings."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from liver_p2p_reg.bench.cases import (
    CaseInfo,
    add_target_noise,
    case_info,
    case_seed,
    list_case_paths,
    read_case,
    resolve_dataset,
    with_noise,
)
from liver_p2p_reg.bench.harness import omp_threads
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.files import write_text_atomic
from liver_p2p_reg.metrics import rms_tre_mm
from liver_p2p_reg.pools import spawn_pool
from liver_p2p_reg.registration.registrar import Registrar
from liver_p2p_reg.result import RegistrationResult

NOISE_MM = 2.0
_CACHE: dict[str, Any] = {}  # one per worker process, shared across cases as the benchmark shares it


def case_registrar(info: CaseInfo, config_dict: dict[str, Any]) -> tuple[dict[str, Any], np.ndarray, Registrar]:
    """A case as the benchmark registers it: its data, its target with the case's added noise, and a Registrar of
    the settings with the case's seed (the process's shared cache)."""
    data = read_case(info.path)
    registrar = Registrar(Config.from_dict({**config_dict, "seed": case_seed(int(config_dict.get("seed", 0)), info)}))
    registrar.cache = _CACHE
    return data, add_target_noise(np.asarray(data["tgt_pcd"], float), info), registrar


def screened_case(
    info: CaseInfo, config_dict: dict[str, Any]
) -> tuple[dict[str, Any], np.ndarray, Registrar, RegistrationResult, dict[str, Any]]:
    """`case_registrar`'s case registered as the benchmark does: (data, noisy target, registrar, result, the row's
    common fields: case, visibility, the method's estimate of it, RMS-TRE, an empty `screened` list)."""
    data, target, registrar = case_registrar(info, config_dict)
    src_marker, tgt_marker = np.asarray(data["src_marker"], float), np.asarray(data["tgt_marker"], float)
    result = registrar.register(data["src_pcd"], target, source_fiducials_mm=src_marker, target_fiducials_mm=tgt_marker)
    row = {
        "case_id": info.case_id,
        "visibility": info.visibility,
        "method_visibility": float(result.visibility),
        "rms_tre_mm": float(rms_tre_mm(result.T_target_source, src_marker, tgt_marker)),
        "screened": [],
    }
    return data, target, registrar, result, row


def set_rows(
    dataset: str,
    run: Callable[[CaseInfo, dict[str, Any]], dict[str, Any]],
    settings: dict[str, Any],
    out: Path,
    *,
    below_visibility: float,
    workers: int,
    tag: dict[str, Any] | None = None,
    from_visibility: float = 0.0,
) -> list[dict[str, Any]]:
    """`run(case, settings)` for every case of `dataset` (named or a folder) from `from_visibility` and below
    `below_visibility`, beside its 2 mm noise copy (as the selection runs, `--noise-bins all`), on `workers` processes of one thread each.

    The rows are kept in OUT/DATASET.json with the settings, the cases' cut and `tag` (what else `run` was told, e.g.
    a bound keyword): a second call with the same ones reads them; one with others is refused (InputError), so rows
    of two configurations never mix. The file is written whole or not at all.
    """
    cut = {"from_visibility": from_visibility} if from_visibility > 0 else {}  # (absent: from 0, as before it existed)
    stamp = {**settings, **cut, "below_visibility": below_visibility, "noise_mm": NOISE_MM, **(tag or {})}
    saved = out / f"{Path(dataset).name}.json"
    if saved.exists():
        try:
            made = json.loads(saved.read_text())
            kept, rows = made["settings"], made["rows"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise InputError(f"cannot read the kept rows {saved} ({type(exc).__name__}): remove it") from None
        if kept != stamp:
            raise InputError(f"{saved} was made with other settings: remove it or give another --out")
        return rows
    if workers < 1:
        raise InputError(f"workers must be >= 1, got {workers}")
    folder, _ = resolve_dataset(dataset, None)
    infos = with_noise([case_info(p) for p in list_case_paths(folder)], [NOISE_MM], "all")
    infos = [i for i in infos if from_visibility <= i.visibility < below_visibility]
    rows = []
    with omp_threads(1), spawn_pool(workers) as pool, tqdm(total=len(infos), desc=dataset, unit="case") as bar:
        for row in pool.map(run, infos, [settings] * len(infos), chunksize=4):
            rows.append(row)
            bar.update()
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(saved, json.dumps({"settings": stamp, "rows": rows}, indent=0) + "\n")
    return rows
