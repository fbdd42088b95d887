"""Shipped matcher weights: safetensors without pickle, reference output, clear errors when broken."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from liver_p2p_reg.errors import WeightsError
from liver_p2p_reg.registration.features.learned.model import MatcherNet, ModelConfig
from liver_p2p_reg.registration.features.learned.provider import LearnedProvider
from liver_p2p_reg.registration.features.learned.weights import (
    BUNDLED_WEIGHTS,
    load_weights,
    save_weights,
    weights_metadata,
)

REFERENCE = Path(__file__).parents[1] / "data" / "learned_reference.npz"


def test_bundled_weights_are_small_safetensors_with_a_model_card() -> None:
    assert BUNDLED_WEIGHTS.is_file()
    assert BUNDLED_WEIGHTS.stat().st_size <= 20 * 1024 * 1024
    assert BUNDLED_WEIGHTS.read_bytes()[:8] != b"\x80\x02\x8a\nl\xfc\x9c"  # not a torch pickle
    meta = weights_metadata(BUNDLED_WEIGHTS)
    assert json.loads(meta["model_config"])["out_dim"] > 0
    card = json.loads(BUNDLED_WEIGHTS.with_suffix(".json").read_text())
    assert {"training_config", "data", "commit", "validation", "wall_clock_min"} <= set(card)


def test_bundled_weights_reproduce_the_reference_output() -> None:
    ref = np.load(REFERENCE, allow_pickle=False)
    provider = LearnedProvider()  # the bundled weights
    xs, xt = provider.describe(torch.as_tensor(ref["source"]), torch.as_tensor(ref["target"]), {})
    np.testing.assert_allclose(xs.numpy(), ref["x_source"], atol=1e-4)
    np.testing.assert_allclose(xt.numpy(), ref["x_target"], atol=1e-4)


def test_save_load_roundtrip_loads_without_pickle(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    torch.manual_seed(3)
    net = MatcherNet(ModelConfig(width=32, layers=1, out_dim=16))
    path = save_weights(net, tmp_path / "m.safetensors")

    def no_pickle(*args: object, **kwargs: object) -> None:
        raise AssertionError("pickle used")

    monkeypatch.setattr("pickle.load", no_pickle)
    monkeypatch.setattr("pickle.loads", no_pickle)
    loaded = load_weights(path)
    for (k, a), (_, b) in zip(net.state_dict().items(), loaded.state_dict().items(), strict=True):
        assert torch.equal(a, b), k


def test_missing_corrupt_and_incompatible_weights_raise_weights_error(tmp_path: Path) -> None:
    with pytest.raises(WeightsError, match="not found"):
        load_weights(tmp_path / "nope.safetensors")
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"this is not a safetensors file at all")
    with pytest.raises(WeightsError, match="unreadable"):
        load_weights(bad)
    truncated = tmp_path / "trunc.safetensors"
    truncated.write_bytes(BUNDLED_WEIGHTS.read_bytes()[:5000])
    with pytest.raises(WeightsError):
        load_weights(truncated)
    from safetensors.torch import save_file

    foreign = tmp_path / "foreign.safetensors"
    save_file({"w": torch.zeros(3)}, str(foreign), metadata={"format": "something-else"})
    with pytest.raises(WeightsError, match="format"):
        load_weights(foreign)
    net = MatcherNet(ModelConfig(width=32, layers=1, out_dim=16))
    path = save_weights(net, tmp_path / "m.safetensors")
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        meta, tensors = f.metadata(), {k: f.get_tensor(k) for k in f.keys()}
    tensors.pop("embed.0.weight")
    save_file(tensors, str(path), metadata=meta)
    with pytest.raises(WeightsError, match=r"do not fit .*: tensor embed.0.weight \(32, 26\) is missing$"):
        load_weights(path)


def _bundled_with_model_config(path: Path, **change: object) -> Path:
    """The bundled tensors under a changed `model_config` (what a hand-edited or foreign file holds)."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(BUNDLED_WEIGHTS), framework="pt") as f:
        meta, tensors = f.metadata(), {k: f.get_tensor(k) for k in f.keys()}
    model_config = {**json.loads(meta["model_config"]), **change}
    save_file(tensors, str(path), metadata={**meta, "model_config": json.dumps(model_config)})
    return path


