"""Training store of simulated livers and the paper's dynamic pairing of fresh random training pairs.

Store layout (`liver-p2p dataset generate --store DIR ...`): `store.json` plus one
`liver_<id>.npz` per liver holding the undeformed surface (vertices, triangles), its fiducials
and every deformation (surfaces (D, V, 3), fiducials (D, F, 3), RMS and max displacement).
`PairSampler` draws a liver, two different shapes among {undeformed, deformations} as source
and target, then a fresh crop, pose and noise: the same target pipeline as the test cases.
"""

from __future__ import annotations

import json
import zipfile
import zlib
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.phantom.artifacts import DENSITY_MODES, Artifacts
from liver_p2p_reg.phantom.crop import CROP_MODES, make_target
from liver_p2p_reg.phantom.dataset import (
    GENERATOR_VERSION,
    MAX_CAMERA_VISIBILITY,
    MAX_LIVERS_PER_SEED,
    REAL_LIVER_SEED,
    RESERVED_SEEDS,
    liver_id_for,
)
from liver_p2p_reg.phantom.simulate import SimulatedLiver, simulate_liver
from liver_p2p_reg.pools import spawn_pool
from liver_p2p_reg.registration.visibility import VisibilityMeter

STORE_VERSION = 1
MIN_VISIBILITY = 0.05  # the smallest visibility a pair may be asked for (smaller views hold a handful of points)


class StoreFileError(InputError):
    """A store's liver file is missing or damaged: drawing another pair would not help."""


def read_store_meta(store: Path) -> dict:
    """A store's store.json as a mapping whose `livers` is a list of file names; InputError naming the file."""
    path = Path(store) / "store.json"
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path} is unreadable or damaged ({exc}); remove it to rebuild the store") from None
    livers = meta.get("livers", []) if isinstance(meta, dict) else None
    if not isinstance(livers, list) or not all(isinstance(name, str) for name in livers):
        raise InputError(f"{path} is damaged (no list of liver files); remove it to rebuild the store")
    return meta


DAMAGE = (OSError, ValueError, zipfile.BadZipFile, EOFError, zlib.error)  # a missing, truncated or corrupt .npz


def _store_file_error(path: Path, why: object) -> StoreFileError:
    """The one-line error of a missing or damaged store liver, saying how to mend the store."""
    if isinstance(why, FileNotFoundError):
        return StoreFileError(f"store liver {path} is missing; rebuild the store (remove its store.json)")
    return StoreFileError(f"store liver {path} is damaged ({why}); remove it and its store.json to rebuild it")


def liver_file_shapes(path: Path) -> dict[str, tuple[int, ...]]:
    """The array shapes of a store liver file, read from the .npy headers (no array decompressed);
    StoreFileError naming a missing or damaged file."""
    fmt = np.lib.format
    try:
        with zipfile.ZipFile(path) as archive:
            shapes = {}
            for name in archive.namelist():
                with archive.open(name) as member:
                    header = (
                        fmt.read_array_header_1_0 if fmt.read_magic(member) == (1, 0) else fmt.read_array_header_2_0
                    )
                    shapes[name.removesuffix(".npy")] = header(member)[0]
    except DAMAGE as exc:
        raise _store_file_error(path, exc) from None
    missing = sorted({"vertices_mm", "triangles", "surfaces_mm", "fiducials_mm"} - set(shapes))
    if missing:
        raise _store_file_error(path, f"no {', '.join(missing)}")
    return shapes


def _check_reused_liver(path: Path, deformations: int, target_tets: int) -> None:
    """A liver file left by an interrupted build is reused only when it was simulated as this build asks
    (files written before the tets were recorded are checked for their deformations only)."""
    shapes = liver_file_shapes(path)
    found = shapes["surfaces_mm"][0]
    recorded = None
    if "target_tets" in shapes:
        try:
            with np.load(path, allow_pickle=False) as data:
                recorded = int(data["target_tets"])
        except DAMAGE as exc:
            raise _store_file_error(path, exc) from None
    if found != deformations or recorded not in (None, target_tets):
        tets = "" if recorded is None else f" and {recorded} target tets"
        raise InputError(
            f"{path} holds a liver simulated with {found} deformations{tets}; this store asks {deformations} "
            f"and {target_tets}; remove it or use another store directory"
        )


