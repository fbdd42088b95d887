"""Training of the matcher on fresh in silico pairs: dual-softmax matching loss + overlap BCE."""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import shutil
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
from liver_p2p_reg.files import write_text_atomic
from liver_p2p_reg.pools import spawn_context
from liver_p2p_reg.registration.features.learned.model import MatcherNet, ModelConfig
from liver_p2p_reg.registration.features.learned.weights import load_weights, save_weights
from liver_p2p_reg.registration.matching import dual_softmax, score_matrix
from liver_p2p_reg.training.data import STREAM_ERROR, PairStream, ensure_real_store, ensure_store
from liver_p2p_reg.training.train_config import TrainConfig
from liver_p2p_reg.training.validation import Validator, validation_cases

log = logging.getLogger(__name__)

# What a run writes into its folder (and the temporary files of its atomic writes): --force removes these, and
# nothing else of the folder, before a fresh run, so the new run's log and checkpoints never mix with an old one's.
RUN_FILES = tuple(
    "best.safetensors last.safetensors optimizer.safetensors state.json log.csv train_config.json".split()
)
TEMP_FILES = tuple(name + ".tmp" for name in RUN_FILES)
# What a resumed run may change: when it stops, when it saves and how fast the store is built; anything else
# would continue one run's weights and optimizer under another's settings (and card).
RESUMABLE = ("steps", "max_minutes", "checkpoint_every", "store_workers")
CSV_COLUMNS = (
    "step elapsed_s lr loss match overlap val_learned_mm val_learned_p2p_mm val_success20 val_low_vis_p2p_mm "
    "val_real_p2p_mm val_score_mm"
).split()


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


def _finite(model: MatcherNet) -> bool:
    """True when every weight is a finite number (a diverged step leaves NaN or inf)."""
    return all(bool(torch.isfinite(p).all()) for p in model.parameters())


def _save_checkpoint(out: Path, model: MatcherNet, opt: torch.optim.Optimizer, state: dict) -> None:
    """Model + optimizer tensors as safetensors, counters as JSON (no pickle anywhere)."""
    from safetensors.torch import save_file

    if not _finite(model):
        raise InputError(_diverged(out, state["step"], "the weights hold NaN or inf"))
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
    write_text_atomic(out / "state.json", json.dumps(state, indent=2))  # a kill mid-write leaves the old one


def _diverged(out: Path, step: int, what: str) -> str:
    """The one-line error of a run whose loss or weights stopped being finite numbers."""
    return (
        f"training diverged at step {step}: {what}; nothing of that step was saved ({out} keeps its last "
        "finite checkpoint, if any); lower lr or check overlap_weight and temperature"
    )


def _read_state(out: Path) -> dict:
    """The saved counters and config of the run in `out`; InputError naming a missing or damaged state.json."""
    path = out / "state.json"
    if not path.is_file():
        raise InputError(f"--resume: {out} holds no state.json (no run to continue); leave out --resume to start one")
    try:
        state = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path} is unreadable or damaged ({exc}); cannot resume") from None
    ok = isinstance(state, dict) and isinstance(state.get("config"), dict) and isinstance(state.get("step"), int)
    if not ok or not isinstance(state.get("elapsed_s"), int | float) or "best_val_mm" not in state:
        raise InputError(f"{path} is damaged (no step, elapsed_s, best_val_mm or config); cannot resume")
    return state


def _check_same_config(out: Path, saved: dict, cfg: TrainConfig) -> None:
    """A resumed run continues under the config it started with (but RESUMABLE); settings that a newer
    version added count as unchanged while they keep their default."""
    old, new, defaults = _flat(saved["config"]), _flat(asdict(cfg)), _flat(asdict(TrainConfig()))
    differ = [
        f"{key} {old.get(key, defaults.get(key))!r} -> {new.get(key)!r}"
        for key in sorted(old.keys() | new.keys())
        if key not in RESUMABLE and old.get(key, defaults.get(key)) != new.get(key)
    ]
    if differ:
        raise InputError(
            f"--resume: {out} was trained with another config ({'; '.join(differ)}); only "
            f"{', '.join(RESUMABLE)} may change; start the new config in another --out"
        )


def _flat(config: dict) -> dict:
    """A config with its `model` overrides spelled out as the full architecture, one `model.KEY` each
    (`{}` and the defaults written out are one net)."""
    flat = {k: v for k, v in config.items() if k != "model"}
    try:
        flat.update({f"model.{k}": v for k, v in ModelConfig(**config.get("model", {})).to_dict().items()})
    except TypeError:  # a damaged state's entry: compared as it is
        flat["model"] = config.get("model")
    return flat


