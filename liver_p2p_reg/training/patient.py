"""Patient-specific preparation: fine-tune the matcher on simulated views of one patient's liver.

`prepare_liver` builds the liver's tetrahedral mesh, draws FEM deformations of it (the last two
held out for validation), and fine-tunes the shipped matcher (`train.train`, resumable) on fresh
random and camera-like views of the training deformations with noise, density variation and
artifacts, always from the undeformed (preoperative) shape. A short probe run measures the
machine's speed so that the whole preparation fits the time budget; the steps it chose are
recorded and `--steps` reproduces the run exactly (deterministic given the seed). The result is
a prepared file (prepared.py) with the source's precomputed features and a model card holding
the mesh hash, budget, steps and the validation before and after on held-out views.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.files import write_text_atomic
from liver_p2p_reg.registration.features.learned.patient import PreparedSource, save_prepared, source_signature

log = logging.getLogger(__name__)

PROBE_STEPS = 20


@dataclass(frozen=True)
class PrepareSize:
    """How much is simulated: FEM deformations to train on and to hold out, held-out views, tets."""

    train_deformations: int = 8
    val_deformations: int = 2
    views: int = 24
    tets: int = 6000


# Start-up, the two validations and saving, beyond the simulation itself (seconds, 2 cores).
RESERVE_S = 25.0
PREPARED_ID_BASE = 7_000_000  # liver ids of prepared livers (their FEM loads differ from any test set's)


def mesh_sha256(vertices: np.ndarray, triangles: np.ndarray) -> str:
    """Hash of a surface mesh's geometry (float64 vertices, int64 triangles)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(triangles, dtype=np.int64).tobytes())
    return h.hexdigest()


