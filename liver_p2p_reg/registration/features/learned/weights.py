"""Safetensors load/save of the matcher (architecture in the header metadata; never pickle)."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from liver_p2p_reg.config_io import quoted
from liver_p2p_reg.errors import WeightsError
from liver_p2p_reg.registration.features.learned.model import MatcherNet, model_config_from

BUNDLED_WEIGHTS = Path(__file__).resolve().parents[3] / "weights" / "matcher_v4.safetensors"
FORMAT = "liver_p2p_reg.matcher/1"


def save_weights(model: MatcherNet, path: str | Path, extra: dict[str, str] | None = None) -> Path:
    """Write the model's tensors and its ModelConfig (JSON in the safetensors metadata)."""
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().to("cpu").contiguous() for k, v in model.state_dict().items()}
    meta = {"format": FORMAT, "model_config": json.dumps(model.cfg.to_dict()), **(extra or {})}
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata=meta)
    tmp.chmod(0o644)  # package data: readable by everyone (the temp file is created private)
    tmp.replace(path)
    return path


def load_weights(path: str | Path | None = None, device: str | torch.device = "cpu") -> MatcherNet:
    """Rebuild the matcher from a safetensors file (default: the bundled weights) in eval mode.

    Raises WeightsError with one line for a missing, corrupt or incompatible file.
    """
    from safetensors import SafetensorError, safe_open

    path = Path(path) if path else BUNDLED_WEIGHTS
    if not path.is_file():
        raise WeightsError(f"matcher weights not found: {path}")
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise WeightsError(f"matcher weights {path} are unreadable (not a valid safetensors file): {exc}") from None
    from liver_p2p_reg.registration.features.learned.patient import PREPARED_FORMAT

    if meta.get("format") == PREPARED_FORMAT:  # a patient-prepared file: its network part
        tensors = {k: v for k, v in tensors.items() if not k.startswith("prepared.")}
    elif meta.get("format") != FORMAT:
        raise WeightsError(f"matcher weights {path} have format {meta.get('format')!r}, expected {FORMAT!r}")
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:  # a diverged training run's weights: every registration would fail, and blame the data
        more = f" and {len(bad) - 1} more" if len(bad) > 1 else ""
        raise WeightsError(f"matcher weights {path} hold NaN or infinite values ({bad[0]}{more}); not usable")
    try:
        cfg = model_config_from(json.loads(meta["model_config"]))
    except KeyError:
        raise WeightsError(f"matcher weights {path} have no model_config metadata") from None
    except ValueError as exc:  # json.JSONDecodeError is one
        raise WeightsError(f"matcher weights {path}: bad model_config metadata ({exc})") from None
    except RecursionError:  # JSON nested thousands deep
        raise WeightsError(f"matcher weights {path}: bad model_config metadata (nested too deeply)") from None
    # The shapes are compared on a net without storage ("meta"): a config that does not match the tensors is
    # refused before a real one, which its fields alone could make gigabytes large, is built.
    with torch.device("meta"):
        expected = MatcherNet(cfg).state_dict()
    mismatch = state_dict_mismatch(expected, tensors)
    if mismatch:
        raise WeightsError(f"matcher weights {path} do not fit the network of their model_config: {mismatch}")
    try:
        model = MatcherNet(cfg)
        model.load_state_dict(tensors, strict=True)
    except RuntimeError as exc:  # not expected after the comparison above; one line all the same
        first = str(exc).splitlines()[0] if str(exc) else "shape mismatch"
        raise WeightsError(f"matcher weights {path} do not fit the network: {quoted(first)}") from None
    return model.to(device).eval()


def state_dict_mismatch(expected: dict[str, torch.Tensor], given: dict[str, torch.Tensor]) -> str:
    """The first difference between a net's tensors and a file's (a key one lacks, or two shapes), "" if none."""
    differ = [k for k in expected if k not in given or tuple(given[k].shape) != tuple(expected[k].shape)]
    extra = [k for k in given if k not in expected]
    more = len(differ) + len(extra) - 1
    tail = f" (and {more} more differences)" if more > 0 else ""
    if differ:
        key, shape = differ[0], tuple(expected[differ[0]].shape)
        if key not in given:
            return f"tensor {key} {shape} is missing{tail}"
        return f"tensor {key} is {tuple(given[key].shape)} in the file, {shape} in the network{tail}"
    if extra:
        return f"tensor {quoted(extra[0])} is not one of the network's{tail}"
    return ""


def weights_metadata(path: str | Path) -> dict[str, str]:
    """The string metadata stored in a safetensors header."""
    from safetensors import safe_open

    with safe_open(str(path), framework="pt", device="cpu") as f:
        return dict(f.metadata() or {})
