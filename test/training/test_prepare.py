"""Patient-specific preparation: a small liver prepared in seconds, its file, the liver check and bad meshes."""

from __future__ import annotations

import json
import pickle
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from liver_p2p_reg import Config, Registrar
from liver_p2p_reg.errors import LiverP2PError
from liver_p2p_reg.phantom.anatomy import make_liver
from liver_p2p_reg.phantom.crop import make_target
from liver_p2p_reg.registration.features.learned.patient import (
    read_prepared_source,
    signature_mismatch,
    source_signature,
)
from liver_p2p_reg.registration.features.learned.weights import load_weights
from liver_p2p_reg.training.data import prepare_pair, training_sampler
from liver_p2p_reg.training.patient import PrepareSize, prepare_liver, training_config
from liver_p2p_reg.training.train import pair_loss

SMALL = PrepareSize(train_deformations=3, val_deformations=1, views=4, tets=1500)
STEPS = 100


@pytest.fixture(scope="module")
def liver():
    return make_liver(21)


@pytest.fixture(scope="module")
def prepared(liver, tmp_path_factory):
    out = tmp_path_factory.mktemp("prep") / "patient.safetensors"
    card = prepare_liver(
        liver.vertices_mm, liver.triangles, liver.vertices_mm, out, 5.0, name="liver21", steps=STEPS,
        progress=False, size=SMALL,
    )  # fmt: skip
    return out, card


def _views_loss(weights: Path | None, pairs: list[dict]) -> float:
    model = load_weights(weights)
    with torch.no_grad():
        return float(np.mean([pair_loss(model, p, 0.1, 0.5)[1]["match"] for p in pairs]))


def test_preparation_lowers_the_matching_loss_on_its_own_views(prepared) -> None:
    out, card = prepared
    assert card["steps"] == STEPS and card["mesh_name"] == "liver21" and len(card["mesh_sha256"]) == 64
    # Fresh views of its own liver, drawn as the preparation draws them (another seed).
    store = out.with_name(out.name + ".work") / "store"
    sampler = training_sampler(
        training_config(store, "", 0, STEPS, 0.0, SMALL), str(store), [store / "liver_train.npz"], 99
    )
    rng, pairs = np.random.default_rng(0), []
    while len(pairs) < 12:
        try:
            pairs.append(prepare_pair(sampler.sample(), 0.04, rng))
        except LiverP2PError:
            continue  # a view the pipeline refuses (as in training): draw another
    assert _views_loss(out, pairs) < 0.99 * _views_loss(None, pairs)


def test_prepared_file_loads_without_pickle_and_reproduces_its_output(prepared, liver, monkeypatch) -> None:
    out, _ = prepared
    rng = np.random.default_rng(3)
    view = make_target(liver.vertices_mm, liver.vertices_mm, liver.triangles, 0.3, "camera", 1.0, rng)["tgt_pcd"]
    first = Registrar(Config(method="learned-p2p", weights_path=str(out))).register(liver.vertices_mm, view)

    def no_pickle(*args, **kwargs):
        raise AssertionError("pickle used")

    monkeypatch.setattr(pickle, "load", no_pickle)
    monkeypatch.setattr(pickle, "loads", no_pickle)
    again = Registrar(Config(method="learned-p2p", weights_path=str(out))).register(liver.vertices_mm, view)
    np.testing.assert_array_equal(first.T_target_source, again.T_target_source)
    assert not first.warnings
    source = read_prepared_source(out)
    assert source.vox_norm is not None and source.f_src.shape[0] == source.vox_norm.shape[0]
    assert source.card["validation_after"]["learned_p2p_mean_mm"] > 0


def test_precomputed_source_features_are_the_ones_the_network_would_compute(prepared, liver) -> None:
    from liver_p2p_reg.registration.features.learned.descriptors import local_features

    source = read_prepared_source(prepared[0])
    np.testing.assert_array_equal(source.f_src, local_features(source.vox_norm).astype(np.float32))


