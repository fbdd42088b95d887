"""Training of the matcher on fresh in silico pairs: dual-softmax matching loss + overlap BCE."""

from __future__ import annotations

import csv
import json
import logging
import math
import tempfile
import time
from contextlib import closing
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
import yaml
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.phantom.artifacts import DENSITY_MODES, Artifacts
from liver_p2p_reg.phantom.crop import CROP_MODES
from liver_p2p_reg.registration.features.learned.descriptors import local_features
from liver_p2p_reg.registration.features.learned.model import MatcherNet, ModelConfig
from liver_p2p_reg.registration.features.learned.weights import load_weights, save_weights
from liver_p2p_reg.registration.matching import dual_softmax, score_matrix
from liver_p2p_reg.registration.preprocess import preprocess_pair
from liver_p2p_reg.training.validation import Validator, validation_cases

log = logging.getLogger(__name__)

GT_RADIUS_NORM = 0.04  # ground-truth pair: nearest neighbour within this after GT alignment (paper)


@dataclass
class TrainConfig:
    """Everything a training run depends on (config/train.yaml)."""

    store_dir: str = "/tmp/liver_p2p_store"
    store_livers: int = 80  # livers simulated into the store when it is built here
    store_deformations: int = 6
    store_seed: int = 11  # generator seed of the training livers (outside the test seeds 900-999)
    store_tets: int = 6000
    val_livers: int = 6  # the last livers of the store: validation only, never trained on
    val_pairs: int = 24
    seed: int = 0
    steps: int = 6000
    lr: float = 1e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 200
    temperature: float = 0.1  # must match Config.temperature used at inference
    overlap_weight: float = 0.5
    visibility_min: float = 0.15
    visibility_max: float = 0.97
    crop_modes: list[str] = field(default_factory=lambda: ["random", "camera"])
    noise_levels_mm: list[float] = field(default_factory=lambda: [0.0, 0.0, 1.0, 2.0, 4.0])
    val_every: int = 500
    checkpoint_every: int = 250
    threads: int = 1
    loader_workers: int = 1  # processes drawing pairs while the main process trains
    max_minutes: float = 0.0  # 0: no wall-clock limit; else stop (and validate) after this long
    model: dict[str, Any] = field(default_factory=dict)  # ModelConfig overrides
    # A second (fine-tuning) stage starts from these weights instead of a random init; its
    # architecture must equal the one `model` describes. Empty: random init.
    init_weights: str = ""
    # Real anatomy (phantom/real.py): a second store of FEM-deformed real CT livers, built from
    # the split's `train` livers (trained on) and `train_dev` livers (checkpoint choice only).
    # Empty: procedural livers only.
    real_store_dir: str = ""
    real_deformations: int = 8
    real_fraction: float = 0.0  # share of training pairs drawn from the real store
    real_val_pairs: int = 0  # validation pairs from the train_dev livers (random + camera, 0 / 2 mm)
    real_livers_limit: int = 0  # > 0: only the first this many train and train_dev livers (quick runs)
    store_workers: int = 1  # processes building the stores (first use only)
    val_workers: int = 0  # > 1: validate in this many CPU processes (a GPU run's loader cores idle meanwhile)
    # What a real view adds (phantom/artifacts.py), drawn per training pair.
    density_modes: list[str] = field(default_factory=lambda: ["uniform"])
    hole_probability: float = 0.0
    outlier_fraction: float = 0.0
    background_fraction: float = 0.0
    source_undeformed: bool = False  # sources are always the undeformed shape (patient preparation)

    @classmethod
    def from_yaml(cls, path: str | Path) -> TrainConfig:
        try:
            data = yaml.safe_load(Path(path).read_text()) or {}
        except OSError as exc:
            raise InputError(f"cannot read training config {path}: {exc.strerror or exc}") from None
        except yaml.YAMLError as exc:
            raise InputError(f"training config {path} is not valid YAML: {str(exc).splitlines()[0]}") from None
        if not isinstance(data, dict):
            raise InputError(f"training config {path} must be a mapping of key: value lines")
        known = {f.name for f in fields(cls)}
        bad = sorted(set(data) - known)
        if bad:
            raise InputError(f"unknown training config keys: {', '.join(bad)}")
        return cls(**data).validate()

    def validate(self) -> TrainConfig:
        """Check types and ranges now, with a one-line InputError, not minutes into building the store."""
        for f in fields(self):
            value, default = getattr(self, f.name), getattr(TrainConfig(), f.name)
            expected = (int, float) if isinstance(default, float) else type(default)
            if isinstance(value, bool) != isinstance(default, bool) or not isinstance(value, expected):
                kind = {
                    "int": "an integer",
                    "float": "a number",
                    "str": "a string",
                    "list": "a list",
                    "dict": "a mapping",
                }
                raise InputError(f"training config: {f.name} must be {kind[type(default).__name__]}, got {value!r}")
        minimums = {
            "store_livers": 2,
            "store_deformations": 1,
            "store_tets": 500,
            "val_livers": 1,
            "val_pairs": 1,
            "seed": 0,
            "steps": 1,
            "lr": 0,  # 0 is allowed: a frozen run (the fine-tuning test uses it)
            "weight_decay": 0,
            "warmup_steps": 0,
            "overlap_weight": 0,
            "val_every": 1,
            "checkpoint_every": 1,
            "threads": 0,
            "loader_workers": 0,
            "max_minutes": 0,
            "real_deformations": 1,
            "real_fraction": 0,
            "real_val_pairs": 0,
            "real_livers_limit": 0,
            "store_workers": 1,
            "val_workers": 0,
            "hole_probability": 0,
            "outlier_fraction": 0,
            "background_fraction": 0,
        }
        for name, minimum in minimums.items():
            if getattr(self, name) < minimum:
                raise InputError(f"training config: {name} must be >= {minimum}, got {getattr(self, name)}")
        if not self.temperature > 0:
            raise InputError(f"training config: temperature must be > 0, got {self.temperature}")
        if self.val_livers >= self.store_livers:
            raise InputError(
                f"training config: val_livers ({self.val_livers}) must be fewer than store_livers ({self.store_livers})"
            )
        if not 0 < self.visibility_min <= self.visibility_max <= 1:
            raise InputError(
                "training config: need 0 < visibility_min <= visibility_max <= 1, got "
                f"{self.visibility_min} and {self.visibility_max}"
            )
        if not self.crop_modes or any(mode not in CROP_MODES for mode in self.crop_modes):
            raise InputError(
                f"training config: crop_modes must be a non-empty list of {CROP_MODES}, got {self.crop_modes}"
            )
        if not self.noise_levels_mm or any(
            not isinstance(n, int | float) or isinstance(n, bool) or not n >= 0 for n in self.noise_levels_mm
        ):
            raise InputError(
                f"training config: noise_levels_mm must be a non-empty list of numbers >= 0, got {self.noise_levels_mm}"
            )
        for name in ("real_fraction", "hole_probability", "outlier_fraction", "background_fraction"):
            if getattr(self, name) > 1:
                raise InputError(f"training config: {name} must be <= 1, got {getattr(self, name)}")
        if (self.real_fraction > 0 or self.real_val_pairs > 0) and not self.real_store_dir:
            raise InputError("training config: real_fraction / real_val_pairs need a real_store_dir")
        if not self.density_modes or any(m not in DENSITY_MODES for m in self.density_modes):
            raise InputError(
                f"training config: density_modes must be a non-empty list of {DENSITY_MODES}, got {self.density_modes}"
            )
        unknown = sorted(set(self.model) - {f.name for f in fields(ModelConfig)})
        if unknown:
            raise InputError(f"training config: unknown model keys: {', '.join(unknown)}")
        if self.init_weights and not Path(self.init_weights).is_file():
            raise InputError(f"training config: init_weights {self.init_weights} not found")
        return self


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


