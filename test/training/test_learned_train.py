"""Training smoke tests: the loss drops on a tiny generated set; checkpoints resume without pickle."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom.loader import PairSampler, build_store
from liver_p2p_reg.registration.features.learned.model import MatcherNet, ModelConfig
from liver_p2p_reg.registration.features.learned.weights import load_weights
from liver_p2p_reg.training.data import prepare_pair
from liver_p2p_reg.training.train import pair_loss, train
from liver_p2p_reg.training.train_config import TrainConfig

SMALL = {"width": 32, "layers": 1, "out_dim": 16, "max_nodes": 64}
# The settings the `store` fixture was built with: a run checks its store is the one its config describes.
STORE = {"store_livers": 2, "store_deformations": 1, "store_seed": 5, "store_tets": 1500}


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_store(
        tmp_path_factory.mktemp("store"), livers=2, deformations=1, seed=5, target_tets=1500, progress=False
    )


def test_prepare_pair_ground_truth_is_consistent(store: Path) -> None:
    sample = PairSampler(store, seed=1, visibility_range=(0.4, 0.6)).sample()
    pair = prepare_pair(sample, 0.06, np.random.default_rng(0))
    assert pair["f_src"].shape[0] == pair["src"].shape[0]
    assert len(pair["gt_src"]) == len(pair["gt_tgt"]) > 0.5 * len(pair["tgt"])
    assert 0.2 < float(pair["ov_src"].mean()) < 0.9  # only part of the source is seen


def test_few_iterations_reduce_the_loss(store: Path) -> None:
    torch.manual_seed(0)
    sampler = PairSampler(store, seed=2, visibility_range=(0.4, 0.8))
    pairs = [prepare_pair(sampler.sample(), 0.08, np.random.default_rng(0))]
    net = MatcherNet(ModelConfig(**SMALL))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)

    def total() -> float:
        with torch.no_grad():
            return sum(pair_loss(net, p, 0.1, 0.5)[1]["loss"] for p in pairs)

    before = total()
    for _ in range(30):
        for p in pairs:
            loss, _ = pair_loss(net, p, 0.1, 0.5)
            opt.zero_grad()
            loss.backward()
            opt.step()
    assert total() < 0.8 * before


def test_train_writes_checkpoints_and_resumes(store: Path, tmp_path: Path) -> None:
    cfg = TrainConfig(
        store_dir=str(store), **STORE, val_livers=1, val_pairs=1, steps=2, val_every=2, checkpoint_every=1,
        loader_workers=0, warmup_steps=1, crop_modes=["random"], model=dict(SMALL),
    )  # fmt: skip
    out = tmp_path / "run"
    state = train(cfg, out, progress=False)
    assert state["step"] == 2 and state["best_step"] == 2
    for name in ("best.safetensors", "last.safetensors", "optimizer.safetensors", "state.json", "log.csv"):
        assert (out / name).is_file(), name
    assert load_weights(out / "best.safetensors").cfg.width == 32
    cfg.steps = 3
    state = train(cfg, out, resume=True, progress=False)
    assert state["step"] == 3
    assert json.loads((out / "state.json").read_text())["step"] == 3
    rows = list(csv.DictReader(open(out / "log.csv")))
    assert rows[-1]["step"] == "3" and float(rows[-1]["val_learned_p2p_mm"]) > 0


def test_training_reproduces_its_first_steps_bitwise_from_the_seed(store: Path, tmp_path: Path) -> None:
    cfg = TrainConfig(
        store_dir=str(store), **STORE, val_livers=1, val_pairs=1, steps=3, val_every=3, checkpoint_every=3,
        loader_workers=0, warmup_steps=1, crop_modes=["random"], model=dict(SMALL), seed=7,
        visibility_min=0.05, visibility_max=0.35, val_visibility_min=0.05, val_visibility_max=0.35,
    )  # fmt: skip
    runs = [train(cfg, tmp_path / f"run{i}", progress=False) for i in range(2)]
    weights = [load_weights(tmp_path / f"run{i}" / "last.safetensors").state_dict() for i in range(2)]
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])
    logs = [[r["loss"] for r in csv.DictReader(open(tmp_path / f"run{i}" / "log.csv"))] for i in range(2)]
    assert logs[0] == logs[1] and len(logs[0]) >= 1
    assert json.dumps(runs[0]["best_metrics"]) == json.dumps(runs[1]["best_metrics"])  # NaN where no real pairs
    cfg.seed = 8  # another seed draws other pairs: the weights differ (the test can fail)
    train(cfg, tmp_path / "run_other", progress=False)
    other = load_weights(tmp_path / "run_other" / "last.safetensors").state_dict()
    assert not all(torch.equal(weights[0][k], other[k]) for k in other)


def test_a_loader_worker_process_trains_to_the_in_process_weights(
    store: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = TrainConfig(
        store_dir=str(store), **STORE, val_livers=1, val_pairs=1, steps=2, val_every=2, checkpoint_every=2,
        loader_workers=0, warmup_steps=1, crop_modes=["random"], model=dict(SMALL), seed=3,
    )  # fmt: skip
    train(cfg, tmp_path / "in_process", progress=False)
    contexts: list = []
    real_loader = torch.utils.data.DataLoader

    def recording_loader(*args, **kwargs):  # torch's own loader, noting how it starts its workers
        contexts.append(kwargs.get("multiprocessing_context"))
        return real_loader(*args, **kwargs)

    monkeypatch.setattr(torch.utils.data, "DataLoader", recording_loader)
    cfg.loader_workers = 1
    train(cfg, tmp_path / "worker", progress=False)
    # spawned, never forked: a forked worker blocks in its first OpenMP region of a runtime the trainer used
    assert [c.get_start_method() for c in contexts] == ["spawn"]
    # worker 0 draws the in-process stream: the same pairs, so the same weights, bit for bit
    a, b = (load_weights(tmp_path / run / "last.safetensors").state_dict() for run in ("in_process", "worker"))
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_bad_training_config_is_an_input_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    bad = tmp_path / "train.yaml"
    bad.write_text("stepz: 3\n")
    with pytest.raises(InputError, match="stepz"):
        TrainConfig.from_yaml(bad)
    with pytest.raises(InputError, match="cannot read"):
        TrainConfig.from_yaml(tmp_path / "missing.yaml")
    # Values are checked when the file is read, before minutes of building the store.
    for text, message in [
        ("steps: -5", "steps must be >= 1"),
        ("steps: abc", "steps must be an integer"),
        ("visibility_min: 0.8\nvisibility_max: 0.5", "visibility_min <= visibility_max"),
        ("crop_modes: [random, sideways]", "crop_modes"),
        ("model: {widht: 3}", "unknown model keys: widht"),
        ("init_weights: nope.safetensors", "init_weights nope.safetensors not found"),
        ("val_visibility_min: 0.0", "val_visibility_min <= val_visibility_max"),
        ("- a list", "must be a mapping"),
    ]:
        bad.write_text(text + "\n")
        with pytest.raises(InputError, match=message):
            TrainConfig.from_yaml(bad)
    monkeypatch.chdir(Path(__file__).parents[2])  # init_weights is relative to the repository
    for name in ("train.yaml", "train_finetune.yaml", "train_small_views.yaml"):  # the shipped configs pass
        TrainConfig.from_yaml(Path("config") / name)


def test_fine_tuning_starts_from_init_weights(store: Path, tmp_path: Path) -> None:
    from liver_p2p_reg.registration.features.learned.weights import save_weights

    torch.manual_seed(3)
    init = save_weights(MatcherNet(ModelConfig(**SMALL)), tmp_path / "init.safetensors")
    cfg = TrainConfig(
        store_dir=str(store), **STORE, val_livers=1, val_pairs=1, steps=1, val_every=1, checkpoint_every=1,
        loader_workers=0, warmup_steps=1, crop_modes=["random"], model=dict(SMALL), lr=0.0,
        init_weights=str(init),
    )  # fmt: skip
    train(cfg, tmp_path / "run", progress=False)
    before, after = load_weights(init).state_dict(), load_weights(tmp_path / "run" / "last.safetensors").state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)  # lr 0: the init survives one step unchanged
    cfg.model = {**SMALL, "width": 48}
    with pytest.raises(InputError, match="architecture"):
        train(cfg, tmp_path / "run2", progress=False)
