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

    The rows are kept in OUT/DATASET.json with the settings and `tag` (what else `run` was told, e.g. a bound
    keyword): a second call with the same settings and tag reads them; one with others is refused (InputError), so
    rows of two configurations never mix.
    """
    stamp = {**settings, **(tag or {})}
    saved = out / f"{Path(dataset).name}.json"
    if saved.exists():
        made = json.loads(saved.read_text())
        if made["settings"] != stamp:
            raise InputError(f"{saved} was made with other settings: remove it or give another --out")
        return made["rows"]
    folder, _ = resolve_dataset(dataset, None)
    infos = with_noise([case_info(p) for p in list_case_paths(folder)], [NOISE_MM], "all")
    infos = [i for i in infos if i.visibility < below_visibility]
    rows = []
    with omp_threads(1), spawn_pool(workers) as pool, tqdm(total=len(infos), desc=dataset, unit="case") as bar:
        for row in pool.map(run, infos, [settings] * len(infos), chunksize=4):
            rows.append(row)
            bar.update()
    out.mkdir(parents=True, exist_ok=True)
    saved.write_text(json.dumps({"settings": stamp, "rows": rows}, indent=0) + "\n")
    return rows