def pair_loss(
    model: MatcherNet, pair: dict[str, torch.Tensor], temperature: float, overlap_weight: float
) -> tuple[torch.Tensor, dict[str, float]]:
    """Negative log dual-softmax confidence at GT pairs (Lepard) + overlap BCE."""
    xs, xt, os_, ot = model(pair["src"], pair["tgt"], pair["f_src"], pair["f_tgt"], with_overlap=True)
    conf = dual_softmax(score_matrix(xs, xt), temperature)
    if len(pair["gt_src"]) == 0:
        match = xs.sum() * 0.0
    else:
        match = -torch.log(conf[pair["gt_src"], pair["gt_tgt"]].clamp_min(1e-12)).mean()
    overlap = F.binary_cross_entropy_with_logits(os_, pair["ov_src"]) + F.binary_cross_entropy_with_logits(
        ot, pair["ov_tgt"]
    )
    loss = match + overlap_weight * overlap
    return loss, {"loss": float(loss.detach()), "match": float(match.detach()), "overlap": float(overlap.detach())}


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


def _lr(cfg: TrainConfig, step: int) -> float:
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    frac = (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps)
    return cfg.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(1.0, frac))))


def _save_checkpoint(out: Path, model: MatcherNet, opt: torch.optim.Optimizer, state: dict) -> None:
    """Model + optimizer tensors as safetensors, counters as JSON (no pickle anywhere)."""
    from safetensors.torch import save_file

    save_weights(model, out / "last.safetensors")
    opt_tensors: dict[str, torch.Tensor] = {}
    for i, p in enumerate(model.parameters()):
        st = opt.state.get(p, {})
        for key in ("exp_avg", "exp_avg_sq"):
            if key in st:
                opt_tensors[f"{i}.{key}"] = st[key].detach().cpu().contiguous()
        if "step" in st:
            opt_tensors[f"{i}.step"] = torch.as_tensor(st["step"], dtype=torch.float32).reshape(1).cpu()
    save_file(opt_tensors, str(out / "optimizer.safetensors.tmp"))
    (out / "optimizer.safetensors.tmp").replace(out / "optimizer.safetensors")
    (out / "state.json").write_text(json.dumps(state, indent=2))


