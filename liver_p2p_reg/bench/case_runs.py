"""A per-case function over a named set's cases and their 2 mm noise copies, in a pool, kept as JSON by settings."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tqdm import tqdm

from liver_p2p_reg.bench.cases import CaseInfo, case_info, list_case_paths, resolve_dataset, with_noise
from liver_p2p_reg.bench.harness import omp_threads
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.files import write_text_atomic
from liver_p2p_reg.pools import spawn_pool

NOISE_MM = 2.0


def set_rows(
    dataset: str,
    run: Callable[[CaseInfo, dict[str, Any]], dict[str, Any]],
    settings: dict[str, Any],
    out: Path,
    *,
    below_visibility: float,
    workers: int,
    tag: dict[str, Any] | None = None,
) -> list[dict[str, Any]]:
    """`run(case, settings)` for every case of `dataset` (named or a folder) below `below_visibility`, beside its
    2 mm noise copy (as the selection runs, `--noise-bins all`), on `workers` processes of one thread each.

    The rows are kept in OUT/DATASET.json with the settings, the cases' cut and `tag` (what else `run` was told, e.g.
    a bound keyword): a second call with the same ones reads them; one with others is refused (InputError), so rows
    of two configurations never mix. The file is written whole or not at all.
    """
    stamp = {**settings, "below_visibility": below_visibility, "noise_mm": NOISE_MM, **(tag or {})}
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
    infos = [i for i in infos if i.visibility < below_visibility]
    rows = []
    with omp_threads(1), spawn_pool(workers) as pool, tqdm(total=len(infos), desc=dataset, unit="case") as bar:
        for row in pool.map(run, infos, [settings] * len(infos), chunksize=4):
            rows.append(row)
            bar.update()
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(saved, json.dumps({"settings": stamp, "rows": rows}, indent=0) + "\n")
    return rows
