"""What a method may use besides the two clouds (ground truth, a prior pose, the sensor origin) and its cache."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class MethodContext:
    """What a method may use besides the two clouds: ground truth (oracle) and a cache."""

    source_fiducials_mm: np.ndarray | None = None
    target_fiducials_mm: np.ndarray | None = None
    # Lives as long as the Registrar: methods keep loaded models / source features here.
    cache: dict[str, Any] = field(default_factory=dict)
    initial_T_mm: np.ndarray | None = None  # a prior T_target_source (method `track`)
    sensor_origin_mm: np.ndarray | None = None  # (3,) where the target's sensor stood, target frame (free space)
    # small views' contenders -> their keys (contenders.py: the elastic stage's residual); None: no judge
    judge_keys: Callable[[list[np.ndarray], list[float]], list[float]] | None = None


def remember_latest(
    cache: dict[str, Any], kind: str, points: np.ndarray, params: tuple, compute: Callable[[], Any]
) -> Any:
    """Per-source memo in a Registrar's cache: `compute()` once per (points, params).

    Keeps only the latest entry of each `kind`, so a node (one preoperative model, many
    frames) hits the cache every frame while a benchmark over many livers stays bounded.
    """
    digest = hashlib.blake2b(np.ascontiguousarray(points).tobytes(), digest_size=16).hexdigest()
    key = f"{kind}:{digest}:{params!r}"
    try:
        return cache[key]
    except KeyError:
        pass
    # list(cache) is one step: the candidate's RANSAC thread (hypotheses.RansacBeside) may add its own kinds meanwhile
    for old in [k for k in list(cache) if isinstance(k, str) and k.startswith(f"{kind}:")]:
        cache.pop(old, None)
    value = compute()
    cache[key] = value
    return value