def _load_checkpoint(out: Path, model: MatcherNet, opt: torch.optim.Optimizer) -> dict:
    from safetensors.torch import load_file

    from liver_p2p_reg.registration.features.learned.weights import load_weights

    loaded = load_weights(out / "last.safetensors")
    model.load_state_dict(loaded.state_dict())
    tensors = load_file(str(out / "optimizer.safetensors"))
    for i, p in enumerate(model.parameters()):
        if f"{i}.exp_avg" in tensors:
            opt.state[p] = {
                "exp_avg": tensors[f"{i}.exp_avg"].to(p.device),
                "exp_avg_sq": tensors[f"{i}.exp_avg_sq"].to(p.device),
                "step": tensors[f"{i}.step"].reshape(()),
            }
    return json.loads((out / "state.json").read_text())


def _init_from(model: MatcherNet, path: Path) -> None:
    """Copy the weights at `path` into `model` (a fine-tuning stage); the architectures must agree."""
    loaded = load_weights(path)
    if loaded.cfg.to_dict() != model.cfg.to_dict():
        raise InputError(
            f"init_weights {path}: architecture {loaded.cfg.to_dict()} differs from the config's {model.cfg.to_dict()}"
        )
    model.load_state_dict(loaded.state_dict())
    log.info("initialized from %s", path)


