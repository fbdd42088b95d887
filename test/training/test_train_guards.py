"""Training refuses what it cannot do well with one line: unreachable views, divergence, a run or export it would
overwrite, a resumed run under another config, a store of other settings, damaged files."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import asdict
from pathlib import Path

import pytest
import yaml

from liver_p2p_reg.cli import main
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom.loader import build_store
from liver_p2p_reg.registration.features.learned.weights import load_weights
from liver_p2p_reg.training.data import ensure_store
from liver_p2p_reg.training.train import train
from liver_p2p_reg.training.train_config import TrainConfig

SMALL = {"width": 32, "layers": 1, "out_dim": 16, "max_nodes": 64}
STORE = {"store_livers": 3, "store_deformations": 1, "store_seed": 5, "store_tets": 500}


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_store(
        tmp_path_factory.mktemp("store"), livers=3, deformations=1, seed=5, target_tets=500, progress=False
    )


def small_config(store: Path, **changes) -> TrainConfig:
    """A run of a few seconds on the test store."""
    base = dict(
        store_dir=str(store), **STORE, val_livers=1, val_pairs=1, steps=2, val_every=2, checkpoint_every=1,
        loader_workers=0, warmup_steps=1, crop_modes=["random"], model=dict(SMALL),
    )  # fmt: skip
    return TrainConfig(**{**base, **changes})


@pytest.fixture(scope="module")
def finished_run(store: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("runs") / "run"
    train(small_config(store), out, progress=False)
    return out


def copy_run(run: Path, tmp_path: Path) -> Path:
    """A copy of the finished run to change."""
    return Path(shutil.copytree(run, tmp_path / "run"))


def contents(folder: Path) -> dict[str, bytes]:
    """Every file of a folder, by name."""
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def cli(capsys: pytest.CaptureFixture, *argv: str) -> tuple[int, str]:
    """Run `liver-p2p ARGV`; the exit status and stderr."""
    code = main(list(argv))
    return code, capsys.readouterr().err


def write_yaml(path: Path, cfg: TrainConfig) -> Path:
    """The config as a YAML file for the CLI."""
    path.write_text(yaml.safe_dump(asdict(cfg)))
    return path


def test_a_stream_that_can_draw_no_pair_stops_with_one_line(store: Path, tmp_path: Path) -> None:
    cfg = small_config(store, crop_modes=["camera"], visibility_min=0.99, visibility_max=1.0)  # no camera sees that
    with pytest.raises(InputError, match=r"no training pair could be drawn.*visibility_min.*crop_modes") as err:
        train(cfg, tmp_path / "run", progress=False)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"noise_levels_mm": [float("inf")]}, "noise_levels_mm"),
        ({"noise_levels_mm": [1.0e6]}, "noise_levels_mm"),
        ({"overlap_weight": float("inf")}, "overlap_weight must be a finite number"),
        ({"lr": float("nan")}, "lr must be a finite number"),
        ({"max_minutes": float("nan")}, "max_minutes must be a finite number"),
        ({"hole_probability": float("nan")}, "hole_probability must be a finite number"),
        ({"seed": 10**23}, r"seed must be in \[0, 2147483647\]"),
        ({"store_seed": 10**9}, "store_seed must be in"),
        ({"store_seed": 900}, "store_seed must be outside 900-999"),
        ({"threads": 100_000}, r"threads must be in \[0, 256\]"),
        ({"loader_workers": 10_000}, "loader_workers must be in"),
        ({"val_workers": 10_000}, "val_workers must be in"),
        ({"store_workers": 10_000}, "store_workers must be in"),
        ({"store_tets": 10**10}, "store_tets must be in"),
        ({"store_livers": 10**6}, "store_livers must be in"),
        ({"model": {"width": "abc"}}, "model.width must be an integer"),
        ({"model": {"width": -4}}, r"model.width must be an integer in \[1, 4096\], got -4"),
        ({"model": {"width": 10, "heads": 3}}, r"model.width \(10\) must be a multiple of model.heads \(3\)"),
        ({"model": {"distance_max_norm": float("nan")}}, "model.distance_max_norm must be a finite number"),
        ({"model": {"in_dim": 5}}, "model.in_dim must be"),
        ({"model": {"layers": True}}, "model.layers must be an integer"),
        ({"store_dir": ""}, "store_dir must name a folder"),
        ({"val_visibility_min": 0.01}, "need 0.05 <= val_visibility_min"),
        ({"visibility_min": 0.01}, "need 0.05 <= visibility_min"),
    ],
)
def test_bad_numbers_are_refused_when_the_config_is_read(tmp_path: Path, changes: dict, message: str) -> None:
    with pytest.raises(InputError, match=message):
        TrainConfig(**changes).validate()


def test_diverged_training_stops_saves_no_best_and_leaves_no_scratch(
    store: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))  # where the run makes its validation folder
    out = tmp_path / "huge_overlap"
    with pytest.raises(InputError, match="training diverged at step 1: the loss is inf"):
        train(small_config(store, overlap_weight=1e308), out, progress=False)
    assert not (out / "best.safetensors").exists() and not (out / "last.safetensors").exists()
    out = tmp_path / "huge_lr"  # the first step is finite, its weights are not fit for a second one
    with pytest.raises(InputError, match="training diverged at step 2"):
        train(small_config(store, lr=1e30), out, progress=False)
    assert not (out / "best.safetensors").exists()
    assert json.loads((out / "state.json").read_text())["step"] == 1  # the last finite checkpoint stays
    load_weights(out / "last.safetensors")  # finite: it loads
    assert not list(scratch.glob("liver_p2p_val_*"))  # the failed runs removed their validation folders


def test_export_overwrites_nothing_without_force(finished_run: Path, tmp_path: Path, capsys) -> None:
    run = copy_run(finished_run, tmp_path)
    before = contents(run)
    for dest, message in [
        (tmp_path / "card.md", "use one of .safetensors"),
        (run / "state.json", "use one of .safetensors"),
        (run / "best.safetensors", "is an input of this command"),
        (run / "state.safetensors", "is inside the run folder"),
    ]:
        code, err = cli(capsys, "train", "--out", str(run), "--export", str(dest))
        assert code == 2 and message in err and err.count("\n") == 1, err
    assert contents(run) == before
    dest = tmp_path / "mine.safetensors"
    assert cli(capsys, "train", "--out", str(run), "--export", str(dest))[0] == 0
    exported = contents(tmp_path)
    code, err = cli(capsys, "train", "--out", str(run), "--export", str(dest))
    assert code == 2 and "exists; pass --force" in err
    dest.unlink()
    code, err = cli(capsys, "train", "--out", str(run), "--export", str(dest))  # the card alone is kept too
    assert code == 2 and "mine.json" in err and "mine.md" in err
    assert cli(capsys, "train", "--out", str(run), "--export", str(dest), "--force")[0] == 0
    assert contents(tmp_path).keys() == exported.keys()


def test_a_run_folder_is_replaced_only_with_force(store: Path, finished_run: Path, tmp_path: Path, capsys) -> None:
    run = copy_run(finished_run, tmp_path)
    before = contents(run)
    config = write_yaml(tmp_path / "t.yaml", small_config(store, seed=3, steps=1, val_every=1))
    code, err = cli(capsys, "train", "--config", str(config), "--out", str(run), "--no-progress")
    assert code == 2 and "holds a training run" in err and "--resume" in err and "--force" in err
    assert contents(run) == before
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "log.csv").write_text("date,mood\n")  # a user's file of that name is never deleted
    code, err = cli(capsys, "train", "--config", str(config), "--out", str(tmp_path / "mine"), "--no-progress")
    assert code == 2 and "log.csv is no training log" in err
    (tmp_path / "afile").write_text("x")
    code, err = cli(capsys, "train", "--config", str(config), "--out", str(tmp_path / "afile"), "--no-progress")
    assert code == 2 and "is a file" in err
    with pytest.raises(InputError, match="holds no state.json"):
        train(small_config(store), tmp_path / "empty", resume=True, progress=False)
    assert cli(capsys, "train", "--config", str(config), "--out", str(run), "--force", "--no-progress")[0] == 0
    assert json.loads((run / "state.json").read_text())["config"]["seed"] == 3
    steps = [line.split(",")[0] for line in (run / "log.csv").read_text().splitlines()]
    assert steps == ["step", "1"]  # the new run's log alone, not appended to the old one's


def test_resume_refuses_another_config(store: Path, finished_run: Path, tmp_path: Path) -> None:
    run = copy_run(finished_run, tmp_path)
    before = contents(run)
    with pytest.raises(InputError, match=r"another config \(lr 0.001 -> 0.5; seed 0 -> 7\)"):
        train(small_config(store, lr=0.5, seed=7, steps=3), run, resume=True, progress=False)
    with pytest.raises(InputError, match=r"another config \(model.width 32 -> 64\)"):
        train(small_config(store, model={**SMALL, "width": 64}, steps=3), run, resume=True, progress=False)
    assert contents(run) == before
    with open(run / "log.csv", "a") as fh:  # a step logged after the last checkpoint, then a kill
        fh.write("7,1.0,0.001,1,1,1,,,,,,\n")
    state = train(small_config(store, steps=3, max_minutes=5.0), run, resume=True, progress=False)
    assert state["step"] == 3 and state["config"]["steps"] == 3  # the card reports what it trained to
    assert [line.split(",")[0] for line in (run / "log.csv").read_text().splitlines()] == ["step", "2", "3"]


def test_a_store_of_other_settings_is_refused(store: Path, tmp_path: Path) -> None:
    for changes, message in [
        ({"store_seed": 7}, r"built with other settings: store_seed 5 \(config 7\)"),
        ({"store_tets": 600}, r"store_tets 500 \(config 600\)"),
        ({"store_deformations": 2}, r"store_deformations 1 \(config 2\)"),
        ({"store_livers": 4}, "holds 3 of the config's 4 livers"),
    ]:
        with pytest.raises(InputError, match=message):
            ensure_store(small_config(store, **changes), progress=False)
    train_files, val_files = ensure_store(small_config(store, store_livers=2), progress=False)
    assert [f.name for f in train_files + val_files] == ["liver_0050000.npz", "liver_0050001.npz"]  # its first two


def test_an_interrupted_build_reuses_only_livers_of_its_settings(store: Path, tmp_path: Path) -> None:
    copy = Path(shutil.copytree(store, tmp_path / "store"))
    (copy / "store.json").unlink()  # as an interrupted build leaves it
    with pytest.raises(InputError, match="simulated with 1 deformations and 500 target tets; this store asks 2"):
        build_store(copy, livers=3, deformations=2, seed=5, target_tets=500, progress=False)
    with pytest.raises(InputError, match="500 target tets; this store asks 1 and 3000"):
        build_store(copy, livers=3, deformations=1, seed=5, target_tets=3000, progress=False)
    shutil.copy(copy / "liver_0050002.npz", copy / "liver_0070000.npz")  # a stray file of another build
    build_store(copy, livers=2, deformations=1, seed=5, target_tets=500, progress=False)
    assert json.loads((copy / "store.json").read_text())["livers"] == ["liver_0050000.npz", "liver_0050001.npz"]


def test_damaged_store_files_are_one_line_errors(store: Path, tmp_path: Path) -> None:
    copy = Path(shutil.copytree(store, tmp_path / "store"))
    cfg = small_config(copy)
    liver = copy / "liver_0050001.npz"
    liver.write_bytes(liver.read_bytes()[:1000])
    with pytest.raises(InputError, match="liver_0050001.npz is damaged"):
        train(cfg, tmp_path / "a", progress=False)
    liver.unlink()
    with pytest.raises(InputError, match="liver_0050001.npz is missing"):
        train(cfg, tmp_path / "b", progress=False)
    text = (copy / "store.json").read_text()
    (copy / "store.json").write_text(text[:20])
    with pytest.raises(InputError, match="store.json is unreadable or damaged"):
        train(cfg, tmp_path / "c", progress=False)


def test_damaged_run_files_are_one_line_errors(store: Path, finished_run: Path, tmp_path: Path) -> None:
    run = copy_run(finished_run, tmp_path)
    cfg = small_config(store, steps=3)
    (run / "optimizer.safetensors").unlink()
    with pytest.raises(InputError, match="optimizer.safetensors is missing"):
        train(cfg, run, resume=True, progress=False)
    (run / "state.json").write_text((run / "state.json").read_text()[:40])
    with pytest.raises(InputError, match="state.json is unreadable or damaged"):
        train(cfg, run, resume=True, progress=False)


def test_state_json_is_replaced_whole(store: Path, finished_run: Path, tmp_path: Path) -> None:
    # A hard-linked copy (cp -al) shares its files with the original: a checkpoint written in place would
    # change the original run's state.json too (and a kill mid-write would leave half a file).
    run = tmp_path / "run"
    run.mkdir()
    for path in finished_run.iterdir():
        os.link(path, run / path.name)
    original = (finished_run / "state.json").read_text()
    train(small_config(store, steps=3), run, resume=True, progress=False)
    assert (finished_run / "state.json").read_text() == original
    assert json.loads((run / "state.json").read_text())["step"] == 3
