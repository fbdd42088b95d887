"""Benchmark support for patient preparation: every test liver prepared once, cached by its mesh hash.

A generator-made case names its liver: `real_liver` (a real CT liver, read again from its file)
or `liver_id` (a procedural liver, rebuilt from its seed). The liver is prepared from its closed
surface with the case's own source cloud, exactly as `liver-p2p prepare` would before surgery,
under `<cache>/<mesh hash>_<minutes>min_seed<seed>.safetensors`; later runs reuse the file.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from liver_p2p_reg.bench.cases import CaseInfo, read_case
from liver_p2p_reg.errors import InputError

log = logging.getLogger(__name__)


def liver_mesh(case: dict) -> tuple[np.ndarray, np.ndarray, str]:
    """The closed surface a generated case's source came from: (vertices mm, triangles, name)."""
    if case.get("real_liver"):
        from liver_p2p_reg.phantom.real import read_obj, require_real_livers

        stem = str(case["real_liver"])
        v, f = read_obj(require_real_livers() / f"{stem}.obj")
        return v, f, stem
    if "liver_id" in case:
        from liver_p2p_reg.phantom.anatomy import make_liver

        liver = make_liver(int(case["liver_id"]))
        return liver.vertices_mm, liver.triangles, f"procedural liver {int(case['liver_id'])}"
    raise InputError("--prepare-minutes needs generator-made cases (they name their liver)")


def prepare_test_livers(
    cases: list[CaseInfo], minutes: float, cache_dir: Path, seed: int = 0, progress: bool = True
) -> dict[str, str]:
    """case_id -> prepared weights of its liver, preparing each distinct liver once (cached)."""
    from liver_p2p_reg.training.patient import mesh_sha256, prepare_liver

    out: dict[str, str] = {}
    by_source: dict[str, str] = {}
    cache_dir.mkdir(parents=True, exist_ok=True)
    for info in cases:
        if info.added_noise_mm > 0:
            continue  # noisy copies use their clean case's entry
        data = read_case(info.path)
        key = str(data.get("real_liver") or data.get("liver_id"))
        if key not in by_source:
            v, f, name = liver_mesh(data)
            path = cache_dir / f"{mesh_sha256(v, f)[:16]}_{minutes:g}min_seed{seed}.safetensors"
            if not path.is_file():
                log.info("preparing %s (%g min)", name, minutes)
                prepare_liver(
                    v, f, np.asarray(data["src_pcd"], float), path, minutes, name=name, seed=seed, progress=progress
                )
            by_source[key] = str(path)
        out[info.case_id] = by_source[key]
    return out
