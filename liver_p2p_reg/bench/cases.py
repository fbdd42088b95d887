"""Benchmark cases: resolving a dataset name or folder, reading case NPZs, visibility bins, presets."""

from __future__ import annotations

import dataclasses
import hashlib
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from liver_p2p_reg.errors import InputError

# Visibility bins: where a laparoscope really looks, [0.05,0.10), [0.10,0.15), [0.15,0.20) (one
# 80-150 mm from a real liver sees 13 % of it, median), then the paper's Table I bins [0.2,0.3) ...
# [0.8,0.9) and the closed [0.9,1.0]. A table shows only the bins that hold cases, so the v1 sets
# (every case >= 0.2) give the tables they always gave.
BIN_EDGES = (0.05, 0.10, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)
PAPER_FIRST_BIN = BIN_EDGES.index(0.2)  # [0.2,0.3): the paper's lowest bin (its Table II noise rows)
BIN_LABELS = tuple(
    f"[{lo:.2f},{hi:.2f})" if lo < 0.2 else f"[{lo:.1f},{hi:.1f}{']' if i == len(BIN_EDGES) - 2 else ')'}"
    for i, (lo, hi) in enumerate(zip(BIN_EDGES, BIN_EDGES[1:], strict=False))
)
# Keys every case NPZ must carry (the phantom generator's format, close to the public P2P dataset).
REQUIRED_KEYS = ("src_pcd", "tgt_pcd", "src_marker", "tgt_marker")
PRESETS = ("smoke", "full")
SMOKE_CASES_PER_BIN = 3  # --preset smoke: this many cases per visibility bin (spread over livers)


@dataclass(frozen=True)
class CaseInfo:
    """Metadata of one case (the clouds are read again by whoever runs it)."""

    case_id: str
    path: Path
    visibility: float
    noise_mm: float
    crop_mode: str
    deformation_rms_mm: float
    seed: int
    added_noise_mm: float = 0.0  # sensor noise the benchmark adds to the target (Table II rows)
    density: str = "uniform"  # how the target samples its surface (phantom/artifacts.py)
    has_sensor_origin: bool = False  # the case stores where its camera stood (camera crops)


def visibility_bin(visibility: float) -> int | None:
    """Index of the visibility bin, or None outside [0.05, 1.0]."""
    if not np.isfinite(visibility) or visibility < BIN_EDGES[0] or visibility > BIN_EDGES[-1]:
        return None
    return min(int(np.searchsorted(BIN_EDGES, visibility, side="right")) - 1, len(BIN_LABELS) - 1)


def read_case(path: Path) -> dict[str, Any]:
    """Read one case NPZ into a dict of arrays and Python scalars; InputError if unusable."""
    try:
        from liver_p2p_reg.phantom.casefile import read_case as phantom_read_case  # the generator's own reader
    except ImportError:
        phantom_read_case = None
    try:
        if phantom_read_case is not None:
            data = dict(phantom_read_case(path))
        else:
            with np.load(path, allow_pickle=False) as npz:
                data = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"cannot read case {path}: {exc}") from None
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        raise InputError(f"case {path} lacks {', '.join(missing)}")
    out: dict[str, Any] = {}
    for key, value in data.items():
        arr = np.asarray(value)
        out[key] = arr.item() if arr.ndim == 0 else arr
    return out


def case_info(path: Path) -> CaseInfo:
    """Metadata of the case at `path` (missing optional fields get neutral values)."""
    data = read_case(path)
    case_id = path.stem
    seed = data.get("seed")
    if seed is None:
        # Cases without a stored seed still get a stable one, derived from their name.
        seed = zlib.crc32(case_id.encode())
    return CaseInfo(
        case_id=case_id,
        path=path,
        visibility=float(data.get("visibility", np.nan)),
        noise_mm=float(data.get("noise_mm", 0.0)),
        crop_mode=str(data.get("crop_mode", "")),
        deformation_rms_mm=float(data.get("deformation_rms_mm", np.nan)),
        seed=int(seed),
        density=str(data.get("density", "uniform")),
        has_sensor_origin=sensor_origin_mm(data) is not None,
    )


def sensor_origin_mm(data: dict[str, Any]) -> np.ndarray | None:
    """The camera position a case stores (mm, target frame); None when it has none (random crops, older files)."""
    from liver_p2p_reg.phantom.casefile import sensor_origin_mm as stored_origin  # the generator owns the key

    return stored_origin(data)


NOISE_BINS = ("lowest", "all")


def with_noise(infos: list[CaseInfo], levels_mm: list[float], bins: str = "lowest") -> list[CaseInfo]:
    """Add noisy copies, one per level > 0, of the cases in the paper's lowest bin [0.2,0.3) (its
    Table II; bins="lowest") or, with bins="all", of every case."""
    if bins not in NOISE_BINS:
        raise InputError(f"noise bins must be one of {NOISE_BINS}, got {bins!r}")
    extra = []
    for info in infos:
        if bins == "lowest" and visibility_bin(info.visibility) != PAPER_FIRST_BIN:
            continue
        for level in levels_mm:
            if level > 0:
                extra.append(
                    dataclasses.replace(
                        info,
                        case_id=f"{info.case_id}+noise{level:g}mm",
                        noise_mm=info.noise_mm + level,
                        added_noise_mm=level,
                    )
                )
    return sorted(infos + extra, key=lambda c: c.case_id)