def _store_liver(args: tuple[int, int, int, str]) -> str:
    liver_id, deformations, target_tets, out = args
    path = Path(out) / f"liver_{liver_id:07d}.npz"
    if path.exists():
        _check_reused_liver(path, deformations, target_tets)
        return path.name
    write_store_liver(path, simulate_liver(liver_id, deformations, target_tets=target_tets), target_tets)
    return path.name


def write_store_liver(path: Path, sim: SimulatedLiver, target_tets: int | None = None) -> None:
    """One liver of a store (atomically); livers read from a file also keep their coarse vertices.
    `target_tets` is recorded so an interrupted build can tell whether the file fits it."""
    arrays = {
        "liver_id": np.int64(sim.liver_id),
        "vertices_mm": sim.vertices_mm.astype(np.float32),
        "triangles": sim.triangles.astype(np.int32),
        "fiducials_mm": sim.fiducials_mm,
        "surfaces_mm": np.stack([d.surface_mm for d in sim.deformations]).astype(np.float32),
        "deformed_fiducials_mm": np.stack([d.fiducials_mm for d in sim.deformations]),
        "rms_mm": np.array([d.rms_mm for d in sim.deformations]),
        "max_mm": np.array([d.max_mm for d in sim.deformations]),
    }
    if sim.coarse_vertices_mm is not None:
        arrays["coarse_vertices_mm"] = sim.coarse_vertices_mm.astype(np.float32)
        arrays["coarse_surfaces_mm"] = np.stack([d.coarse_mm for d in sim.deformations]).astype(np.float32)
    if target_tets is not None:
        arrays["target_tets"] = np.int64(target_tets)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(path)


def _store_real_liver(args: tuple[str, int, int, str]) -> str:
    from liver_p2p_reg.phantom.real import load_real_liver, real_liver_id

    stem, deformations, target_tets, out = args
    path = Path(out) / f"liver_{real_liver_id(stem):07d}.npz"
    if path.exists():
        _check_reused_liver(path, deformations, target_tets)
        return path.name
    liver = load_real_liver(stem)
    write_store_liver(path, simulate_liver(liver.seed, deformations, target_tets=target_tets, liver=liver), target_tets)
    return path.name


def build_real_store(
    store_dir: str | Path,
    stems: Sequence[str],
    deformations: int,
    workers: int = 1,
    target_tets: int = 10_000,
    progress: bool = True,
) -> Path:
    """FEM-deform the real livers `stems` (../shared/data/livers) into a training store."""
    from liver_p2p_reg.phantom.real import require_real_livers

    require_real_livers()
    if deformations < 1:
        raise InputError(f"deformations must be >= 1, got {deformations}")
    store = Path(store_dir)
    store.mkdir(parents=True, exist_ok=True)
    meta = {
        "store_version": STORE_VERSION,
        "generator_version": GENERATOR_VERSION,
        "kind": "real",
        "real_livers": sorted(stems),
        "deformations": deformations,
        "target_tets": target_tets,
    }
    listed = _check_same_store(store, meta)
    jobs = [(stem, deformations, target_tets, str(store)) for stem in sorted(stems)]
    return _finish_store(store, meta, listed + _run_jobs(_store_real_liver, jobs, workers, progress))


def _check_same_store(store: Path, meta: dict) -> list[str]:
    """Refuse a store.json of other parameters; the livers it lists (none without one)."""
    if not (store / "store.json").exists():
        return []
    old = read_store_meta(store)
    if {k: old.get(k) for k in meta} != meta:
        raise InputError(f"{store} holds a store with different parameters; use another directory")
    return old["livers"]


def _run_jobs(fn, jobs: list, workers: int, progress: bool) -> list[str]:
    """Run the liver jobs (in `workers` processes); the file names they return."""
    from tqdm import tqdm

    names = []
    with tqdm(total=len(jobs), desc="livers", unit="liver", disable=not progress) as bar:
        if workers == 1:
            for job in jobs:
                names.append(fn(job))
                bar.update(1)
        else:
            with spawn_pool(workers) as pool:
                for name in pool.map(fn, jobs):
                    names.append(name)
                    bar.update(1)
    return names