def _check_out(out: Path, cfg: TrainConfig, resume: bool, force: bool) -> dict | None:
    """Refuse an output folder the run would wreck, before any work; the saved state to resume (None: a fresh run)."""
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file; give a folder")
    if resume and force:
        raise InputError("--resume continues the run in --out and --force replaces it; give one of them")
    if resume:
        saved = _read_state(out)
        _check_same_config(out, saved, cfg)
        return saved
    held = sorted(p.name for p in out.glob("*.safetensors")) + (["state.json"] if (out / "state.json").exists() else [])
    if held and not force:
        raise InputError(
            f"{out} holds a training run ({', '.join(held)}); pass --resume to continue it or --force to replace it"
        )
    if not _is_training_log(out / "log.csv"):  # a file of the user's that has the name: never deleted
        raise InputError(f"{out}/log.csv is no training log; choose another --out (a run writes its log there)")
    if cfg.init_weights and any(_same_file(Path(cfg.init_weights), out / name) for name in RUN_FILES):
        raise InputError(f"init_weights {cfg.init_weights} is a file this run replaces; copy it out of {out} first")
    return None


def _same_file(a: Path, b: Path) -> bool:
    """True when two paths name one file."""
    return a.exists() and b.exists() and os.path.samefile(a, b)


def _is_training_log(path: Path) -> bool:
    """True when `path` is missing or starts with the header of a run's log.csv."""
    try:
        with open(path, newline="") as fh:
            return next(csv.reader(fh), []) == CSV_COLUMNS
    except FileNotFoundError:
        return True
    except (OSError, UnicodeDecodeError, csv.Error):
        return False


def _start_afresh(out: Path) -> None:
    """Remove what an earlier run wrote here (replaced with --force, or a run stopped before its first
    checkpoint), so the new run's log and files do not mix with it; nothing else in the folder is touched."""
    for name in RUN_FILES + TEMP_FILES:
        (out / name).unlink(missing_ok=True)


def _trim_log(path: Path, step: int) -> None:
    """Drop the log rows after the resumed checkpoint (a killed run logged steps it never saved)."""
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError, csv.Error):  # none, or not ours to rewrite: appended to as it is
        return
    kept = rows[:1] + [r for r in rows[1:] if not (r and r[0].isdigit() and int(r[0]) > step)]
    if len(kept) < len(rows):
        with open(path, "w", newline="") as fh:
            csv.writer(fh).writerows(kept)