def add_target_noise(target_mm: np.ndarray, info: CaseInfo) -> np.ndarray:
    """Uniform noise in [-0.5, 0.5] x level mm per coordinate (the paper's model), seeded per case."""
    if info.added_noise_mm <= 0:
        return target_mm
    rng = np.random.default_rng([info.seed, int(round(info.added_noise_mm * 1000))])
    return target_mm + rng.uniform(-0.5, 0.5, size=target_mm.shape) * info.added_noise_mm


def resolve_dataset(dataset: str, data_root: Path | None, livers: list[int] | None = None) -> tuple[Path, str]:
    """A folder of case NPZs, or a named test set generated (once) under `data_root`.

    `livers`: of a named set, build only these livers (`planned_cases`). Returns the folder and
    the dataset's identity recorded in the run settings.
    """
    path = Path(dataset)
    if path.is_dir():
        return path, str(path.resolve())
    if path.suffix or "/" in dataset:
        raise InputError(f"dataset folder {dataset} does not exist")
    try:
        from liver_p2p_reg.phantom import testset
    except ImportError:
        raise InputError(
            f"named test set {dataset!r} needs the phantom generator (liver_p2p_reg.phantom.testset)"
        ) from None
    return Path(testset.ensure_testset(dataset, root=data_root, livers=livers)), dataset


def planned_cases(dataset: str, preset: str, limit: int | None) -> tuple[list[int], list[str]] | None:
    """Of a named test set: the livers to build and the case files the preset and --limit select.

    Chosen from the set's design (every case it makes, with its requested visibility bin), not
    from what is on disk, so `--preset smoke` builds a few livers instead of the whole set and
    picks the same cases whether or not the rest exists. None for a dataset folder.
    """
    if Path(dataset).is_dir() or Path(dataset).suffix or "/" in dataset:
        return None
    try:
        from liver_p2p_reg.phantom.realsets import REAL_SETS
        from liver_p2p_reg.phantom.testset import expected_cases
    except ImportError:
        return None
    if dataset in REAL_SETS:  # built whole, from the real livers
        return None
    design = expected_cases(dataset)
    liver_of = {name: liver for liver, name, _ in design}
    infos = [
        CaseInfo(Path(name).stem, Path(name), visibility, 0.0, "", float("nan"), 0) for _, name, visibility in design
    ]
    chosen = [str(info.path) for info in select_cases(infos, preset, limit)]
    return sorted({liver_of[name] for name in chosen}), chosen


def list_case_paths(folder: Path) -> list[Path]:
    """All case NPZs of a dataset folder, in a stable order."""
    try:
        from liver_p2p_reg.phantom.testset import testset_cases
    except ImportError:
        testset_cases = None
    paths: list[Path] = []
    if testset_cases is not None:
        try:
            paths = [Path(p) for p in testset_cases(folder)]
        except Exception:  # not a generator-made folder (no manifest): fall back to the files
            paths = []
    if not paths:
        paths = sorted(folder.rglob("*.npz"))
    if not paths:
        raise InputError(f"no case files (*.npz) in {folder}")
    return sorted(paths, key=lambda p: p.stem)


def select_cases(infos: list[CaseInfo], preset: str, limit: int | None) -> list[CaseInfo]:
    """Apply the preset (smoke: first cases of each visibility bin) and --limit, in case-id order."""
    if preset not in PRESETS:
        raise InputError(f"preset must be one of {PRESETS}, got {preset!r}")
    infos = sorted(infos, key=lambda c: c.case_id)
    if preset == "smoke":
        infos = first_per_bin(infos, SMOKE_CASES_PER_BIN)
    if limit is not None:
        if limit < 1:
            raise InputError(f"--limit must be >= 1, got {limit}")
        infos = infos[:limit]
    return infos


def first_per_bin(infos: list[CaseInfo], per_bin: int) -> list[CaseInfo]:
    """`per_bin` cases of every visibility bin, evenly spread over the bin's cases in case-id order.

    Spreading (rather than taking the first ones) mixes livers and deformations into small presets.
    """
    groups: dict[int | None, list[CaseInfo]] = {}
    for info in sorted(infos, key=lambda c: c.case_id):
        groups.setdefault(visibility_bin(info.visibility), []).append(info)
    chosen = []
    for group in groups.values():
        if len(group) <= per_bin:
            chosen += group
        else:
            picks = np.unique(np.round(np.linspace(0, len(group) - 1, per_bin)).astype(int))
            chosen += [group[i] for i in picks]
    return sorted(chosen, key=lambda c: c.case_id)


def fingerprint(infos: list[CaseInfo]) -> str:
    """Short hash of the selected case ids (detects a changed dataset behind the same name)."""
    digest = hashlib.sha256("\n".join(c.case_id for c in infos).encode()).hexdigest()
    return digest[:16]


def case_seed(base_seed: int, info: CaseInfo) -> int:
    """The seed a method gets on this case: fixed per case, independent of order and workers.

    Mixes the stored seed with the case id, so cases that share a stored seed still differ.
    """
    mixed = zlib.crc32(f"{base_seed}:{info.seed}:{info.case_id}".encode())
    return int(mixed % (2**31 - 1))
