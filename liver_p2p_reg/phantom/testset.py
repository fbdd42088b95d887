"""Named, versioned test sets that regenerate identically on any machine.

`insilico-test-v1`: 12 livers (seed 900, never used for training), 5 FEM deformations each,
8 random-crop targets per deformation, one per visibility bin [0.2,0.3) ... [0.9,1.0), no
noise: 480 cases, 60 per bin (the paper's protocol). `insilico-camera-v1`: the same livers
and deformations seen by an anterior laparoscope, 4 targets per deformation in the bins
[0.2,0.3) and [0.3,0.4) (a camera rarely sees more): 240 cases, 120 per bin. `insilico-smoke`: 2 livers x 1
deformation x 8 bins for fast tests and demo bags. `insilico-val-v1` / `insilico-val-camera-v1`:
6 other livers (seed 990) in the same two forms (240 / 120 cases), the validation sets on which
defaults and thresholds are chosen. Camera crops also store where the camera stood
(`sensor_origin_mm`, target frame) for free-space checks; sets made before that field existed are
brought up to date in place, every other array unchanged. Noise levels are applied by the benchmark
on top of these clean targets (or with `--noise` when generating other sets).
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import asdict
from pathlib import Path

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom.dataset import (
    CAMERA_VISIBILITY_BINS,
    COMPLETE_MARKER,
    LOW_VISIBILITY_BINS,
    VISIBILITY_BINS,
    DatasetSpec,
    case_is_current,
    case_name,
    generate_dataset,
    liver_id_for,
    requested_visibility,
    spec_record,
)
from liver_p2p_reg.phantom.manifest import read_manifest

TESTSETS: dict[str, DatasetSpec] = {
    "insilico-test-v1": DatasetSpec(livers=12, deformations=5, targets=8, crop="random", seed=900, split="test"),
    "insilico-camera-v1": DatasetSpec(livers=12, deformations=5, targets=4, crop="camera", seed=900, split="test"),
    "insilico-smoke": DatasetSpec(livers=2, deformations=1, targets=8, crop="random", seed=901, split="test"),
    # Validation: for choosing defaults and thresholds, so the test sets stay unseen. A reserved
    # seed, so no training store can contain these livers either.
    "insilico-val-v1": DatasetSpec(livers=6, deformations=5, targets=8, crop="random", seed=990, split="val"),
    "insilico-val-camera-v1": DatasetSpec(livers=6, deformations=5, targets=4, crop="camera", seed=990, split="val"),
}


def _v2_bins(crop: str) -> list:
    """The v2 sets' bins, one target each per deformation: the low bins and [0.2,0.3) twice (the
    operating point gets the samples), then the paper's higher bins (random crops; a camera on a
    procedural liver sees at most ~0.4)."""
    high = CAMERA_VISIBILITY_BINS[1:] if crop == "camera" else VISIBILITY_BINS[1:]
    return [list(b) for b in (*LOW_VISIBILITY_BINS * 2, VISIBILITY_BINS[0], VISIBILITY_BINS[0], *high)]


# v2: the bins below 0.2 (`LOW_VISIBILITY_BINS`), random and camera crops, each in both deformation
# families ("-arap": as-rigid-as-possible with handles, which no method here models). Same livers
# and seeds as v1; the v1 sets stay as they were.
for _name, _livers, _seed, _split in (("test", 12, 900, "test"), ("val", 6, 990, "val")):
    for _crop, _tag in (("random", ""), ("camera", "-camera")):
        for _family, _suffix in (("fem", ""), ("arap", "-arap")):
            TESTSETS[f"insilico-{_name}{_tag}-v2{_suffix}"] = DatasetSpec(
                livers=_livers,
                deformations=5,
                targets=len(_v2_bins(_crop)),
                crop=_crop,
                seed=_seed,
                split=_split,
                visibility_bins=_v2_bins(_crop),
                family=_family,
            )
ENV_DATA_ROOT = "LIVER_P2P_DATA"
APPROX_MB_PER_CASE = 0.32  # insilico-test-v1: 154 MB for 480 cases (announced before a build)
log = logging.getLogger(__name__)


def default_root() -> Path:
    """$LIVER_P2P_DATA if set, else ./data."""
    return Path(os.environ.get(ENV_DATA_ROOT, "data"))


def known_sets() -> list[str]:
    """Every named set: the in silico ones and the real-anatomy ones (realsets.py)."""
    from liver_p2p_reg.phantom.realsets import REAL_SETS

    return sorted(TESTSETS) + sorted(REAL_SETS)


def testset_spec(name: str) -> DatasetSpec:
    if name not in TESTSETS:
        raise InputError(f"unknown test set {name!r}; known: {', '.join(known_sets())}")
    spec = TESTSETS[name]
    return DatasetSpec(**asdict(spec)).validate(allow_reserved=True)


def is_complete(path: Path, spec: DatasetSpec) -> bool:
    """True when a finished run of this spec left its manifest and every listed case file."""
    spec_path = path / "dataset.json"
    if not spec_path.is_file() or not (path / COMPLETE_MARKER).is_file() or not (path / "manifest.csv").is_file():
        return False
    if json.loads(spec_path.read_text()) != spec_record(spec):
        return False
    return all(case_is_current(path / r["file"], spec.crop) for r in read_manifest(path))


def expected_cases(name: str) -> list[tuple[int, str, float]]:
    """(liver index, case file name, requested visibility) of every case the named set makes, in
    file-name order, known without generating anything (a case whose visibility cannot be reached
    is skipped by the generator and then missing on disk)."""
    spec = testset_spec(name)
    out = []
    for i in range(spec.livers):
        liver_id = liver_id_for(spec.seed, i)
        for d in range(spec.deformations):
            for t in range(spec.targets):
                out.append((i, case_name(liver_id, d, t), requested_visibility(spec, liver_id, d, t)))
    return sorted(out, key=lambda c: c[1])


def ensure_testset(
    name: str = "insilico-test-v1",
    root: str | Path | None = None,
    workers: int = 1,
    progress: bool = True,
    livers: list[int] | None = None,
) -> Path:
    """Path of the named test set under `root`, generating (or finishing) it when absent.

    `livers`: build only these livers' cases (what a small benchmark preset needs); a later call
    without it finishes the set. What is built, and about how big, is announced first. The
    real-anatomy sets (realsets.py) are built whole.
    """
    from liver_p2p_reg.phantom.realsets import REAL_SETS, ensure_real_set

    if name in REAL_SETS:
        return ensure_real_set(name, Path(root) if root is not None else default_root(), progress=progress)
    spec = testset_spec(name)
    path = Path(root) / name if root is not None else default_root() / name
    if not is_complete(path, spec):
        _remove_stale(path, spec)
        wanted = sorted(set(livers)) if livers is not None else list(range(spec.livers))
        if livers is not None:  # livers an earlier partial build made are done (their manifest rows exist)
            done = {r["liver_id"] for r in read_manifest(path)} if (path / "manifest.csv").is_file() else set()
            wanted = [i for i in wanted if liver_id_for(spec.seed, i) not in done]
            if not wanted:
                return path
        n_cases = len(wanted) * spec.deformations * spec.targets
        part = "all" if len(wanted) == spec.livers else f"{len(wanted)} of the {spec.livers}"
        log.info(
            "building test set %s in %s: %s livers, %d cases, about %.0f MB (once; later runs reuse it)",
            name,
            path,
            part,
            n_cases,
            n_cases * APPROX_MB_PER_CASE,
        )
        generate_dataset(
            path,
            spec,
            workers=workers,
            progress=progress,
            allow_reserved_seed=True,
            livers=None if len(wanted) == spec.livers else wanted,
        )
    return path


def _remove_stale(path: Path, spec: DatasetSpec) -> None:
    """Delete a set made by another generator version (only the files the generator writes)."""
    spec_path = path / "dataset.json"
    if not spec_path.is_file():
        return
    old = json.loads(spec_path.read_text())
    if old.get("generator_version") == spec.generator_version:
        return  # same generator: an unfinished run, resumed by generate_dataset
    log.warning(
        "%s was made by generator v%s; regenerating with v%s",
        path,
        old.get("generator_version"),
        spec.generator_version,
    )
    for pattern in ("case_*.npz", "*.tmp.npz", "manifest.csv", COMPLETE_MARKER, "stats.png", "dataset.json"):
        for file in path.glob(pattern):
            file.unlink()


def testset_cases(path: str | Path) -> list[Path]:
    """Sorted case files of a generated dataset (from its manifest)."""
    path = Path(path)
    return sorted(path / row["file"] for row in read_manifest(path))
