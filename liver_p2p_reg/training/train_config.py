"""The settings of a matcher training run (config/train.yaml), checked on load."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from liver_p2p_reg.config import MAX_SEED
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom.artifacts import DENSITY_MODES
from liver_p2p_reg.phantom.crop import CROP_MODES
from liver_p2p_reg.phantom.dataset import MAX_LIVERS_PER_SEED, REAL_LIVER_SEED, RESERVED_SEEDS
from liver_p2p_reg.phantom.loader import MIN_VISIBILITY
from liver_p2p_reg.registration.features.learned.model import ModelConfig, model_config_from

# Lower bounds of the numbers that have nothing but a lower bound.
MINIMUMS: dict[str, float] = {
    "store_deformations": 1,
    "val_livers": 1,
    "val_pairs": 1,
    "steps": 1,
    "lr": 0,  # 0 is allowed: a frozen run (the fine-tuning test uses it)
    "weight_decay": 0,
    "warmup_steps": 0,
    "overlap_weight": 0,
    "val_every": 1,
    "checkpoint_every": 1,
    "max_minutes": 0,
    "real_deformations": 1,
    "real_fraction": 0,
    "real_val_pairs": 0,
    "real_livers_limit": 0,
    "hole_probability": 0,
    "outlier_fraction": 0,
    "background_fraction": 0,
}
# [low, high] of integer settings, as Config has them: a huge thread or process count failed with a misleading
# ImportError or a segfault; liver ids are store_seed * MAX_LIVERS_PER_SEED + index and stay 32-bit; a tet mesh of
# millions of tets takes hours and gigabytes per liver.
CLOSED: dict[str, tuple[int, int]] = {
    "seed": (0, MAX_SEED),
    "store_seed": (0, (MAX_SEED + 1) // MAX_LIVERS_PER_SEED - 1),
    "store_livers": (2, MAX_LIVERS_PER_SEED),
    "store_tets": (500, 200_000),
    "threads": (0, 256),
    "loader_workers": (0, 256),
    "val_workers": (0, 256),
    "store_workers": (1, 256),
}
MAX_NOISE_MM = 50.0  # make_target refuses more (phantom/crop.py): every draw would fail


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
    # Visibility of the validation pairs that pick the checkpoint: procedural (held-out livers) and
    # real (train_dev livers). A small-view stage validates where it trains.
    val_visibility_min: float = 0.2
    val_visibility_max: float = 1.0
    real_val_visibility_min: float = 0.2
    real_val_visibility_max: float = 0.5
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
        from liver_p2p_reg.config_io import read_yaml_mapping

        data = read_yaml_mapping(path, "training config")
        known = {f.name for f in fields(cls)}
        bad = sorted(set(data) - known)
        if bad:
            raise InputError(f"unknown training config keys: {', '.join(bad)}")
        return cls(**data).validate()

    def validate(self) -> TrainConfig:
        """Check types and ranges now, with a one-line InputError, not minutes into building the store."""
        _check_types(self)
        _check_numbers(self)
        _check_visibility(self)
        _check_lists(self)
        _check_model(self.model)
        if not self.store_dir:  # Path("") is the current folder: the store would be built there
            raise InputError("training config: store_dir must name a folder, got an empty string")
        if self.store_seed in RESERVED_SEEDS or self.store_seed == REAL_LIVER_SEED:
            raise InputError(
                f"training config: store_seed must be outside 900-999 (test livers) and not {REAL_LIVER_SEED} "
                f"(real livers), got {self.store_seed}"
            )
        if self.val_livers >= self.store_livers:
            raise InputError(
                f"training config: val_livers ({self.val_livers}) must be fewer than store_livers ({self.store_livers})"
            )
        if (self.real_fraction > 0 or self.real_val_pairs > 0) and not self.real_store_dir:
            raise InputError("training config: real_fraction / real_val_pairs need a real_store_dir")
        if self.init_weights and not Path(self.init_weights).is_file():
            raise InputError(f"training config: init_weights {self.init_weights} not found")
        return self


_KINDS = {"int": "an integer", "float": "a number", "str": "a string", "list": "a list", "dict": "a mapping"}


def _check_types(cfg: TrainConfig) -> None:
    """Each field has its default's type (an int stands for a float; a bool is no number)."""
    defaults = TrainConfig()
    for f in fields(cfg):
        value, default = getattr(cfg, f.name), getattr(defaults, f.name)
        expected = (int, float) if isinstance(default, float) else type(default)
        if isinstance(value, bool) != isinstance(default, bool) or not isinstance(value, expected):
            raise InputError(f"training config: {f.name} must be {_KINDS[type(default).__name__]}, got {value!r}")


