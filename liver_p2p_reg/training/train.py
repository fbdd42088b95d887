"""Training of the matcher on fresh in silico pairs: dual-softmax matching loss + overlap BCE."""

from __future__ import annotations

import csv
import json
import logging
import math
import tempfile
import time
from contextlib import closing
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.pools import spawn_context
from liver_p2p_reg.registration.features.learned.model import MatcherNet, ModelConfig
from liver_p2p_reg.registration.features.learned.weights import load_weights, save_weights
from liver_p2p_reg.registration.matching import dual_softmax, score_matrix
from liver_p2p_reg.training.data import PairStream, ensure_real_store, ensure_store
from liver_p2p_reg.training.train_config import TrainConfig
from liver_p2p_reg.training.validation import Validator, validation_cases

log = logging.getLogger(__name__)


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
    workers = cfg.loader_workers
    loader = torch.utils.data.DataLoader(
        stream,
        batch_size=None,
        num_workers=workers,
        prefetch_factor=4 if workers else None,
        # spawned like every worker of the package (pools.py): a forked one would block in its first
        # OpenMP region of a runtime this process has used (torch, Open3D, pykdtree)
        multiprocessing_context=spawn_context() if workers else None,
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