def test_another_liver_gets_the_general_weights_and_a_warning(prepared) -> None:
    out, _ = prepared
    other = make_liver(22).vertices_mm
    rng = np.random.default_rng(4)
    n = len(other) // 3
    view = other[np.argsort(other[:, 1])[-n:]] + rng.normal(scale=0.3, size=(n, 3))
    result = Registrar(Config(method="learned-p2p", weights_path=str(out))).register(other, view)
    assert len(result.warnings) == 1 and "another liver" in result.warnings[0]
    general = Registrar(Config(method="learned-p2p")).register(other, view)
    np.testing.assert_array_equal(result.T_target_source, general.T_target_source)


def test_the_warning_names_the_prepared_surface_and_this_one(prepared, liver) -> None:
    # it named the prepared mesh beside the current source's count ("liver21: 6000 points, prepared for 3000"), and
    # called the same liver sampled more densely "another liver"
    out, _ = prepared
    v, t = liver.vertices_mm, liver.triangles
    denser = np.vstack([v, v[t].mean(axis=1)])  # the same surface: its vertices and its triangles' centres
    view = v[np.argsort(v[:, 1])[-len(v) // 3 :]]
    result = Registrar(Config(method="learned-p2p", weights_path=str(out))).register(denser, view)
    expected = (
        rf"prepared weights {re.escape(str(out))} were prepared for another preop surface "
        rf"\(liver21: {len(v)} points, this one {len(denser)}\): another liver, or the same one meshed or sampled "
        "otherwise; general weights used"
    )
    assert len(result.warnings) == 1 and re.fullmatch(expected, result.warnings[0]), result.warnings


def test_the_same_liver_moved_still_matches_its_signature(liver) -> None:
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    moved = liver.vertices_mm @ rot.T + [30.0, -5.0, 12.0]
    assert signature_mismatch(source_signature(liver.vertices_mm), source_signature(moved)) == ""
    assert signature_mismatch(source_signature(liver.vertices_mm), source_signature(make_liver(22).vertices_mm))
    # the prepared surface's value first, then this one's
    half = liver.vertices_mm[::2]
    n = len(liver.vertices_mm)
    assert signature_mismatch(source_signature(liver.vertices_mm), source_signature(half)) == (
        f"{n} points, this one {len(half)}"
    )
    grown = liver.vertices_mm * 1.5
    said = re.fullmatch(
        r"spread0_mm (\d+\.\d) mm, this one (\d+\.\d) mm",
        signature_mismatch(source_signature(liver.vertices_mm), source_signature(grown)),
    )
    assert said and float(said[2]) == pytest.approx(1.5 * float(said[1]), abs=0.2)


def test_node_core_reports_the_mismatch_as_warn(prepared) -> None:
    from liver_p2p_reg.stream.core import NodeCore
    from liver_p2p_reg.stream.outputs import WARN

    out, _ = prepared
    other = make_liver(22).vertices_mm
    core = NodeCore(Config(method="learned-p2p", weights_path=str(out), track_previous_pose=False, mode="on_demand"))
    core.set_preop(other, frame_id="ct")
    view = other[np.argsort(other[:, 1])[-len(other) // 3 :]]
    core.on_intraop_points(view, frame_id="camera", stamp_ns=1)
    output = core.reregister()
    assert output.pose is not None and output.level == WARN and "another liver" in output.summary


def _write_obj(path: Path, v: np.ndarray, f: np.ndarray) -> Path:
    lines = [f"v {x:.5f} {y:.5f} {z:.5f}" for x, y, z in v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize(
    "make, words",
    [
        (lambda v, f: (v, f[:-4]), "open mesh"),
        (lambda v, f: (v / 1000.0, f), "metres?"),
        (lambda v, f: (v, np.concatenate([f, f[:1]])), "non-manifold"),
    ],
)
def test_cli_bad_meshes_get_one_line(tmp_path, liver, make, words) -> None:
    v, f = make(liver.vertices_mm, liver.triangles)
    mesh = _write_obj(tmp_path / "bad.obj", v, f)
    cmd = [
        sys.executable,
        "-m",
        "liver_p2p_reg",
        "prepare",
        str(mesh),
        "--minutes",
        "1",
        "--out",
        str(tmp_path / "p.safetensors"),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip() and "INFO" not in line]
    assert len(lines) == 1 and words in lines[0], proc.stderr


def test_cli_refuses_to_overwrite_and_bad_budgets(tmp_path, liver) -> None:
    mesh = _write_obj(tmp_path / "liver.obj", liver.vertices_mm, liver.triangles)
    existing = tmp_path / "p.safetensors"
    existing.write_bytes(b"keep me")
    folder = tmp_path / "folder.safetensors"
    folder.mkdir()
    link = tmp_path / "link.safetensors"
    link.symlink_to(tmp_path / "not_yet.safetensors")
    base = [sys.executable, "-m", "liver_p2p_reg", "prepare", str(mesh), "--out"]
    for extra, words in (
        ([str(existing), "--minutes", "1"], "exists; pass --force"),
        ([str(tmp_path / "q.safetensors"), "--minutes", "0"], "--minutes must be a finite number > 0"),
        ([str(tmp_path / "q.pt"), "--minutes", "1"], "use one of .safetensors"),
        # refused before the work, not after it (inf crashed once the budget became steps; a huge seed overflowed
        # torch's after the simulation; a folder was found when the weights were written)
        ([str(tmp_path / "q.safetensors"), "--minutes", "inf"], "--minutes must be a finite number > 0"),
        ([str(tmp_path / "q.safetensors"), "--minutes", "1", "--seed", str(2**64)], "--seed must be in"),
        ([str(folder), "--minutes", "1", "--force"], "is a folder"),
        ([str(link), "--minutes", "1"], "is a link to"),
    ):
        proc = subprocess.run(base + extra, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2 and words in proc.stderr and len(proc.stderr.splitlines()) == 1, proc.stderr
    assert existing.read_bytes() == b"keep me" and link.is_symlink()


def test_a_rerun_with_other_settings_is_refused_or_started_afresh(prepared, liver, tmp_path) -> None:
    """A new --steps or --minutes was silently ignored: the work folder's plan was resumed as it was."""
    out, card = prepared
    args = (liver.vertices_mm, liver.triangles, liver.vertices_mm, out)
    for minutes, steps, words in ((5.0, 40, "other --steps (it planned 100)"), (5.0, None, "this run fits the budget")):
        with pytest.raises(LiverP2PError, match=re.escape(words)):
            prepare_liver(*args, minutes, name="liver21", steps=steps, progress=False, size=SMALL)
    # --force (fresh): the other preparation's folder is discarded and this one made from the start
    other = tmp_path / "other.safetensors"
    work = other.with_name(other.name + ".work")
    work.mkdir()
    (work / "plan.json").write_text(json.dumps({**json.loads((out.with_name(out.name + ".work") / "plan.json")
                                                             .read_text()), "seed": 7}))  # fmt: skip
    (work / "stale.txt").write_text("from the other preparation")
    with pytest.raises(LiverP2PError, match="other --seed"):
        prepare_liver(*args[:3], other, 5.0, name="liver21", steps=2, progress=False, size=SMALL)
    (work / "plan.json").write_text('{"mesh_sha256": "cut sh')  # a kill mid-write (it is written whole now)
    with pytest.raises(LiverP2PError, match="is damaged.*pass --force"):
        prepare_liver(*args[:3], other, 5.0, name="liver21", steps=2, progress=False, size=SMALL)
    card = prepare_liver(*args[:3], other, 5.0, name="liver21", steps=2, fresh=True, progress=False, size=SMALL)
    assert card["steps"] == 2 and card["seed"] == 0 and not (work / "stale.txt").exists()