def _finish_store(store: Path, meta: dict, names: list[str]) -> Path:
    """Write store.json listing `names` (built now or listed before), never a stray file of another build."""
    meta["livers"] = sorted(set(names))
    (store / "store.json").write_text(json.dumps(meta, indent=2))
    return store


def build_store(
    store_dir: str | Path,
    livers: int,
    deformations: int,
    seed: int = 0,
    workers: int = 1,
    target_tets: int = 10_000,
    progress: bool = True,
) -> Path:
    """Simulate `livers` livers with `deformations` deformations each into a training store."""
    if livers < 1 or livers > MAX_LIVERS_PER_SEED:
        raise InputError(f"--livers must be in [1, {MAX_LIVERS_PER_SEED}], got {livers}")
    if deformations < 1:
        raise InputError(f"--deformations must be >= 1, got {deformations}")
    if seed < 0 or seed in RESERVED_SEEDS or seed == REAL_LIVER_SEED:
        raise InputError(
            f"--seed must be >= 0, outside 900-999 (test livers) and not {REAL_LIVER_SEED} (real livers), got {seed}"
        )
    if workers < 1:
        raise InputError(f"--workers must be >= 1, got {workers}")
    store = Path(store_dir)
    store.mkdir(parents=True, exist_ok=True)
    meta = {
        "store_version": STORE_VERSION,
        "generator_version": GENERATOR_VERSION,
        "seed": seed,
        "deformations": deformations,
        "target_tets": target_tets,
    }
    listed = _check_same_store(store, meta)
    jobs = [(liver_id_for(seed, i), deformations, target_tets, str(store)) for i in range(livers)]
    return _finish_store(store, meta, listed + _run_jobs(_store_liver, jobs, workers, progress))