def train(
    cfg: TrainConfig, out_dir: str | Path, device: str = "cpu", resume: bool = False, progress: bool = True
) -> dict:
    """Run (or resume) training; returns the final state dict (best validation numbers, paths)."""
    from tqdm import tqdm

    cfg.validate()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    train_files, val_files = ensure_store(cfg, progress)
    real_train, real_dev = ensure_real_store(cfg, progress) if cfg.real_store_dir else ([], [])
    voxel = Config().voxel_size_norm
    model = MatcherNet(ModelConfig(**cfg.model)).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    state: dict[str, Any] = {"step": 0, "best_val_mm": None, "elapsed_s": 0.0, "config": asdict(cfg)}
    state["device"] = device
    state["hardware"] = torch.cuda.get_device_name(0) if device == "cuda" else "CPU"
    if resume and (out / "state.json").is_file():
        state = _load_checkpoint(out, model, opt)
        log.info("resumed at step %d", state["step"])
    elif cfg.init_weights:
        _init_from(model, Path(cfg.init_weights))
    (out / "train_config.json").write_text(json.dumps(asdict(cfg), indent=2))
    scratch = tempfile.mkdtemp(prefix="liver_p2p_val_")  # the weights the validation workers read
    validator = Validator(validation_cases(cfg, val_files, real_dev), device, cfg.val_workers, Path(scratch))
    stream = PairStream(cfg, train_files, state["step"], voxel, real_train)
    loader = torch.utils.data.DataLoader(
        stream, batch_size=None, num_workers=cfg.loader_workers, prefetch_factor=4 if cfg.loader_workers else None
    )
    csv_path = out / "log.csv"
    new_csv = not csv_path.exists()
    columns = [
        "step",
        "elapsed_s",
        "lr",
        "loss",
        "match",
        "overlap",
        "val_learned_mm",
        "val_learned_p2p_mm",
        "val_success20",
        "val_low_vis_p2p_mm",
        "val_real_p2p_mm",
        "val_score_mm",
    ]
    t0 = time.perf_counter() - state["elapsed_s"]
    model.train()
    with (
        closing(validator),
        open(csv_path, "a", newline="") as fh,
        tqdm(total=cfg.steps, initial=state["step"], desc="train", unit="step", disable=not progress) as bar,
    ):
        writer = csv.DictWriter(fh, fieldnames=columns)
        if new_csv:
            writer.writeheader()
        running: dict[str, float] = {}
        for pair in loader:
            step = state["step"]
            if step >= cfg.steps:
                break
            pair = {k: v.to(device) for k, v in pair.items()}
            for g in opt.param_groups:
                g["lr"] = _lr(cfg, step)
            loss, parts = pair_loss(model, pair, cfg.temperature, cfg.overlap_weight)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            running = {k: 0.98 * running.get(k, v) + 0.02 * v for k, v in parts.items()}
            state["step"] = step + 1
            state["elapsed_s"] = time.perf_counter() - t0
            bar.update(1)
            bar.set_postfix(loss=f"{running['loss']:.3f}")
            over_time = cfg.max_minutes > 0 and state["elapsed_s"] > 60 * cfg.max_minutes
            row = {"step": state["step"], "elapsed_s": round(state["elapsed_s"], 1), "lr": _lr(cfg, step), **parts}
            if state["step"] % cfg.val_every == 0 or state["step"] == cfg.steps or over_time:
                metrics = validator(model)
                row.update(metrics)
                log.info("step %d: %s", state["step"], json.dumps(metrics))
                if state["best_val_mm"] is None or metrics["val_score_mm"] < state["best_val_mm"]:
                    state["best_val_mm"] = metrics["val_score_mm"]
                    state["best_step"] = state["step"]
                    state["best_metrics"] = metrics
                    save_weights(
                        model, out / "best.safetensors", {"step": str(state["step"]), "val": json.dumps(metrics)}
                    )
            if state["step"] % 10 == 0 or "val_learned_mm" in row:
                writer.writerow(row)
                fh.flush()
            if state["step"] % cfg.checkpoint_every == 0 or over_time or state["step"] == cfg.steps:
                _save_checkpoint(out, model, opt, state)
            if over_time:
                log.info("wall-clock limit of %.1f min reached at step %d", cfg.max_minutes, state["step"])
                break
    _save_checkpoint(out, model, opt, state)
    return state


