"""The training data: stores of simulated livers, pairs drawn from them, prepared for the matcher with ground truth."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.phantom.artifacts import Artifacts
from liver_p2p_reg.phantom.loader import StoreFileError
from liver_p2p_reg.registration.features.learned.descriptors import local_features
from liver_p2p_reg.registration.preprocess import preprocess_pair
from liver_p2p_reg.training.train_config import TrainConfig

GT_RADIUS_NORM = 0.04  # ground-truth pair: nearest neighbour within this after GT alignment (paper)
# Draws in a row that may fail before the stream gives up. Each draw already tries up to 20 crops
# (PairSampler.sample); the shipped configs failed no draw in 240 (a full view that voxelizes larger than
# its source is the rare failure), so five in a row mean the settings ask for views no crop can give.
MAX_FAILED_DRAWS = 5
STREAM_ERROR = "error"  # the key of the one item a stream that gave up yields (a worker's raise would be a traceback)


def prepare_pair(
    sample: dict, voxel_size_norm: float, rng: np.random.Generator | None = None
) -> dict[str, torch.Tensor]:
    """A sampled case -> voxelized normalized clouds, invariant features, GT pairs and overlap labels.

    A random rotation of the source before voxelization varies the voxel grid (the only
    non-invariant step), so the net sees the sampling jitter it meets at test time.
    """
    src_mm, tgt_mm = sample["src_pcd"], sample["tgt_pcd"]
    R, t = np.asarray(sample["R_gt"], dtype=np.float64), np.asarray(sample["t_gt"], dtype=np.float64).reshape(3)
    if rng is not None:
        Rs = Rotation.random(random_state=rng).as_matrix()
        src_mm = src_mm @ Rs.T
        R = R @ Rs.T
    prep = preprocess_pair(src_mm, tgt_mm, Config(voxel_size_norm=voxel_size_norm))
    s, cs, ct = prep.source_norm.scale_mm, prep.source_norm.centroid_mm, prep.target_norm.centroid_mm
    src_in_t = ((prep.source * s + cs) @ R.T + t - ct) / s
    d_t, nn_t = cKDTree(src_in_t).query(prep.target, k=1)
    d_s, _ = cKDTree(prep.target).query(src_in_t, k=1)
    keep = d_t < GT_RADIUS_NORM
    return {
        "src": torch.as_tensor(prep.source, dtype=torch.float32),
        "tgt": torch.as_tensor(prep.target, dtype=torch.float32),
        "f_src": torch.as_tensor(local_features(prep.source), dtype=torch.float32),
        "f_tgt": torch.as_tensor(local_features(prep.target), dtype=torch.float32),
        "gt_src": torch.as_tensor(nn_t[keep], dtype=torch.long),
        "gt_tgt": torch.as_tensor(np.nonzero(keep)[0], dtype=torch.long),
        "ov_src": torch.as_tensor(d_s < GT_RADIUS_NORM, dtype=torch.float32),
        "ov_tgt": torch.as_tensor(keep, dtype=torch.float32),
    }


def training_sampler(cfg: TrainConfig, store_dir: str, files: list[Path], seed: int):
    """A PairSampler over `files` of a store with the config's crops, noise, density and artifacts."""
    from liver_p2p_reg.phantom.loader import PairSampler

    sampler = PairSampler(
        store_dir,
        seed=seed,
        visibility_range=(cfg.visibility_min, cfg.visibility_max),
        crop_modes=cfg.crop_modes,
        noise_levels_mm=cfg.noise_levels_mm,
        density_modes=cfg.density_modes,
        artifacts=Artifacts(cfg.hole_probability, cfg.outlier_fraction, cfg.background_fraction),
        source_undeformed=cfg.source_undeformed,
    )
    sampler.files = list(files)  # training livers only (validation livers held out)
    return sampler


class PairStream(torch.utils.data.IterableDataset):
    """Endless stream of prepared training pairs (deterministic for a seed, start step and worker)."""

    def __init__(
        self, cfg: TrainConfig, files: list[Path], start: int, voxel_size_norm: float, real_files: list[Path] = ()
    ) -> None:
        super().__init__()
        self.cfg, self.files, self.start, self.voxel = cfg, files, start, voxel_size_norm
        self.real_files = list(real_files)

    def __iter__(self):
        torch.set_num_threads(1)
        cfg = self.cfg
        info = torch.utils.data.get_worker_info()
        # Worker 0 (or no workers) keeps the single-stream seeds of earlier runs; other workers
        # get their own streams (several workers would otherwise yield the same pairs).
        worker = 0 if info is None else info.id
        seed = cfg.seed * 1_000_003 + self.start + 7_919 * worker
        sampler = training_sampler(cfg, cfg.store_dir, self.files, seed)
        real = None
        if cfg.real_fraction > 0 and self.real_files:
            real = training_sampler(cfg, cfg.real_store_dir, self.real_files, seed + 1)
        rng = np.random.default_rng([cfg.seed, self.start, 17] + ([worker] if worker else []))
        failed = 0
        while True:
            use_real = real is not None and rng.random() < cfg.real_fraction
            try:
                pair = prepare_pair((real if use_real else sampler).sample(), self.voxel, rng)
            except StoreFileError as exc:  # another draw would not mend a damaged file
                yield {STREAM_ERROR: str(exc)}
                return
            except LiverP2PError as exc:  # e.g. a deformed full view voxelizes larger than the source: draw again
                failed += 1
                if failed >= MAX_FAILED_DRAWS:
                    yield {STREAM_ERROR: _unreachable(cfg, failed, exc)}
                    return
                continue
            failed = 0
            yield pair