def training_config(
    store: Path, base_weights: str, seed: int, steps: int, max_minutes: float, size: PrepareSize | None = None
) -> Any:
    """The fine-tuning run of a preparation (the views and augmentations of config/train_real.yaml)."""
    from liver_p2p_reg.training.train_config import TrainConfig

    size = size or PrepareSize()
    return TrainConfig(
        store_dir=str(store),
        store_livers=2,
        store_deformations=size.train_deformations,
        store_tets=size.tets,
        val_livers=1,
        val_pairs=2,
        seed=seed,
        steps=steps,
        lr=1e-4,
        warmup_steps=max(1, min(50, steps // 10)),
        visibility_min=0.12,
        visibility_max=1.0,
        crop_modes=["random", "camera"],
        noise_levels_mm=[0.0, 0.0, 1.0, 2.0, 3.0, 4.0],
        val_every=steps,
        checkpoint_every=max(10, steps // 5),
        threads=1,
        loader_workers=1,
        max_minutes=max_minutes,
        init_weights=base_weights,
        density_modes=["uniform", "uniform", "mesh-vertices", "depth-falloff"],
        hole_probability=0.3,
        outlier_fraction=0.03,
        background_fraction=0.05,
        source_undeformed=True,
    )


def _store(work: Path, liver: Any, liver_id: int, size: PrepareSize) -> Path:
    """One liver simulated once: deformations for training, the last ones held out (validation)."""
    from liver_p2p_reg.phantom.loader import write_store_liver
    from liver_p2p_reg.phantom.simulate import simulate_liver

    store = work / "store"
    if (store / "store.json").is_file():
        return store
    store.mkdir(parents=True, exist_ok=True)
    n_train = size.train_deformations
    sim = simulate_liver(liver_id, n_train + size.val_deformations, target_tets=size.tets, liver=liver)
    write_store_liver(store / "liver_train.npz", replace(sim, deformations=sim.deformations[:n_train]))
    write_store_liver(store / "liver_val.npz", replace(sim, deformations=sim.deformations[n_train:]))
    (store / "store.json").write_text(json.dumps({"livers": ["liver_train.npz", "liver_val.npz"]}, indent=2))
    return store


def _val_views(store: Path, seed: int, n_views: int) -> list[dict]:
    """Held-out views: the held-out deformations seen as in surgery (random and camera, 0 / 2 mm)."""
    from liver_p2p_reg.phantom.loader import PairSampler

    sampler = PairSampler(
        store,
        seed=30_000 + seed,
        visibility_range=(0.15, 0.5),
        crop_modes=("random", "camera"),
        noise_levels_mm=(0.0, 2.0),
        source_undeformed=True,
    )
    sampler.files = [store / "liver_val.npz"]
    return [sampler.sample() for _ in range(n_views)]


def _validate(model: Any, views: list[dict]) -> dict[str, float]:
    """learned-p2p (no ICP) on the held-out views: mean RMS-TRE and success at 10 / 20 mm."""
    from liver_p2p_reg.training.validation import score_case

    errors = np.array([score_case(model, view, "cpu", variants=(True,))[0] for view in views])
    return {
        "learned_p2p_mean_mm": float(errors.mean()),
        "learned_p2p_median_mm": float(np.median(errors)),
        "success10": float(np.mean(errors < 10.0)),
        "success20": float(np.mean(errors < 20.0)),
    }


def _probe_rate(work: Path, cfg: Any) -> float:
    """Training steps per second on this machine: a short throw-away run, timed between its
    logged steps (the data loader's start-up and the final validation excluded)."""
    import csv

    from liver_p2p_reg.training.train import train

    probe = work / "probe"
    shutil.rmtree(probe, ignore_errors=True)
    train(replace(cfg, steps=PROBE_STEPS, val_every=10**9, checkpoint_every=10**9), probe, progress=False)
    with open(probe / "log.csv", newline="") as fh:
        # A row's elapsed time is taken before that step's validation, so the last row counts too.
        rows = [(int(r["step"]), float(r["elapsed_s"])) for r in csv.DictReader(fh)]
    shutil.rmtree(probe, ignore_errors=True)
    (s0, t0), (s1, t1) = rows[0], rows[-1]
    if s1 <= s0:  # a single logged row: the whole run, start-up included (slower, so safe)
        s0, t0 = 0, 0.0
    return (s1 - s0) / max(1e-3, t1 - t0)


def _read_plan(path: Path) -> dict[str, Any]:
    """A preparation's plan.json ({} when there is none); a damaged one is one line."""
    if not path.is_file():
        return {}
    try:
        plan = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{path} is damaged ({exc}); remove its folder or pass --force") from None
    if not isinstance(plan, dict):
        raise InputError(f"{path} is not a preparation's plan; remove its folder or pass --force")
    return plan


def _plan_differences(plan: dict, digest: str, seed: int, base: str, steps: int | None, minutes: float) -> list[str]:
    """What an earlier preparation's plan was made with that this one asks otherwise ([] when it may resume)."""
    differ = [
        name
        for name, ours, theirs in (("mesh", digest, plan.get("mesh_sha256")), ("--seed", seed, plan.get("seed")))
        if ours != theirs
    ]
    if plan.get("base") != base:
        differ.append("--weights")
    if steps is not None and (plan.get("from_budget", True) or plan.get("steps") != steps):
        differ.append(f"--steps (it planned {plan.get('steps')})")
    elif steps is None and not plan.get("from_budget", True):
        differ.append(f"--steps (it planned {plan.get('steps')}; this run fits the budget)")
    elif steps is None and plan.get("minutes", minutes) != minutes:  # plans before 'minutes' was kept: as asked
        differ.append(f"--minutes (it had {plan.get('minutes')})")
    return differ


def prepare_liver(
    vertices_mm: np.ndarray,
    triangles: np.ndarray,
    source_mm: np.ndarray,
    out: str | Path,
    minutes: float,
    *,
    name: str = "mesh",
    seed: int = 0,
    steps: int | None = None,
    device: str = "cpu",
    base_weights: str = "",
    fresh: bool = False,
    progress: bool = True,
    size: PrepareSize | None = None,
) -> dict[str, Any]:
    """Prepare a matcher for the liver with this closed surface; `source_mm` is the preoperative cloud
    registrations will use (for the precomputed features and the signature). Returns the model card.

    An interrupted preparation resumes from OUT.work when asked again with the same settings; with other
    settings it is refused, or with `fresh` discarded and started anew."""
    from liver_p2p_reg.phantom.real import liver_from_surface
    from liver_p2p_reg.registration.features.learned.descriptors import local_features
    from liver_p2p_reg.registration.features.learned.weights import BUNDLED_WEIGHTS, load_weights
    from liver_p2p_reg.registration.preprocess import preprocess_pair as preprocess
    from liver_p2p_reg.training.train import train

    start = time.perf_counter()
    size = size or PrepareSize()
    if not minutes > 0:
        raise InputError(f"--minutes must be > 0, got {minutes}")
    if steps is not None and steps < 1:
        raise InputError(f"--steps must be >= 1, got {steps}")
    out = Path(out)
    digest = mesh_sha256(vertices_mm, triangles)
    liver_id = PREPARED_ID_BASE + int(hashlib.sha256(f"{digest}:{seed}".encode()).hexdigest()[:8], 16) % 10**6
    liver = liver_from_surface(vertices_mm, triangles, liver_id=liver_id, name=name)  # bad meshes: one line
    base = str(base_weights or BUNDLED_WEIGHTS)
    base_model = load_weights(base)
    work = out.with_name(out.name + ".work")
    plan_path = work / "plan.json"
    try:
        plan = _read_plan(plan_path)
    except InputError:
        if not fresh:
            raise
        plan = {"damaged": True}  # --force, as its message says: started afresh
    differ = _plan_differences(plan, digest, seed, base, steps, minutes) if plan else []
    if differ and not fresh:
        raise InputError(
            f"{work} holds a preparation with other {', '.join(differ)}: rerun its command to resume it, "
            "or pass --force to start afresh"
        )
    if differ:
        shutil.rmtree(work)
        plan = {}
    work.mkdir(parents=True, exist_ok=True)
    log.info("prepare %s: simulating %d FEM deformations", name, size.train_deformations + size.val_deformations)
    store = _store(work, liver, liver_id, size)
    views = _val_views(store, seed, size.views)
    before = plan.get("before") or _validate(base_model, views)
    if not plan:
        budget_s = minutes * 60.0 - (time.perf_counter() - start) - RESERVE_S
        if steps is None:
            rate = _probe_rate(work, training_config(store, base, seed, PROBE_STEPS, 0.0, size))
            budget_s -= PROBE_STEPS / rate
            steps = max(1, int(rate * budget_s))
            log.info("prepare %s: %.2f steps/s here; %d steps fit the budget", name, rate, steps)
            from_budget = True
        else:
            from_budget = False  # an explicit --steps reproduces a run exactly: no clock involved
        plan = {
            "mesh_sha256": digest,
            "seed": seed,
            "base": base,
            "steps": int(steps),
            "from_budget": from_budget,
            "minutes": minutes,
            "before": before,
        }
        write_text_atomic(plan_path, json.dumps(plan, indent=2))  # a kill mid-write leaves no half plan
    steps = int(plan["steps"])
    # A budget-fitted run also stops at the deadline (a slower moment of the machine); the card
    # then records the steps it really made.
    left_min = max(0.1, minutes - (time.perf_counter() - start) / 60.0) if plan["from_budget"] else 0.0
    cfg = training_config(store, base, seed, steps, left_min, size)
    resume = (work / "run" / "state.json").is_file()
    # without a state (a kill before the first checkpoint was complete) the run's own leftovers are replaced
    state = train(cfg, work / "run", device=device, resume=resume, progress=progress, force=not resume)
    model = load_weights(work / "run" / "last.safetensors")
    after = _validate(model, views)
    config = Config()
    prep = preprocess(source_mm, source_mm[: max(3, len(source_mm) // 4)], config)
    # The network sees the source as float32 (pipeline.run_feature_pipeline): precompute on those values.
    vox = prep.source.astype(np.float32).astype(np.float64)
    card = {
        "mesh_name": name,
        "mesh_sha256": digest,
        "base_weights": Path(base).name,
        "budget_minutes": minutes,
        "steps": state["step"],
        "steps_planned": steps,
        "seed": seed,
        "device": device,
        "wall_clock_s": round(time.perf_counter() - start, 1),
        "deformations": {"train": size.train_deformations, "validation": size.val_deformations},
        "validation_views": size.views,
        "validation_before": before,
        "validation_after": after,
        "training_config": asdict(cfg),
    }
    source = PreparedSource(
        signature=source_signature(source_mm),
        vox_norm=vox,
        f_src=local_features(vox).astype(np.float32),
        card=card,
    )
    save_prepared(model, out, source)
    return card


def prepare_file(path: str | Path, out: str | Path, minutes: float, **kwargs: Any) -> dict[str, Any]:
    """`liver-p2p prepare PREOP_MESH`: the mesh file's surface, and the cloud `register` reads from it."""
    from liver_p2p_reg.cloud_io import load_mesh, load_points

    path = Path(path)
    vertices, triangles = load_mesh(path)
    if len(triangles) == 0:
        raise InputError(f"{path}: a point cloud; preparation needs the closed surface mesh of the liver")
    return prepare_liver(vertices, triangles, load_points(path), out, minutes, name=path.name, **kwargs)
