"""Validation of the matcher during training: fixed held-out pairs, learned and learned-p2p RMS-TRE.

With several workers the pairs are registered in parallel CPU processes (started once per run,
`spawn`, one torch thread each) from a safetensors copy of the current weights, so a GPU run's
validation costs seconds while the data-loading workers wait anyway.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

import numpy as np

from liver_p2p_reg.config import Config
from liver_p2p_reg.metrics import rms_tre_mm
from liver_p2p_reg.pools import spawn_pool

FAILED_MM = 1e3  # a failed registration counts as this error
LOW_VISIBILITY = 0.35


def _visibility(cfg: Any, kind: str, default: tuple[float, float]) -> tuple[float, float]:
    """The config's (min, max) validation visibility of `kind`; `default` for configs without one."""
    return (getattr(cfg, f"{kind}_min", default[0]), getattr(cfg, f"{kind}_max", default[1]))


def validation_cases(cfg: Any, val_files: list[Path], real_dev_files: list[Path] = ()) -> list[dict]:
    """A fixed set of validation pairs from the held-out livers (random crops, no noise), plus,
    with `real_val_pairs`, real train_dev livers seen as in surgery (random and camera crops,
    noise 0 or 2 mm); visibilities from the config (by default 0.2-1.0 and 0.2-0.5)."""
    from liver_p2p_reg.phantom.loader import PairSampler

    sampler = PairSampler(
        cfg.store_dir, seed=10_000 + cfg.seed, visibility_range=_visibility(cfg, "val_visibility", (0.2, 1.0))
    )
    sampler.files = list(val_files)
    cases = [sampler.sample() for _ in range(cfg.val_pairs)]
    if cfg.real_val_pairs and real_dev_files:
        real = PairSampler(
            cfg.real_store_dir,
            seed=20_000 + cfg.seed,
            visibility_range=_visibility(cfg, "real_val_visibility", (0.2, 0.5)),
            crop_modes=("random", "camera"),
            noise_levels_mm=(0.0, 2.0),
        )
        real.files = list(real_dev_files)
        cases += [dict(real.sample(), real=True) for _ in range(cfg.real_val_pairs)]
    return cases


def score_case(model: Any, case: dict, device: str, variants: tuple[bool, ...] = (False, True)) -> tuple[float, ...]:
    """RMS-TRE (mm) of `learned` (False) and `learned-p2p` (True; no ICP) on one pair."""
    from liver_p2p_reg.registration.context import MethodContext
    from liver_p2p_reg.registration.features.learned.provider import LearnedProvider
    from liver_p2p_reg.registration.pipeline import run_feature_pipeline

    provider = LearnedProvider(model=model)
    config = Config(device=device)
    errors = []
    for use_p2p in variants:
        try:
            res = run_feature_pipeline(
                case["src_pcd"], case["tgt_pcd"], config, MethodContext(), provider, use_p2p=use_p2p, refine=False
            )
            errors.append(rms_tre_mm(res.T_target_source, case["src_marker"], case["tgt_marker"]))
        except Exception:  # noqa: BLE001 - a failed registration counts as a large error
            errors.append(FAILED_MM)
    return tuple(errors)


def summarize(errors: list[tuple[float, float]], cases: list[dict]) -> dict[str, float]:
    """The logged metrics; `val_score_mm` (learned-p2p over every pair) picks the best checkpoint."""
    learned = np.array([e[0] for e, c in zip(errors, cases, strict=True) if not c.get("real")])
    p2p = np.array([e[1] for e, c in zip(errors, cases, strict=True) if not c.get("real")])
    low = [e[1] for e, c in zip(errors, cases, strict=True) if not c.get("real") and c["visibility"] < LOW_VISIBILITY]
    real = [e[1] for e, c in zip(errors, cases, strict=True) if c.get("real")]
    return {
        "val_learned_mm": float(np.mean(learned)),
        "val_learned_p2p_mm": float(np.mean(p2p)),
        "val_success20": float(np.mean(p2p <= 20.0)),
        "val_low_vis_p2p_mm": float(np.mean(low)) if low else float("nan"),
        "val_real_p2p_mm": float(np.mean(real)) if real else float("nan"),
        "val_score_mm": float(np.mean(np.concatenate([p2p, real]))),
    }


_WORKER: dict[str, Any] = {}


def _init_worker(cases: list[dict]) -> None:
    import torch

    torch.set_num_threads(1)
    _WORKER["cases"] = cases


def _score_in_worker(args: tuple[str, int, int]) -> tuple[float, float]:
    from liver_p2p_reg.registration.features.learned.weights import load_weights

    path, version, index = args
    if _WORKER.get("version") != version:
        _WORKER["model"], _WORKER["version"] = load_weights(path, "cpu"), version
    return score_case(_WORKER["model"], _WORKER["cases"][index], "cpu")


class Validator:
    """Scores a model on fixed validation cases, in `workers` CPU processes or in this process."""

    def __init__(self, cases: list[dict], device: str, workers: int, scratch_dir: Path) -> None:
        self.cases, self.device = cases, device
        self.path = Path(scratch_dir) / "validating.safetensors"
        self.version = 0
        self.pool = None
        if workers > 1:
            self.pool = spawn_pool(workers, initializer=_init_worker, initargs=(cases,))

    def __call__(self, model: Any) -> dict[str, float]:
        from liver_p2p_reg.registration.features.learned.weights import save_weights

        model.eval()
        try:
            if self.pool is None:
                errors = [score_case(model, case, self.device) for case in self.cases]
            else:
                self.version += 1
                save_weights(model, self.path)
                jobs = [(str(self.path), self.version, i) for i in range(len(self.cases))]
                errors = list(self.pool.map(_score_in_worker, jobs))
        finally:
            model.train()
        return summarize(errors, self.cases)

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)
            self.pool = None
        self.path.unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            self.path.parent.rmdir()  # the scratch folder, when it was made for this validator
