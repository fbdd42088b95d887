"""Named real-anatomy sets, built at run time from the held-out real CT livers (never shipped).

`real-val-v1` / `real-test-v1`: the split's 8 `val` (or `test`) livers, 4 FEM deformations each,
8 random crops per deformation, one per visibility bin [0.2,0.3) ... [0.9,1.0] (32 per bin).
`real-val-camera-v1` / `real-test-camera-v1`: the same livers and deformations seen by the
anterior laparoscope, 2 crops per deformation, both in [0.2,0.3): a 70-degree camera 80-150 mm
from a real liver sees 13 % of it (median; 22-31 % at most), far less than on the procedural
livers, so [0.3,0.4) is out of its reach and a request in [0.2,0.3) may need several poses.
`real-val-density-v1` / `real-test-density-v1`: 4 random crops (bins 0.2-0.6) and 2 camera crops
per deformation, each in three densities of the same crop and pose (`density` in the case):
uniform, the vertices of the liver's own decimated CT mesh (`mesh-vertices`, deformed with it)
and a depth camera's falloff (`depth-falloff`). Density twins are binned by the visibility of
their uniform twin (`visibility`); `visibility_measured` is their own M/N.
Noise: the benchmark adds it (`--noise-levels 2 --noise-bins all`). The sets live under the
data root like the in silico ones, and are skipped with one line when the real livers are absent.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.phantom.casefile import read_case, write_case
from liver_p2p_reg.phantom.dataset import (
    COMPLETE_MARKER,
    GENERATOR_VERSION,
    LOW_VISIBILITY_BINS,
    VISIBILITY_BINS,
    make_case,
    spec_record,
)
from liver_p2p_reg.phantom.manifest import manifest_row, read_manifest, write_manifest
from liver_p2p_reg.phantom.real import load_real_liver, real_liver_id, real_split, require_real_livers
from liver_p2p_reg.phantom.simulate import simulate_liver
from liver_p2p_reg.registration.visibility import VisibilityMeter

log = logging.getLogger(__name__)


@dataclass
class RealSetSpec:
    """Everything that determines a real-anatomy set (stored as dataset.json)."""

    split: str  # val | test (real_livers_split.json)
    deformations: int = 4
    random_bins: list = field(default_factory=list)  # one random crop per bin and deformation
    camera_bins: list = field(default_factory=list)  # one camera crop per bin and deformation
    densities: list = field(default_factory=lambda: ["uniform"])
    target_tets: int = 10_000
    generator_version: int = GENERATOR_VERSION
    livers: list = field(default_factory=list)  # filled from the split file when generated
    family: str = "fem"  # the deformation family (simulate.DEFORMATION_FAMILIES)


def _bins(bins: tuple) -> list:
    return [list(b) for b in bins]


DENSITY_TWINS = ["uniform", "mesh-vertices", "depth-falloff"]
REAL_CAMERA_BINS = (VISIBILITY_BINS[0], VISIBILITY_BINS[0])  # see the module docstring
CAMERA_ATTEMPTS = 8  # camera poses tried (deterministic seeds) before a target is skipped
REAL_SETS: dict[str, RealSetSpec] = {}
for _split in ("val", "test"):
    REAL_SETS[f"real-{_split}-v1"] = RealSetSpec(_split, random_bins=_bins(VISIBILITY_BINS))
    REAL_SETS[f"real-{_split}-camera-v1"] = RealSetSpec(_split, camera_bins=_bins(REAL_CAMERA_BINS))
    REAL_SETS[f"real-{_split}-density-v1"] = RealSetSpec(
        _split,
        random_bins=_bins(VISIBILITY_BINS[:4]),
        camera_bins=_bins(REAL_CAMERA_BINS),
        densities=DENSITY_TWINS,
    )


# v2: >= 128 poses in each bin from 0.05 to 0.3 (8 livers x 4 deformations x 4 crops per bin), fewer
# above; random crops and laparoscope crops as two sets, each in both deformation families ("-arap").
V2_LOW_BINS = (*LOW_VISIBILITY_BINS, VISIBILITY_BINS[0])
for _split in ("val", "test"):
    for _family, _suffix in (("fem", ""), ("arap", "-arap")):
        REAL_SETS[f"real-{_split}-v2{_suffix}"] = RealSetSpec(
            _split, random_bins=_bins(V2_LOW_BINS * 4 + VISIBILITY_BINS[1:]), family=_family
        )
        REAL_SETS[f"real-{_split}-camera-v2{_suffix}"] = RealSetSpec(
            _split, camera_bins=_bins(V2_LOW_BINS * 4), family=_family
        )


def real_set_spec(name: str) -> RealSetSpec:
    """The spec of a named real set with its livers filled in from the split file."""
    spec = RealSetSpec(**asdict(REAL_SETS[name]))
    spec.livers = real_split()[spec.split]
    return spec


def _case_file(liver_id: int, d: int, t: int, density: str) -> str:
    suffix = "" if density == "uniform" else f"_{density}"
    return f"case_L{liver_id:07d}_D{d:02d}_T{t:03d}{suffix}.npz"


def _targets(spec: RealSetSpec) -> list[tuple[str, list]]:
    return [("random", b) for b in spec.random_bins] + [("camera", b) for b in spec.camera_bins]


def _in_bin(visibility: float, lo: float, hi: float) -> bool:
    return lo <= visibility < hi or (hi >= 1.0 and visibility <= 1.0)


def _generate_real_liver(spec: RealSetSpec, stem: str, out: Path) -> list[dict]:
    """Simulate one real liver and write all its cases (deterministic: ids and indices only)."""
    import numpy as np

    liver_id = real_liver_id(stem)
    names = [
        _case_file(liver_id, d, t, dens)
        for d in range(spec.deformations)
        for t in range(len(_targets(spec)))
        for dens in spec.densities
    ]
    if all((out / n).exists() for n in names):
        return [manifest_row(out / n, read_case(out / n), spec.split) for n in names]
    liver = load_real_liver(stem)
    sim = simulate_liver(liver.seed, spec.deformations, target_tets=spec.target_tets, liver=liver, family=spec.family)
    meter = VisibilityMeter(sim.vertices_mm)
    rows = []
    for d in range(spec.deformations):
        for t, (crop, (lo, hi)) in enumerate(_targets(spec)):
            rng = np.random.default_rng([liver_id, 5, d, t])
            wanted = float(rng.uniform(lo + 0.005, min(hi, 0.97 if crop == "random" else 0.36) - 0.005))
            uniform, seed = None, 0
            for attempt in range(CAMERA_ATTEMPTS):  # a camera pose may miss the bin; retry deterministically
                seed = t + 100_000 * attempt
                try:
                    case = make_case(sim, d, wanted, crop, 0.0, seed=seed, meter=meter)
                except LiverP2PError:
                    continue
                if _in_bin(case["visibility"], lo, hi):
                    uniform = case
                    break
            if uniform is None:
                log.warning("skipped %s D%02d T%03d: requested visibility not reachable", stem, d, t)
                continue
            for density in spec.densities:
                case = uniform
                if density != "uniform":  # same crop and pose: the same seed, then the density's own draws
                    try:
                        case = make_case(sim, d, wanted, crop, 0.0, seed=seed, meter=meter, density=density)
                    except LiverP2PError as exc:
                        log.warning("skipped %s D%02d T%03d %s: %s", stem, d, t, density, exc)
                        continue
                    case["visibility_measured"] = case["visibility"]
                    case["visibility"] = uniform["visibility"]  # binned with its uniform twin
                case = dict(case, target_id=t, density=density, real_liver=stem)
                path = out / _case_file(liver_id, d, t, density)
                write_case(path, case)
                rows.append(manifest_row(path, case, spec.split))
    return rows


def is_complete(path: Path, spec: RealSetSpec) -> bool:
    """True when a finished run of this spec left its marker, manifest and every listed case."""
    spec_path = path / "dataset.json"
    if not (spec_path.is_file() and (path / COMPLETE_MARKER).is_file() and (path / "manifest.csv").is_file()):
        return False
    if json.loads(spec_path.read_text()) != spec_record(spec):
        return False
    return all((path / r["file"]).is_file() for r in read_manifest(path))


def ensure_real_set(name: str, root: Path, progress: bool = True) -> Path:
    """Path of the named real set under `root`, generating it when absent (needs the real livers)."""
    require_real_livers()
    spec = real_set_spec(name)
    path = Path(root) / name
    if is_complete(path, spec):
        return path
    path.mkdir(parents=True, exist_ok=True)
    spec_path = path / "dataset.json"
    if spec_path.is_file() and json.loads(spec_path.read_text()) != spec_record(spec):
        for file in path.glob("case_*.npz"):  # another spec or generator: start over
            file.unlink()
    spec_path.write_text(json.dumps(spec_record(spec), indent=2))
    (path / COMPLETE_MARKER).unlink(missing_ok=True)
    from tqdm import tqdm

    n_cases = len(spec.livers) * spec.deformations * len(_targets(spec)) * len(spec.densities)
    log.info("building %s: %d real livers, up to %d cases (a few minutes)", name, len(spec.livers), n_cases)
    rows = []
    for stem in tqdm(spec.livers, desc=name, unit="liver", disable=not progress):
        rows += _generate_real_liver(spec, stem, path)
    write_manifest(path, rows)
    if not rows:
        raise InputError(f"{name}: no case could be generated")
    (path / COMPLETE_MARKER).write_text(json.dumps({"cases": len(rows)}, indent=2))
    return path
