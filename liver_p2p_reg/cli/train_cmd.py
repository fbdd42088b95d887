"""`liver-p2p train`: train the learned matcher on fresh in silico pairs."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from liver_p2p_reg.cli import terminate_as_interrupt
from liver_p2p_reg.cli.output_paths import given_paths, output_file, output_folder
from liver_p2p_reg.errors import InputError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register the `train` subcommand."""
    p = subparsers.add_parser("train", help="train the learned matcher (checkpoints, CSV log, validation)")
    p.add_argument("--config", default="config/train.yaml", help="training config YAML (default: %(default)s)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue from OUT/last.safetensors + OUT/state.json (same config; steps, max_minutes may change)",
    )
    p.add_argument("--out", default="train_out", help="output directory (default: %(default)s)")
    p.add_argument("--steps", type=int, help="override the number of steps in the config")
    p.add_argument("--max-minutes", type=float, help="override the config's wall-clock limit (0: none)")
    p.add_argument(
        "--export",
        metavar="PATH",
        help="no training: copy OUT's best checkpoint to PATH (.safetensors) with a model card",
    )
    p.add_argument("--notes", default="", help="with --export: a paragraph added to the model card")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the run in OUT (its checkpoints, state and log); with --export: overwrite PATH and its card",
    )
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=run)


def export(args: argparse.Namespace) -> int:
    """Copy the run's best weights out with their model card."""
    import subprocess

    from liver_p2p_reg.training.export import export_weights

    run_files = [Path(args.out) / name for name in ("best.safetensors", "state.json")]
    dest = output_file(args.export, args.force, "--export", inputs=run_files, suffixes=(".safetensors",))
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    dest = export_weights(args.out, dest, commit=commit, notes=args.notes, force=args.force)
    print(f"exported {dest} (+ {dest.with_suffix('.json').name}, {dest.with_suffix('.md').name})")
    return 0


def run(args: argparse.Namespace) -> int:
    """Train; print where the best weights are."""
    if args.export:
        return export(args)
    import torch

    from liver_p2p_reg.training.train import train
    from liver_p2p_reg.training.train_config import TrainConfig

    output_folder(args.out, "--out", inputs=given_paths(args.config))
    cfg = TrainConfig.from_yaml(args.config)
    if args.steps is not None:
        if args.steps < 1:
            raise InputError(f"--steps must be >= 1, got {args.steps}")
        cfg.steps = args.steps
    if args.max_minutes is not None:
        if not (math.isfinite(args.max_minutes) and args.max_minutes >= 0):
            raise InputError(f"--max-minutes must be a finite number >= 0, got {args.max_minutes}")
        cfg.max_minutes = float(args.max_minutes)
    if args.device == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: torch sees no CUDA device")
    # A kill (SIGTERM: a scheduler's, a time limit's) ends the run as Ctrl-C does, so its cleanup runs: the
    # validation workers and the temporary folder of weights they read (also when called without `main`).
    with terminate_as_interrupt():
        state = train(
            cfg, args.out, device=args.device, resume=args.resume, progress=not args.no_progress, force=args.force
        )
    print(
        f"trained {state['step']} steps in {state['elapsed_s'] / 60:.1f} min; best weights: {args.out}/best.safetensors"
    )
    print(json.dumps(state.get("best_metrics", {})))
    return 0
