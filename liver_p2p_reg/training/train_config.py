"""The settings of a matcher training run (config/train.yaml), checked on load."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom.artifacts import DENSITY_MODES
from liver_p2p_reg.phantom.crop import CROP_MODES
from liver_p2p_reg.registration.features.learned.model import ModelConfig


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
        for kind in ("val_visibility", "real_val_visibility"):
            lo, hi = getattr(self, f"{kind}_min"), getattr(self, f"{kind}_max")
            if not 0 < lo <= hi <= 1:
                raise InputError(f"training config: need 0 < {kind}_min <= {kind}_max <= 1, got {lo} and {hi}")
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