def _check_numbers(cfg: TrainConfig) -> None:
    """Every number finite, above its minimum, inside its range."""
    for f in fields(cfg):
        value = getattr(cfg, f.name)
        if isinstance(value, float) and not math.isfinite(value):  # NaN passes `<` tests; inf diverges the loss
            raise InputError(f"training config: {f.name} must be a finite number, got {value}")
    for name, minimum in MINIMUMS.items():
        if getattr(cfg, name) < minimum:
            raise InputError(f"training config: {name} must be >= {minimum}, got {getattr(cfg, name)}")
    for name, (low, high) in CLOSED.items():
        if not low <= getattr(cfg, name) <= high:
            raise InputError(f"training config: {name} must be in [{low}, {high}], got {getattr(cfg, name)}")
    if not cfg.temperature > 0:
        raise InputError(f"training config: temperature must be > 0, got {cfg.temperature}")
    for name in ("real_fraction", "hole_probability", "outlier_fraction", "background_fraction"):
        if getattr(cfg, name) > 1:
            raise InputError(f"training config: {name} must be <= 1, got {getattr(cfg, name)}")


def _check_visibility(cfg: TrainConfig) -> None:
    """The sampler's rule for every visibility range, now rather than when the first pair is drawn."""
    for kind in ("visibility", "val_visibility", "real_val_visibility"):
        lo, hi = getattr(cfg, f"{kind}_min"), getattr(cfg, f"{kind}_max")
        if not MIN_VISIBILITY <= lo <= hi <= 1:
            raise InputError(
                f"training config: need {MIN_VISIBILITY} <= {kind}_min <= {kind}_max <= 1, got {lo} and {hi}"
            )


def _check_lists(cfg: TrainConfig) -> None:
    """Crop modes, density modes and noise levels: non-empty lists of known choices / finite levels."""
    if not cfg.crop_modes or any(mode not in CROP_MODES for mode in cfg.crop_modes):
        raise InputError(f"training config: crop_modes must be a non-empty list of {CROP_MODES}, got {cfg.crop_modes}")
    if not cfg.density_modes or any(m not in DENSITY_MODES for m in cfg.density_modes):
        raise InputError(
            f"training config: density_modes must be a non-empty list of {DENSITY_MODES}, got {cfg.density_modes}"
        )
    if not cfg.noise_levels_mm or any(
        not isinstance(n, int | float) or isinstance(n, bool) or not 0 <= n <= MAX_NOISE_MM for n in cfg.noise_levels_mm
    ):
        raise InputError(
            f"training config: noise_levels_mm must be a non-empty list of numbers in [0, {MAX_NOISE_MM:g}], "
            f"got {cfg.noise_levels_mm}"
        )


def _check_model(model: dict[str, Any]) -> None:
    """The `model` overrides: known keys, each within MODEL_LIMITS (the limits a weights file is loaded with, so
    what trains here loads there), width a multiple of heads: the net is built, not refused by torch mid-run."""
    unknown = sorted(map(str, set(model) - {f.name for f in fields(ModelConfig)}))
    if unknown:
        raise InputError(f"training config: unknown model keys: {', '.join(unknown)}")
    try:
        model_config_from(model, prefix="model.")
    except ValueError as exc:
        raise InputError(f"training config: {exc}") from None
