"""In silico datasets: cases made from simulated livers and generated deterministically into a folder.

Every random stream is derived from indices only -- liver id, deformation index, target index
-- never from worker order, so a dataset is identical for any number of workers and can be
resumed (finished case files are skipped). Liver ids are `seed * 10000 + liver index`; seeds
900-999 are reserved for the named test and validation sets (testset.py), so training livers drawn with any
other seed are disjoint from them by construction.
"""

from __future__ import annotations

import json
import logging
import zipfile
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.phantom.casefile import SENSOR_ORIGIN_KEY, TRIANGLES_KEY, read_case, write_case
from liver_p2p_reg.phantom.crop import CROP_MODES, make_target
from liver_p2p_reg.phantom.manifest import manifest_row, read_manifest, write_manifest
from liver_p2p_reg.phantom.simulate import DEFORMATION_FAMILIES, SimulatedLiver, simulate_liver
from liver_p2p_reg.pools import spawn_pool
from liver_p2p_reg.registration.visibility import VisibilityMeter

log = logging.getLogger(__name__)

GENERATOR_VERSION = 2  # bump whenever generated data would change (stale sets are then rebuilt)
VISIBILITY_BINS = tuple((round(0.2 + 0.1 * i, 1), round(0.3 + 0.1 * i, 1)) for i in range(8))
# A full resampled target occupies a few percent fewer voxels than the source (its own grid
# offset, sampling gaps), so the top bin is drawn from [0.9, 0.97].
MAX_RANDOM_VISIBILITY = 0.97
# A 70-degree laparoscope 80-150 mm from the anterior surface sees 14-38 % of the liver (5-95 %
# of random poses, median 26 %); camera targets use these two bins.
CAMERA_VISIBILITY_BINS = VISIBILITY_BINS[:2]
# Below the paper's bins, where a laparoscope looks (the v2 sets): [0.05,0.10), [0.10,0.15), [0.15,0.20).
LOW_VISIBILITY_BINS = ((0.05, 0.1), (0.1, 0.15), (0.15, 0.2))
MAX_CAMERA_VISIBILITY = 0.36  # requests above this often need more than a camera can see
RESERVED_SEEDS = range(900, 1000)
# Liver ids of the real livers (phantom/real.py) are REAL_LIVER_SEED * 10_000 + their number.
REAL_LIVER_SEED = 500
MAX_LIVERS_PER_SEED = 10_000
COMPLETE_MARKER = "complete.json"


def make_case(
    sim: SimulatedLiver,
    deformation_index: int,
    visibility: float,
    crop_mode: str = "random",
    noise_mm: float = 0.0,
    seed: int = 0,
    meter: VisibilityMeter | None = None,
    density: str = "uniform",
) -> dict:
    """One registration case from a simulated liver: source = undeformed surface, target = crop.

    tgt_pcd = R_gt @ deformed + t_gt (+ noise); tgt_marker = R_gt @ deformed fiducials + t_gt.
    `density` (crop.make_target) samples the same crop and pose otherwise; `mesh-vertices` uses a
    liver read from a file's own deformed vertices where it has them.
    """
    if not 0 <= deformation_index < len(sim.deformations):
        raise InputError(f"deformation index {deformation_index} out of range (liver has {len(sim.deformations)})")
    deformation = sim.deformations[deformation_index]
    rng = np.random.default_rng([int(sim.liver_id), 4, int(deformation_index), int(seed)])
    target = make_target(
        sim.vertices_mm,
        deformation.surface_mm,
        sim.triangles,
        visibility,
        crop_mode,
        noise_mm,
        rng,
        meter=meter,
        density=density,
        coarse_mm=deformation.coarse_mm if density == "mesh-vertices" else None,
    )
    R, t = target["R_gt"], target["t_gt"]
    case = {
        "src_pcd": np.asarray(sim.vertices_mm, dtype=np.float64),
        TRIANGLES_KEY: np.asarray(sim.triangles, dtype=np.int32),
        "tgt_pcd": target["tgt_pcd"],
        "src_marker": np.asarray(sim.fiducials_mm, dtype=np.float64),
        "tgt_marker": deformation.fiducials_mm @ R.T + t,
        "R_gt": R,
        "t_gt": t,
        "visibility": target["visibility"],
        "visibility_requested": target["visibility_requested"],
        "deformation_rms_mm": float(deformation.rms_mm),
        "deformation_max_mm": float(deformation.max_mm),
        "noise_mm": float(noise_mm),
        "crop_mode": crop_mode,
        "liver_id": int(sim.liver_id),
        "deformation_id": int(deformation_index),
        "target_id": 0,
        "seed": int(seed),
        "generator_version": GENERATOR_VERSION,
    }
    eye = target["crop_info"].get("eye_mm")
    if eye is not None:  # the eye moves with the target: the same R_gt, t_gt (noise is the sensor's own)
        case[SENSOR_ORIGIN_KEY] = R @ np.asarray(eye, dtype=np.float64) + t
    return case


