"""Patient-prepared matcher files: weights tuned to one liver, its shape signature and precomputed source features.

A prepared file is a safetensors file like the general weights (architecture in the header) plus
- `prepared.source_vox_norm` (N, 3) and `prepared.f_src` (N, F): the voxelized, normalized
  preoperative source and its invariant input features, so the first registration in surgery
  skips them when its source is the same cloud;
- metadata `source_signature`: rigid-invariant numbers of the liver's surface (point count, PCA
  spreads, radial quantiles), so a prepared file used with another liver is noticed (the
  general weights are then used, with a warning) while the same liver in another frame is not
  refused; `model_card`: how it was prepared and validated.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from liver_p2p_reg.errors import WeightsError

PREPARED_FORMAT = "liver_p2p_reg.prepared/1"
SIGNATURE_REL_TOL = 0.01  # spreads and radii may differ by 1 % (float32 metres on ROS, resampling)
SIGNATURE_ABS_TOL_MM = 0.5


def source_signature(source_mm: np.ndarray) -> dict[str, float]:
    """Rigid-invariant description of a preoperative surface cloud (mm)."""
    pts = np.asarray(source_mm, dtype=np.float64)
    centred = pts - pts.mean(axis=0)
    spreads = np.sqrt(np.clip(np.linalg.eigvalsh(centred.T @ centred / len(pts)), 0.0, None))
    radii = np.quantile(np.linalg.norm(centred, axis=1), [0.1, 0.5, 0.9, 1.0])
    return {
        "n_points": int(len(pts)),
        **{f"spread{i}_mm": float(v) for i, v in enumerate(spreads)},
        **{f"radius_q{q}_mm": float(v) for q, v in zip((10, 50, 90, 100), radii, strict=True)},
    }


def signature_mismatch(expected: dict[str, float], actual: dict[str, float]) -> str:
    """Empty when both describe the same surface (within tolerance); else what differs, in words: the prepared
    surface's value first, then this one's ("28005 points, this one 31080").

    The point count is compared too: the same liver meshed more finely, or given as its own points, is another
    surface here (its prepared source features would not be its own)."""
    if abs(expected["n_points"] - actual["n_points"]) > SIGNATURE_REL_TOL * expected["n_points"]:
        return f"{expected['n_points']} points, this one {actual['n_points']}"
    for key, value in expected.items():
        if key == "n_points":
            continue
        got = actual.get(key, float("nan"))
        if not abs(got - value) <= max(SIGNATURE_ABS_TOL_MM, SIGNATURE_REL_TOL * abs(value)):
            return f"{key} {value:.1f} mm, this one {got:.1f} mm"
    return ""


@dataclass
class PreparedSource:
    """What a prepared file knows about its liver."""

    signature: dict[str, float]
    vox_norm: np.ndarray | None = None  # (N, 3) voxelized normalized source
    f_src: np.ndarray | None = None  # (N, F) its input features
    card: dict[str, Any] = field(default_factory=dict)


def read_prepared_source(path: str | Path) -> PreparedSource | None:
    """The prepared part of a weights file, or None for general weights."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="np", device="cpu") as f:
            meta = f.metadata() or {}
            if meta.get("format") != PREPARED_FORMAT:
                return None
            keys = set(f.keys())
            vox = f.get_tensor("prepared.source_vox_norm") if "prepared.source_vox_norm" in keys else None
            feats = f.get_tensor("prepared.f_src") if "prepared.f_src" in keys else None
    except (SafetensorError, OSError, ValueError) as exc:
        raise WeightsError(f"prepared weights {path} are unreadable: {exc}") from None
    try:
        signature = json.loads(meta["source_signature"])
        card = json.loads(meta.get("model_card", "{}"))
    except (KeyError, ValueError) as exc:
        raise WeightsError(f"prepared weights {path}: bad metadata ({exc})") from None
    return PreparedSource(signature, vox, feats, card)


def save_prepared(
    model: Any,
    path: str | Path,
    source: PreparedSource,
    extra: dict[str, str] | None = None,
) -> Path:
    """Write a prepared file: the model's tensors, the source's precomputed tensors, the metadata."""
    from safetensors.torch import save_file

    path = Path(path)
    tensors = {k: v.detach().to("cpu").contiguous() for k, v in model.state_dict().items()}
    import torch

    if source.vox_norm is not None and source.f_src is not None:
        tensors["prepared.source_vox_norm"] = torch.as_tensor(source.vox_norm, dtype=torch.float64).contiguous()
        tensors["prepared.f_src"] = torch.as_tensor(source.f_src, dtype=torch.float32).contiguous()
    meta = {
        "format": PREPARED_FORMAT,
        "model_config": json.dumps(model.cfg.to_dict()),
        "source_signature": json.dumps(source.signature),
        "model_card": json.dumps(source.card),
        **(extra or {}),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata=meta)
    tmp.chmod(0o644)
    tmp.replace(path)
    return path