def _load_checkpoint(out: Path, model: MatcherNet, opt: torch.optim.Optimizer, saved: dict) -> dict:
    """Load the last checkpoint's weights and optimizer moments into `model` and `opt`; the saved state."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    loaded = load_weights(out / "last.safetensors")  # missing or damaged: WeightsError, one line
    if loaded.cfg.to_dict() != model.cfg.to_dict():
        raise InputError(
            f"{out}/last.safetensors holds another architecture than its state.json's config; cannot resume"
        )
    model.load_state_dict(loaded.state_dict())
    path = out / "optimizer.safetensors"
    if not path.is_file():
        raise InputError(f"{path} is missing (the run's optimizer state); cannot resume")
    try:
        tensors = load_file(str(path))
        for i, p in enumerate(model.parameters()):
            if f"{i}.exp_avg" in tensors:
                opt.state[p] = {
                    "exp_avg": tensors[f"{i}.exp_avg"].to(p.device),
                    "exp_avg_sq": tensors[f"{i}.exp_avg_sq"].to(p.device),
                    "step": tensors[f"{i}.step"].reshape(()),
                }
    except (SafetensorError, OSError, KeyError, RuntimeError) as exc:
        raise InputError(f"{path} is damaged ({type(exc).__name__}: {exc}); cannot resume") from None
    return saved


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
    cfg: TrainConfig,
    out_dir: str | Path,
    device: str = "cpu",
    resume: bool = False,
    progress: bool = True,
    force: bool = False,
) -> dict:
    """Run (or resume) training; returns the final state dict (best validation numbers, paths).

    A folder holding a run is continued only with `resume` (under the same config but RESUMABLE) and
    replaced only with `force`."""
    cfg.validate()
    out = Path(out_dir)
    saved = _check_out(out, cfg, resume, force)
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
    if saved is not None:
        state = _load_checkpoint(out, model, opt, saved)
        state["config"] = asdict(cfg)  # the steps and time limit it now trains to (the card reports them)
        _trim_log(out / "log.csv", state["step"])
        log.info("resumed at step %d", state["step"])
    elif cfg.init_weights:
        _init_from(model, Path(cfg.init_weights))
    out.mkdir(parents=True, exist_ok=True)
    if saved is None:
        _start_afresh(out)
    (out / "train_config.json").write_text(json.dumps(asdict(cfg), indent=2))
    scratch = Path(tempfile.mkdtemp(prefix="liver_p2p_val_"))  # the weights the validation workers read
    try:
        validator = Validator(validation_cases(cfg, val_files, real_dev), device, cfg.val_workers, scratch)
        with closing(validator):
            _run_steps(
                cfg,
                out,
                model,
                opt,
                state,
                validator,
                _loader(cfg, train_files, state, voxel, real_train),
                device,
                progress,
            )
    finally:
        shutil.rmtree(scratch, ignore_errors=True)  # also when the run fails or is interrupted
    _save_checkpoint(out, model, opt, state)
    return state


def _loader(
    cfg: TrainConfig, files: list[Path], state: dict, voxel: float, real_files: list[Path]
) -> torch.utils.data.DataLoader:
    """The training pairs, drawn in `loader_workers` processes (none: in this one)."""
    stream = PairStream(cfg, files, state["step"], voxel, real_files)
    workers = cfg.loader_workers
    return torch.utils.data.DataLoader(
        stream,
        batch_size=None,
        num_workers=workers,
        prefetch_factor=4 if workers else None,
        # spawned like every worker of the package (pools.py): a forked one would block in its first
        # OpenMP region of a runtime this process has used (torch, Open3D, pykdtree)
        multiprocessing_context=spawn_context() if workers else None,
    )


def _run_steps(
    cfg: TrainConfig,
    out: Path,
    model: MatcherNet,
    opt: torch.optim.Optimizer,
    state: dict,
    validator: Validator,
    loader: torch.utils.data.DataLoader,
    device: str,
    progress: bool,
) -> None:
    """The training steps from state["step"] to cfg.steps (or the time limit): log, validate, checkpoint."""
    from tqdm import tqdm

    csv_path = out / "log.csv"
    new_csv = not csv_path.exists()
    t0 = time.perf_counter() - state["elapsed_s"]
    model.train()
    with (
        open(csv_path, "a", newline="") as fh,
        tqdm(total=cfg.steps, initial=state["step"], desc="train", unit="step", disable=not progress) as bar,
    ):
        writer = csv.DictWriter(fh, fieldnames=CSV_COLUMNS)
        if new_csv:
            writer.writeheader()
        running: dict[str, float] = {}
        for pair in loader:
            if STREAM_ERROR in pair:  # the stream could draw no pair: the config's views are unreachable
                raise InputError(pair[STREAM_ERROR])
            step = state["step"]
            if step >= cfg.steps:
                break
            pair = {k: v.to(device) for k, v in pair.items()}
            for g in opt.param_groups:
                g["lr"] = _lr(cfg, step)
            loss, parts = pair_loss(model, pair, cfg.temperature, cfg.overlap_weight)
            if not math.isfinite(parts["loss"]):  # stop before the step spreads NaN into the weights
                raise InputError(_diverged(out, step + 1, f"the loss is {parts['loss']}"))
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
                row.update(_validate(out, model, state, validator))
            if state["step"] % 10 == 0 or "val_learned_mm" in row:
                writer.writerow(row)
                fh.flush()
            if state["step"] % cfg.checkpoint_every == 0 or over_time or state["step"] == cfg.steps:
                _save_checkpoint(out, model, opt, state)
            if over_time:
                log.info("wall-clock limit of %.1f min reached at step %d", cfg.max_minutes, state["step"])
                break


def _validate(out: Path, model: MatcherNet, state: dict, validator: Validator) -> dict[str, float]:
    """Score the model; a better one (and only finite weights) becomes best.safetensors. The metrics."""
    if not _finite(model):  # NaN weights fail every pair: 1000 mm, which would still be saved as a "best"
        raise InputError(_diverged(out, state["step"], "the weights hold NaN or inf"))
    metrics = validator(model)
    log.info("step %d: %s", state["step"], json.dumps(metrics))
    if state["best_val_mm"] is None or metrics["val_score_mm"] < state["best_val_mm"]:
        state["best_val_mm"] = metrics["val_score_mm"]
        state["best_step"] = state["step"]
        state["best_metrics"] = metrics
        save_weights(model, out / "best.safetensors", {"step": str(state["step"]), "val": json.dumps(metrics)})
    return metrics