@dataclass
class DatasetSpec:
    """Everything that determines a generated dataset (stored as dataset.json)."""

    livers: int
    deformations: int
    targets: int
    crop: str = "random"
    noise_mm: float = 0.0
    seed: int = 0
    split: str = "train"
    target_tets: int = 10_000
    generator_version: int = GENERATOR_VERSION
    visibility_bins: list = field(default_factory=list)
    family: str = "fem"  # the deformation family (simulate.DEFORMATION_FAMILIES)

    def validate(self, allow_reserved: bool = False) -> DatasetSpec:
        if self.livers < 1 or self.livers > MAX_LIVERS_PER_SEED:
            raise InputError(f"--livers must be in [1, {MAX_LIVERS_PER_SEED}], got {self.livers}")
        if self.deformations < 1:
            raise InputError(f"--deformations must be >= 1, got {self.deformations}")
        if self.targets < 1:
            raise InputError(f"--targets must be >= 1, got {self.targets}")
        if self.crop not in CROP_MODES:
            raise InputError(f"--crop must be one of {', '.join(CROP_MODES)}, got {self.crop!r}")
        if not 0 <= self.noise_mm <= 50:
            raise InputError(f"--noise must be in [0, 50] mm, got {self.noise_mm}")
        if self.seed < 0:
            raise InputError(f"--seed must be >= 0, got {self.seed}")
        if self.seed == REAL_LIVER_SEED:
            raise InputError(f"--seed {REAL_LIVER_SEED} names the real livers' ids; pick another")
        if self.seed in RESERVED_SEEDS and not allow_reserved:
            raise InputError(
                f"--seed {self.seed} is reserved for the named test and validation sets (900-999); pick another"
            )
        if self.target_tets < 500:
            raise InputError(f"target_tets must be >= 500, got {self.target_tets}")
        if self.family not in DEFORMATION_FAMILIES:
            raise InputError(f"--family must be one of {', '.join(DEFORMATION_FAMILIES)}, got {self.family!r}")
        if not self.visibility_bins:
            bins = CAMERA_VISIBILITY_BINS if self.crop == "camera" else VISIBILITY_BINS
            self.visibility_bins = [list(b) for b in bins]
        return self


def spec_record(spec: Any) -> dict:
    """A set's spec as stored in its dataset.json: every field, but `family` only when it is not the
    default "fem", so the sets made before families existed still match their stored spec."""
    record = asdict(spec)
    if record.get("family") == "fem":
        del record["family"]
    return record


def liver_id_for(seed: int, index: int) -> int:
    """The liver id (= anatomy seed) of liver `index` of a dataset generated with `seed`."""
    return int(seed) * MAX_LIVERS_PER_SEED + int(index)


def case_name(liver_id: int, deformation: int, target: int) -> str:
    return f"case_L{liver_id:07d}_D{deformation:02d}_T{target:03d}.npz"


def requested_visibility(spec: DatasetSpec, liver_id: int, deformation: int, target: int) -> float:
    """Target t of a deformation falls in bin t mod n_bins (balanced bins), uniform inside it."""
    lo, hi = spec.visibility_bins[target % len(spec.visibility_bins)]
    hi = min(hi, MAX_CAMERA_VISIBILITY if spec.crop == "camera" else MAX_RANDOM_VISIBILITY)
    rng = np.random.default_rng([int(liver_id), 5, int(deformation), int(target)])
    return float(rng.uniform(lo + 0.005, hi - 0.005))