class PairSampler:
    """Fresh random training pairs from a store (deterministic sequence for a given seed)."""

    def __init__(
        self,
        store_dir: str | Path,
        seed: int,
        visibility_range: tuple[float, float] = (0.2, 0.97),
        crop_modes: Sequence[str] = ("random",),
        noise_levels_mm: Sequence[float] = (0.0,),
        cache_livers: int = 64,
        density_modes: Sequence[str] = ("uniform",),
        artifacts: Artifacts | None = None,
        source_undeformed: bool = False,
    ) -> None:
        self.store = Path(store_dir)
        meta_path = self.store / "store.json"
        if not meta_path.is_file():
            raise InputError(f"{self.store}: no store.json (build one with `liver-p2p dataset generate --store`)")
        self.files = sorted(self.store / name for name in read_store_meta(self.store)["livers"])
        self.files = [f for f in self.files if f.is_file()]
        if not self.files:
            raise InputError(f"{self.store}: the store holds no livers")
        lo, hi = visibility_range
        if not MIN_VISIBILITY <= lo <= hi <= 1.0:
            raise InputError(f"visibility range must satisfy {MIN_VISIBILITY} <= lo <= hi <= 1, got {visibility_range}")
        bad = [m for m in crop_modes if m not in CROP_MODES]
        if bad or not crop_modes:
            raise InputError(f"crop modes must be among {CROP_MODES}, got {list(crop_modes)}")
        self.visibility_range = (float(lo), float(hi))
        self.crop_modes = tuple(crop_modes)
        self.noise_levels_mm = tuple(float(n) for n in noise_levels_mm) or (0.0,)
        bad = [m for m in density_modes if m not in DENSITY_MODES]
        if bad or not density_modes:
            raise InputError(f"density modes must be among {DENSITY_MODES}, got {list(density_modes)}")
        self.density_modes = tuple(density_modes)
        self.artifacts = artifacts
        # Patient preparation: the source is always the undeformed (preoperative) shape.
        self.source_undeformed = source_undeformed
        self.rng = np.random.default_rng([int(seed), 6])
        self.seed = int(seed)
        self.count = 0
        self._cache: OrderedDict[Path, dict] = OrderedDict()
        self._cache_size = max(1, cache_livers)

    def __len__(self) -> int:
        return len(self.files)

    def reseed(self, seed: int) -> None:
        """Restart the random stream (e.g. one distinct seed per DataLoader worker process)."""
        self.rng = np.random.default_rng([int(seed), 6])
        self.seed = int(seed)
        self.count = 0

    def __iter__(self):
        """Endless stream of fresh pairs."""
        while True:
            yield self.sample()

    def _liver(self, path: Path) -> dict:
        if path in self._cache:
            self._cache.move_to_end(path)
            return self._cache[path]
        try:
            with np.load(path, allow_pickle=False) as data:
                liver = {k: data[k] for k in data.files}
        except DAMAGE as exc:
            raise _store_file_error(path, exc) from None
        liver["meters"] = {}
        self._cache[path] = liver
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return liver

    def sample(self) -> dict:
        """One training pair with the keys of a test case (tgt = R_gt @ target shape + t_gt).

        deformation_id is the target shape's deformation index (-1: the undeformed liver);
        deformation_rms_mm / _max_mm compare the source and target shapes' fiducials.
        """
        for _ in range(20):
            rng = self.rng
            liver = self._liver(self.files[int(rng.integers(len(self.files)))])
            n_shapes = 1 + len(liver["surfaces_mm"])
            if self.source_undeformed:
                s, t = 0, int(rng.integers(1, n_shapes))
            else:
                s, t = rng.choice(n_shapes, size=2, replace=False)
            src = liver["vertices_mm"] if s == 0 else liver["surfaces_mm"][s - 1]
            tgt = liver["vertices_mm"] if t == 0 else liver["surfaces_mm"][t - 1]
            src_fid = liver["fiducials_mm"] if s == 0 else liver["deformed_fiducials_mm"][s - 1]
            tgt_fid = liver["fiducials_mm"] if t == 0 else liver["deformed_fiducials_mm"][t - 1]
            src = src.astype(np.float64)
            meter = liver["meters"].get(int(s))
            if meter is None:
                meter = liver["meters"][int(s)] = VisibilityMeter(src)
            mode = str(rng.choice(self.crop_modes))
            lo, hi = self.visibility_range
            if mode == "camera":  # a laparoscope rarely sees more; larger requests only fail
                hi = max(lo, min(hi, MAX_CAMERA_VISIBILITY))
            visibility = float(rng.uniform(lo, hi))
            noise = float(rng.choice(self.noise_levels_mm))
            # Drawn only when configured, so stores sampled without them keep their old streams.
            density = str(rng.choice(self.density_modes)) if self.density_modes != ("uniform",) else "uniform"
            coarse = None
            if density == "mesh-vertices" and "coarse_surfaces_mm" in liver:
                coarse = liver["coarse_vertices_mm"] if t == 0 else liver["coarse_surfaces_mm"][t - 1]
            try:
                target = make_target(
                    src,
                    tgt.astype(np.float64),
                    liver["triangles"],
                    visibility,
                    mode,
                    noise,
                    rng,
                    meter=meter,
                    density=density,
                    coarse_mm=coarse,
                    artifacts=self.artifacts,
                )
            except LiverP2PError:
                continue  # e.g. a camera cannot see that much; draw another pair
            self.count += 1
            R, tr = target["R_gt"], target["t_gt"]
            d = tgt_fid - src_fid
            return {
                "src_pcd": src,
                "tgt_pcd": target["tgt_pcd"],
                "src_marker": src_fid.astype(np.float64),
                "tgt_marker": tgt_fid @ R.T + tr,
                "R_gt": R,
                "t_gt": tr,
                "visibility": target["visibility"],
                "visibility_requested": visibility,
                "deformation_rms_mm": float(np.sqrt(np.mean(np.sum(d**2, axis=1)))),
                "deformation_max_mm": float(np.max(np.linalg.norm(d, axis=1))),
                "noise_mm": noise,
                "crop_mode": mode,
                "density": density,
                "liver_id": int(liver["liver_id"]),
                "deformation_id": int(t) - 1,
                "target_id": self.count,
                "seed": self.seed,
                "generator_version": GENERATOR_VERSION,
            }
        raise LiverP2PError("could not draw a training pair (crop requests unreachable)")
