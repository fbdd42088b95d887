"""`liver-p2p prepare`: tune the matcher to one patient's liver before surgery (patient-prepared weights)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from liver_p2p_reg.cli.output_paths import output_file
from liver_p2p_reg.config_ranges import MAX_SEED
from liver_p2p_reg.errors import InputError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register the `prepare` subcommand."""
    p = subparsers.add_parser(
        "prepare",
        help="fine-tune the matcher on simulated views of this patient's liver (hours before surgery)",
        description=(
            "Builds a tetrahedral mesh of the preoperative surface, draws FEM deformations and random and "
            "camera-like views of it with noise and density variation, and fine-tunes the shipped matcher on "
            "them within the time budget. The output (safetensors, no pickle) carries the model card and the "
            "source's precomputed features; use it with `register --weights` or the node's weights_path. "
            "Resumable: rerun the same command after an interruption."
        ),
    )
    p.add_argument("preop_mesh", metavar="PREOP_MESH", help="closed surface mesh of the liver in mm (STL/OBJ/PLY/OFF)")
    p.add_argument("--minutes", type=float, required=True, help="time budget for the whole preparation")
    p.add_argument("--out", required=True, help="prepared weights file to write (e.g. patient.safetensors)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--seed", type=int, default=0, help="seed of the deformations, views and training (default 0)")
    p.add_argument(
        "--steps",
        type=int,
        help="train exactly this many steps (reproduces a card's run) instead of fitting the budget",
    )
    p.add_argument("--weights", default="", help="general weights to start from (default: the bundled ones)")
    p.add_argument(
        "--force",
        action="store_true",
        help="overwrite an existing --out, and start afresh a preparation left in OUT.work with other settings",
    )
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Check everything cheap first, then prepare and print the model card's summary."""
    mesh = Path(args.preop_mesh)
    if not mesh.is_file():
        raise InputError(f"file not found: {mesh}")
    if args.weights and not Path(args.weights).is_file():
        raise InputError(f"--weights {args.weights} not found")
    # checked before hours of work: a folder, an input, an existing file or link without --force
    inputs = [mesh, *([Path(args.weights)] if args.weights else [])]
    out = output_file(args.out, args.force, "--out", inputs=inputs, suffixes=(".safetensors",))
    if not 0 < args.minutes < math.inf:  # inf was accepted and crashed once the budget became a step count
        raise InputError(f"--minutes must be a finite number > 0, got {args.minutes}")
    if not 0 <= args.seed <= MAX_SEED:  # a larger seed overflowed torch's, after the simulation
        raise InputError(f"--seed must be in [0, {MAX_SEED}], got {args.seed}")
    if args.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise InputError("--device cuda: torch sees no CUDA device")
    from liver_p2p_reg.training.patient import prepare_file

    card = prepare_file(
        mesh,
        out,
        args.minutes,
        seed=args.seed,
        steps=args.steps,
        device=args.device,
        base_weights=args.weights,
        fresh=args.force,
        progress=not args.no_progress,
    )
    b, a = card["validation_before"], card["validation_after"]
    print(
        f"prepared {out} for {mesh.name} (sha256 {card['mesh_sha256'][:12]}): {card['steps']} steps in "
        f"{card['wall_clock_s'] / 60:.1f} min; held-out views ({card['validation_views']}): learned-p2p mean "
        f"{b['learned_p2p_mean_mm']:.2f} -> {a['learned_p2p_mean_mm']:.2f} mm, success@10 mm "
        f"{100 * b['success10']:.0f} -> {100 * a['success10']:.0f} %"
    )
    if getattr(args, "quiet", False) is False:
        print(json.dumps({k: card[k] for k in ("mesh_sha256", "steps", "seed", "budget_minutes")}))
    return 0