def _generate_liver(args: tuple[DatasetSpec, int, str]) -> list[dict]:
    """Worker: simulate one liver and write all its cases; returns manifest rows."""
    spec, liver_index, out = args
    out_dir = Path(out)
    liver_id = liver_id_for(spec.seed, liver_index)
    paths = [out_dir / case_name(liver_id, d, t) for d in range(spec.deformations) for t in range(spec.targets)]
    if all(case_is_current(p, spec.crop) for p in paths):  # resumed run: nothing to simulate for this liver
        return [manifest_row(p, read_case(p), spec.split) for p in paths]
    sim = simulate_liver(liver_id, spec.deformations, target_tets=spec.target_tets, family=spec.family)
    meter = VisibilityMeter(sim.vertices_mm)
    rows = []
    for d in range(spec.deformations):
        for t in range(spec.targets):
            path = out_dir / case_name(liver_id, d, t)
            if case_is_current(path, spec.crop):
                rows.append(manifest_row(path, read_case(path), spec.split))
                continue
            case = None
            wanted = requested_visibility(spec, liver_id, d, t)
            lo, hi = spec.visibility_bins[t % len(spec.visibility_bins)]
            for attempt in range(4):  # a camera pose may miss the request; retry deterministically
                seed = t + 100_000 * attempt
                try:
                    case = make_case(sim, d, wanted, spec.crop, spec.noise_mm, seed=seed, meter=meter)
                except LiverP2PError as exc:
                    log.debug("liver %d def %d target %d attempt %d: %s", liver_id, d, t, attempt, exc)
                    continue
                # Keep bins balanced: the achieved visibility must stay in the requested bin.
                if lo <= case["visibility"] < hi or (hi >= 1.0 and case["visibility"] <= 1.0):
                    break
                case = None
            if case is None:
                log.warning("skipped %s: requested visibility not reachable", path.name)
                continue
            case["target_id"] = t
            write_case(path, case)
            rows.append(manifest_row(path, case, spec.split))
    return rows


def case_is_current(path: Path, crop: str) -> bool:
    """A finished case file of this generator; a camera crop made before the camera position was
    stored is not (regenerating it changes nothing else: the generator is deterministic)."""
    if not path.is_file():
        return False
    if crop != "camera":
        return True
    try:
        with zipfile.ZipFile(path) as archive:  # the key list only, no array is read
            return f"{SENSOR_ORIGIN_KEY}.npy" in archive.namelist()
    except (OSError, zipfile.BadZipFile):
        return False


def generate_dataset(
    out: str | Path,
    spec: DatasetSpec,
    workers: int = 1,
    progress: bool = True,
    allow_reserved_seed: bool = False,
    on_liver_done: Callable[[int], None] | None = None,
    livers: Sequence[int] | None = None,
) -> Path:
    """Generate (or finish) a dataset in `out`; returns the manifest path (manifest.csv).

    `livers`: only these liver indices (the cases a small benchmark preset uses); the set is then
    left unfinished (no completion marker) and a later full run adds the other livers.
    """
    spec.validate(allow_reserved=allow_reserved_seed)
    if workers < 1:
        raise InputError(f"--workers must be >= 1, got {workers}")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out} exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    spec_path = out / "dataset.json"
    if spec_path.exists():
        old = json.loads(spec_path.read_text())
        if old != spec_record(spec):
            raise InputError(f"{out} holds a dataset with different parameters; use another --out")
    elif any(out.iterdir()):  # every folder a run made holds dataset.json (written first): this one is someone's
        raise InputError(f"{out} is not empty and holds no dataset.json; give an empty or new folder as --out")
    spec_path.write_text(json.dumps(spec_record(spec), indent=2))
    (out / COMPLETE_MARKER).unlink(missing_ok=True)
    rows_by_liver: dict[int, list[dict]] = {}
    indices = sorted(set(livers)) if livers is not None else list(range(spec.livers))
    if any(not 0 <= i < spec.livers for i in indices):
        raise InputError(f"liver indices must lie in [0, {spec.livers}), got {indices}")
    jobs = [(spec, i, str(out)) for i in indices]
    from tqdm import tqdm

    bar = tqdm(total=len(jobs), desc="livers", unit="liver", disable=not progress)
    if workers == 1:
        for job in jobs:
            rows_by_liver[job[1]] = _generate_liver(job)
            bar.update(1)
    else:
        with spawn_pool(workers) as pool:
            for job, rows in zip(jobs, pool.map(_generate_liver, jobs), strict=True):
                rows_by_liver[job[1]] = rows
                bar.update(1)
    bar.close()
    rows = [row for i in sorted(rows_by_liver) for row in rows_by_liver[i]]
    if len(indices) < spec.livers:  # part of the set: keep the livers earlier partial runs made; not complete
        ids = {liver_id_for(spec.seed, i) for i in indices}
        old = read_manifest(out) if (out / "manifest.csv").is_file() else []
        rows = sorted([r for r in old if r["liver_id"] not in ids] + rows, key=lambda r: r["file"])
        return write_manifest(out, rows)
    manifest = write_manifest(out, rows)
    expected = [
        case_name(liver_id_for(spec.seed, i), d, t)
        for i in range(spec.livers)
        for d in range(spec.deformations)
        for t in range(spec.targets)
    ]
    written = {row["file"] for row in rows}
    skipped = [name for name in expected if name not in written]
    # Written last: its presence means the run finished (skipped cases are deterministic).
    (out / COMPLETE_MARKER).write_text(json.dumps({"cases": len(rows), "skipped": skipped}, indent=2))
    return manifest