@pytest.mark.parametrize(
    ("change", "says"),
    [
        ({"width": "64"}, r"width must be an integer in \[1, 4096\], got '64'"),  # was a TypeError from torch
        ({"width": None}, r"width must be an integer in \[1, 4096\], got None"),
        ({"width": 0}, r"width must be an integer in \[1, 4096\], got 0"),  # was a torch warning, then an error
        ({"points_per_node": 0}, r"points_per_node must be an integer in \[1, 100000\]"),  # ZeroDivisionError
        ({"distance_max_norm": float("nan")}, r"distance_max_norm must be a finite number in \(0, 100\], got nan"),
        ({"layers": 100_000}, r"layers must be an integer in \[1, 64\], got 100000"),  # 7 GB, then out of memory
        ({"max_nodes": -5}, r"max_nodes must be an integer in \[4, 16384\], got -5"),  # silently ran with 4
        ({"heads": 3}, r"width \(64\) must be a multiple of heads \(3\)"),
        ({"in_dim": 7}, "in_dim must be 26"),
        ({"depth": 2}, "unknown keys: 'depth'"),
    ],
)
def test_odd_model_config_metadata_is_refused_before_the_net_is_built(tmp_path: Path, change: dict, says: str) -> None:
    path = _bundled_with_model_config(tmp_path / "odd.safetensors", **change)
    with pytest.raises(WeightsError, match=f"bad model_config metadata \\({says}") as info:
        load_weights(path)
    assert "\n" not in str(info.value)


def test_a_model_config_that_does_not_fit_the_tensors_names_the_first_one_in_one_line(tmp_path: Path) -> None:
    path = _bundled_with_model_config(tmp_path / "heads2.safetensors", heads=2)
    with pytest.raises(
        WeightsError, match=r"tensor distance_bias is \(3, 33, 4\) in the file, \(3, 33, 2\) in the"
    ) as info:
        load_weights(path)
    assert "\n" not in str(info.value)
    # the largest net the limits allow is compared without being built (64 layers of 4096 wide: ~100 GB)
    path = _bundled_with_model_config(tmp_path / "huge.safetensors", layers=64, width=4096)
    with pytest.raises(WeightsError, match=r"tensor distance_bias is .* \(and \d+ more differences\)"):
        load_weights(path)


def test_weights_holding_nan_or_inf_raise_weights_error(tmp_path: Path) -> None:
    # A diverged training run's checkpoint: every registration with it would fail and blame the data.
    net = MatcherNet(ModelConfig(width=32, layers=1, out_dim=16))
    with torch.no_grad():
        net.embed[0].bias[0] = float("nan")
        net.head[0].weight[0, 0] = float("inf")
    path = save_weights(net, tmp_path / "diverged.safetensors")
    with pytest.raises(WeightsError, match="hold NaN or infinite values .* and 1 more") as err:
        load_weights(path)
    assert "\n" not in str(err.value)


def test_cli_reports_bad_weights_in_one_line(tmp_path: Path) -> None:
    from liver_p2p_reg.cloud_io import save_points

    rng = np.random.default_rng(0)
    d = rng.normal(size=(3000, 3))
    src = 80 * d / np.linalg.norm(d, axis=1, keepdims=True)
    save_points(tmp_path / "s.npy", src)
    save_points(tmp_path / "t.npy", src[src[:, 0] > 20])
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"weights_path: {tmp_path / 'missing.safetensors'}\nmethod: learned-p2p\n")
    proc = subprocess.run(
        [sys.executable, "-m", "liver_p2p_reg", "register", str(tmp_path / "s.npy"), str(tmp_path / "t.npy"),
         "--config", str(cfg)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "weights not found" in lines[0], proc.stderr


# Another CPU takes other SIMD paths and moves a pose by ~1e-5 mm; a changed pose moves it by far more.
POSE_TOLERANCE_MM = 0.05


def test_bundled_weights_reproduce_the_reference_poses_on_bundled_bags() -> None:
    from learned_reference_poses import FRAMES, REFERENCE, frame_pose
    from same_pose import surface_shift_mm

    from liver_p2p_reg.config import Config
    from liver_p2p_reg.registration.weights_id import weights_sha256

    ref = json.loads(REFERENCE.read_text())
    assert ref["weights_sha256"] == weights_sha256(Config()), "reference made with other weights: rewrite it"
    for bag, index in FRAMES:
        pose, preop = frame_pose(bag, index)
        shift = surface_shift_mm(pose, np.asarray(ref["poses"][f"{bag}#{index}"]), preop)
        assert shift <= POSE_TOLERANCE_MM, f"{bag}#{index}: {shift:.4f} mm from the reference pose"
