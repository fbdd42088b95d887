"""Exporting a training run's best checkpoint as shipped weights with its model card (.json and .md)."""

from __future__ import annotations

import json
from pathlib import Path

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.files import path_inside
from liver_p2p_reg.registration.features.learned.weights import load_weights, save_weights

SIDECARS = (".json", ".md")  # the model card next to the weights
# The state.json keys (and its config's) the card is written from.
STATE_KEYS = ("step", "elapsed_s", "config")
CONFIG_KEYS = (
    "store_dir",
    "store_seed",
    "store_deformations",
    "store_livers",
    "val_livers",
    "val_pairs",
    "temperature",
    "overlap_weight",
)


def check_destination(run: Path, dest: Path, force: bool) -> None:
    """Refuse a destination that is no .safetensors file, lies in the run folder (it would replace the run's
    own files) or, without `force`, exists with or without its card."""
    if dest.suffix.lower() != ".safetensors":
        raise InputError(f"--export {dest}: use a .safetensors path (the card goes next to it as .json and .md)")
    if dest.is_dir():
        raise InputError(f"--export {dest} is a folder; give a file path")
    if path_inside(dest, run):
        raise InputError(f"--export {dest} is inside the run folder {run}; choose a path outside it")
    existing = [p for p in [dest, *(dest.with_suffix(s) for s in SIDECARS)] if p.exists() or p.is_symlink()]
    if existing and not force:
        raise InputError(f"{', '.join(map(str, existing))} exists; pass --force to overwrite")


def read_run_state(run: Path) -> dict:
    """A finished run's state.json with the keys the card needs; InputError naming a damaged one."""
    path = run / "state.json"
    try:
        state = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path} is unreadable or damaged ({exc})") from None
    if not isinstance(state, dict) or any(k not in state for k in STATE_KEYS) or not isinstance(state["config"], dict):
        raise InputError(f"{path} is damaged (no {', '.join(STATE_KEYS)})")
    missing = [k for k in CONFIG_KEYS if k not in state["config"]]
    if missing:
        raise InputError(f"{path} is damaged (its config lacks {', '.join(missing)})")
    return state


def export_weights(
    run_dir: str | Path, dest: str | Path, commit: str = "", notes: str = "", force: bool = False
) -> Path:
    """Copy a run's best checkpoint to `dest` with a model card (`.json` + `.md` next to it); an existing
    destination or card only with `force`."""
    run, dest = Path(run_dir), Path(dest)
    best = run / "best.safetensors"
    if not best.is_file() or not (run / "state.json").is_file():
        raise InputError(f"{run}: no best.safetensors/state.json (train first)")
    check_destination(run, dest, force)
    state = read_run_state(run)
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
        from liver_p2p_reg.phantom.loader import read_store_meta

        store_meta.update(read_store_meta(store_meta_path.parent))
        # a larger store: the run trained on its first store_livers (training.data.ensure_store)
        store_meta["livers"] = store_meta["livers"][: cfg["store_livers"]]
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
        f"- Validation ({cfg['val_pairs']} pairs, held-out livers, random crops, visibility "
        f"{cfg.get('val_visibility_min', 0.2):g}-{cfg.get('val_visibility_max', 1.0):g}, no noise): "
        f"learned {val.get('val_learned_mm', float('nan')):.2f} mm, "
        f"learned-p2p {val.get('val_learned_p2p_mm', float('nan')):.2f} mm mean RMS-TRE, "
        f"success@20mm {val.get('val_success20', float('nan')):.2f}"
        + (
            f"; {cfg['real_val_pairs']} pairs of the real train_dev livers (random and camera crops, visibility "
            f"{cfg.get('real_val_visibility_min', 0.2):g}-{cfg.get('real_val_visibility_max', 0.5):g}, "
            f"noise 0 or 2 mm): learned-p2p {val['val_real_p2p_mm']:.2f} mm."
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