def export_weights(run_dir: str | Path, dest: str | Path, commit: str = "", notes: str = "") -> Path:
    """Copy a run's best checkpoint to `dest` with a model card (`.json` + `.md` next to it)."""
    run = Path(run_dir)
    best = run / "best.safetensors"
    if not best.is_file() or not (run / "state.json").is_file():
        raise InputError(f"{run}: no best.safetensors/state.json (train first)")
    state = json.loads((run / "state.json").read_text())
    cfg = state["config"]
    store_meta_path = Path(cfg["store_dir"]) / "store.json"
    from liver_p2p_reg.phantom.dataset import GENERATOR_VERSION
    from liver_p2p_reg.phantom.loader import STORE_VERSION

    # The store's own record where it is on this machine (a GPU run's store stays there); else the config's.
    store_meta = {
        "seed": cfg["store_seed"],
        "deformations": cfg["store_deformations"],
        "livers": [None] * cfg["store_livers"],
        "generator_version": GENERATOR_VERSION,
        "store_version": STORE_VERSION,
    }
    if store_meta_path.is_file():
        store_meta.update(json.loads(store_meta_path.read_text()))
    model = load_weights(best)
    dest = save_weights(model, dest, {"step": str(state.get("best_step", "")), "commit": commit})
    card = {
        "name": dest.stem,
        "format": "safetensors (no pickle); architecture in the header metadata",
        "size_bytes": dest.stat().st_size,
        "parameters": sum(p.numel() for p in model.parameters()),
        "model_config": model.cfg.to_dict(),
        "training_config": cfg,
        "data": {
            "source": "procedural in silico livers (liver_p2p_reg.phantom)"
            + (
                " and FEM-deformed real CT livers (../shared/data/livers: Medical Segmentation Decathlon Task03 / "
                "LiTS, CC BY-SA 4.0; the split's train livers, train_dev for the checkpoint choice; "
                "liver_p2p_reg/data/real_livers_split.json)"
                if cfg.get("real_store_dir")
                else ", none from ../shared/data"
            ),
            "real_fraction": cfg.get("real_fraction", 0.0),
            "store_seed": store_meta.get("seed"),
            "generator_version": store_meta.get("generator_version"),
            "store_version": store_meta.get("store_version"),
            "livers_total": len(store_meta.get("livers", [])),
            "livers_validation": cfg["val_livers"],
            "deformations_per_liver": store_meta.get("deformations"),
            "test_livers_excluded": "insilico-test-v1 uses generator seeds 900-999; the store uses another seed",
        },
        "commit": commit,
        "steps_trained": state["step"],
        "best_step": state.get("best_step"),
        "validation": state.get("best_metrics", {}),
        "wall_clock_min": round(state["elapsed_s"] / 60, 1),
        "device": state.get("device", "cpu"),
        "hardware": state.get("hardware", "a shared 2-core CPU"),
        "notes": notes,
    }
    dest.with_suffix(".json").write_text(json.dumps(card, indent=2) + "\n")
    val = card["validation"]
    md = [
        f"# Model card: {dest.name}",
        "",
        "Learned rotation-invariant point matcher of liver_p2p_reg.",
        "",
        f"- Parameters: {card['parameters']:,}; file size {card['size_bytes'] / 1e6:.2f} MB (safetensors, no pickle).",
        "- Inputs: voxelized, normalized clouds; invariant multi-scale covariance features per point; "
        "attention over FPS nodes with a learned distance-only bias (self) and no positional terms (cross).",
        (
            f"- Real anatomy: {100 * cfg.get('real_fraction', 0.0):.0f} % of the pairs from FEM-deformed real CT livers "
            "(the split's 40 train livers; its 4 train_dev livers in the validation that picks the checkpoint; "
            "its val and test livers never seen), with the density and artifact augmentations of the config."
            if cfg.get("real_store_dir")
            else "- Real anatomy: none."
        ),
        f"- Training data: procedural livers, store seed {store_meta.get('seed')} "
        f"({len(store_meta.get('livers', []))} livers x {store_meta.get('deformations')} FEM deformations, "
        f"generator v{store_meta.get('generator_version')}), the last {cfg['val_livers']} held out for validation; "
        "fresh crops/poses/noise drawn on the fly. No livers of insilico-test-v1 (seeds 900-999).",
        f"- Loss: dual-softmax matching loss at GT pairs (NN within 0.04 after GT alignment), T={cfg['temperature']}, "
        f"+ {cfg['overlap_weight']} x overlap BCE.",
        f"- Trained {state['step']} steps (best at step {state.get('best_step')}) in "
        f"{card['wall_clock_min']} min wall clock on {card['hardware']} (device {card['device']})"
        + (
            f", starting from {cfg['init_weights']} (a second stage; see that file's card)."
            if cfg.get("init_weights")
            else "."
        ),
        f"- Validation ({cfg['val_pairs']} pairs, held-out livers, random crops, visibility 0.2-1.0, no noise): "
        f"learned {val.get('val_learned_mm', float('nan')):.2f} mm, "
        f"learned-p2p {val.get('val_learned_p2p_mm', float('nan')):.2f} mm mean RMS-TRE, "
        f"success@20mm {val.get('val_success20', float('nan')):.2f}"
        + (
            f"; {cfg['real_val_pairs']} pairs of the real train_dev livers (random and camera crops, visibility "
            f"0.2-0.5, noise 0 or 2 mm): learned-p2p {val['val_real_p2p_mm']:.2f} mm."
            if cfg.get("real_val_pairs") and "val_real_p2p_mm" in val
            else "."
        ),
        f"- Commit of the training code: {commit or 'unknown'}.",
        "",
        "Training config:",
        "",
        "```json",
        json.dumps(cfg, indent=2),
        "```",
    ]
    if notes:
        md += ["", notes]
    dest.with_suffix(".md").write_text("\n".join(md) + "\n")
    return dest