def _unreachable(cfg: TrainConfig, failed: int, exc: Exception) -> str:
    """The one-line error of a stream that could draw no pair: the settings that decide which views exist."""
    return (
        f"no training pair could be drawn in {failed} tries in a row (last: {exc}); the config asks for views "
        f"no crop gives: check visibility_min/visibility_max ({cfg.visibility_min}-{cfg.visibility_max}), "
        f"crop_modes {cfg.crop_modes}, noise_levels_mm {cfg.noise_levels_mm}"
    )


def ensure_store(cfg: TrainConfig, progress: bool = True) -> tuple[list[Path], list[Path]]:
    """Build the training store if needed; split the config's livers of it into (train, validation)."""
    from liver_p2p_reg.phantom.loader import build_store, read_store_meta

    store = _store_folder(cfg.store_dir, "store_dir")
    if not (store / "store.json").is_file():
        build_store(
            store,
            cfg.store_livers,
            cfg.store_deformations,
            cfg.store_seed,
            cfg.store_workers,
            cfg.store_tets,
            progress=progress,
        )
    files = _checked_files(store, _config_livers(cfg, store, read_store_meta(store)))
    return files[: -cfg.val_livers], files[-cfg.val_livers :]


def _store_folder(value: str, name: str) -> Path:
    """A store folder of the config: not an existing file."""
    store = Path(value)
    if store.exists() and not store.is_dir():
        raise InputError(f"training config: {name} {store} is a file; give a folder")
    return store


def _config_livers(cfg: TrainConfig, store: Path, meta: dict) -> list[str]:
    """The store's livers the config names. A built store must have been built with the config's settings
    and hold its livers; one that holds more (a larger run's) gives the config's own, its first
    `store_livers` (the same livers a store of that size holds, so a run does not depend on what else was
    built there). A store assembled by hand (`prepare` writes one: no builder record) is used as listed."""
    from liver_p2p_reg.phantom.dataset import GENERATOR_VERSION, liver_id_for
    from liver_p2p_reg.phantom.loader import STORE_VERSION

    if "store_version" not in meta:
        if len(meta["livers"]) != cfg.store_livers:
            raise InputError(
                f"{store}/store.json lists {len(meta['livers'])} livers, the config's store_livers is {cfg.store_livers}"
            )
        return meta["livers"]
    _refuse_mismatch(
        store,
        meta,
        {
            "kind": (None, "the kind of store (a real store is real_store_dir's)"),
            "seed": (cfg.store_seed, "store_seed"),
            "deformations": (cfg.store_deformations, "store_deformations"),
            "target_tets": (cfg.store_tets, "store_tets"),
            "generator_version": (GENERATOR_VERSION, "generator_version"),
            "store_version": (STORE_VERSION, "store_version"),
        },
    )
    names = [f"liver_{liver_id_for(cfg.store_seed, i):07d}.npz" for i in range(cfg.store_livers)]
    listed = set(meta["livers"])
    if any(name not in listed for name in names):
        raise InputError(
            f"{store} holds {len(listed & set(names))} of the config's {cfg.store_livers} livers (store_livers); "
            "use another store_dir, or remove its store.json to build the missing ones"
        )
    if len(listed) > len(names):  # a larger store's first livers: another split than training on all would give
        logging.getLogger(__name__).warning(
            "%s holds %d livers; this run uses its first %d (store_livers), the last %d of them for validation",
            store, len(listed), len(names), cfg.val_livers,
        )  # fmt: skip
    return names


def _refuse_mismatch(store: Path, meta: dict, expected: dict[str, tuple[object, str]]) -> None:
    """InputError listing each store.json value that differs from what the config asks."""
    differ = [f"{label} {meta.get(key)!r} (config {value!r})" for key, (value, label) in expected.items()
              if meta.get(key) != value]  # fmt: skip
    if differ:
        raise InputError(f"{store} was built with other settings: {'; '.join(differ)}; use another store directory")


def _checked_files(store: Path, names: list[str]) -> list[Path]:
    """The store's liver files, each present and readable (a missing or damaged one: one line now, not a
    worker's traceback mid-run)."""
    from liver_p2p_reg.phantom.loader import liver_file_shapes

    files = [store / name for name in names]
    for path in files:
        liver_file_shapes(path)
    return files


def ensure_real_store(cfg: TrainConfig, progress: bool = True) -> tuple[list[Path], list[Path]]:
    """Build the real-anatomy store if needed; its (train, train_dev) liver files by the fixed split."""
    from liver_p2p_reg.phantom.dataset import GENERATOR_VERSION
    from liver_p2p_reg.phantom.loader import STORE_VERSION, build_real_store, read_store_meta
    from liver_p2p_reg.phantom.real import real_liver_id, real_split

    split = real_split()
    if cfg.real_livers_limit:
        split = {part: names[: cfg.real_livers_limit] for part, names in split.items()}
    store = _store_folder(cfg.real_store_dir, "real_store_dir")
    stems = split["train"] + split["train_dev"]
    if not (store / "store.json").is_file() or any(
        not (store / f"liver_{real_liver_id(s):07d}.npz").is_file() for s in stems
    ):
        build_real_store(store, stems, cfg.real_deformations, cfg.store_workers, cfg.store_tets, progress=progress)
    meta = read_store_meta(store)
    _refuse_mismatch(
        store,
        meta,
        {
            "kind": ("real", "the kind of store (a procedural store is store_dir's)"),
            "deformations": (cfg.real_deformations, "real_deformations"),
            "target_tets": (cfg.store_tets, "store_tets"),
            "generator_version": (GENERATOR_VERSION, "generator_version"),
            "store_version": (STORE_VERSION, "store_version"),
        },
    )

    def files(names: list[str]) -> list[Path]:
        return _checked_files(store, [f"liver_{real_liver_id(s):07d}.npz" for s in names])

    return files(split["train"]), files(split["train_dev"])
