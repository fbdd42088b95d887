"""The training data: stores of simulated livers, pairs drawn from them, prepared for the matcher with ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.phantom.artifacts import Artifacts
from liver_p2p_reg.registration.features.learned.descriptors import local_features
from liver_p2p_reg.registration.preprocess import preprocess_pair
from liver_p2p_reg.training.train_config import TrainConfig

GT_RADIUS_NORM = 0.04  # ground-truth pair: nearest neighbour within this after GT alignment (paper)


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
        while True:
            use_real = real is not None and rng.random() < cfg.real_fraction
            try:
                yield prepare_pair((real if use_real else sampler).sample(), self.voxel, rng)
            except LiverP2PError:
                continue  # e.g. a deformed full view voxelizes larger than the source: draw again


def ensure_store(cfg: TrainConfig, progress: bool = True) -> tuple[list[Path], list[Path]]:
    """Build the training store if needed; split its livers into (train, validation)."""
    from liver_p2p_reg.phantom.loader import build_store

    store = Path(cfg.store_dir)
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
    meta = json.loads((store / "store.json").read_text())
    files = [store / name for name in meta.get("livers", [])]
    if len(files) <= cfg.val_livers:
        raise InputError(f"{store}: {len(files)} livers, need more than val_livers={cfg.val_livers}")
    return files[: -cfg.val_livers], files[-cfg.val_livers :]


def ensure_real_store(cfg: TrainConfig, progress: bool = True) -> tuple[list[Path], list[Path]]:
    """Build the real-anatomy store if needed; its (train, train_dev) liver files by the fixed split."""
    from liver_p2p_reg.phantom.loader import build_real_store
    from liver_p2p_reg.phantom.real import real_liver_id, real_split

    split = real_split()
    if cfg.real_livers_limit:
        split = {part: names[: cfg.real_livers_limit] for part, names in split.items()}
    store = Path(cfg.real_store_dir)
    stems = split["train"] + split["train_dev"]
    if not (store / "store.json").is_file() or any(
        not (store / f"liver_{real_liver_id(s):07d}.npz").is_file() for s in stems
    ):
        build_real_store(store, stems, cfg.real_deformations, cfg.store_workers, cfg.store_tets, progress=progress)

    def files(names: list[str]) -> list[Path]:
        return [store / f"liver_{real_liver_id(s):07d}.npz" for s in names]

    return files(split["train"]), files(split["train_dev"])
