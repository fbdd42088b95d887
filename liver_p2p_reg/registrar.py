"""The public registration API: `Registrar(config).register(source_mm, target_mm)`.

The CLI, the benchmark, bag replay and the ROS node all call this and nothing else.
Methods register themselves by name with `@method("name")` in their own modules.
"""

from __future__ import annotations

import hashlib
import importlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .alloc import reuse_freed_memory
from .cloud_io import as_float_array, clean_points, require_plausible_extent
from .config import Config
from .errors import InputError, LiverP2PError
from .method_names import METHOD_MODULES, method_names
from .metrics import rms_tre_mm, tre_mm
from .result import RegistrationResult


@dataclass
class MethodContext:
    """What a method may use besides the two clouds: ground truth (oracle) and a cache."""

    source_fiducials_mm: np.ndarray | None = None
    target_fiducials_mm: np.ndarray | None = None
    # Lives as long as the Registrar: methods keep loaded models / source features here.
    cache: dict[str, Any] = field(default_factory=dict)
    initial_T_mm: np.ndarray | None = None  # a prior T_target_source (method `track`)
    sensor_origin_mm: np.ndarray | None = None  # (3,) where the target's sensor stood, target frame (free space)


def remember_latest(
    cache: dict[str, Any], kind: str, points: np.ndarray, params: tuple, compute: Callable[[], Any]
) -> Any:
    """Per-source memo in a Registrar's cache: `compute()` once per (points, params).

    Keeps only the latest entry of each `kind`, so a node (one preoperative model, many
    frames) hits the cache every frame while a benchmark over many livers stays bounded.
    """
    digest = hashlib.blake2b(np.ascontiguousarray(points).tobytes(), digest_size=16).hexdigest()
    key = f"{kind}:{digest}:{params!r}"
    if key not in cache:
        for old in [k for k in cache if isinstance(k, str) and k.startswith(f"{kind}:")]:
            del cache[old]
        cache[key] = compute()
    return cache[key]


MethodFn = Callable[[np.ndarray, np.ndarray, Config, MethodContext], RegistrationResult]
_REGISTRY: dict[str, MethodFn] = {}
_loaded = False


def method(name: str) -> Callable[[MethodFn], MethodFn]:
    """Decorator registering a registration method under `name`."""

    def wrap(fn: MethodFn) -> MethodFn:
        _REGISTRY[name] = fn
        return fn

    return wrap


def _import_method_module(module: str) -> None:
    try:
        importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name is None or not module.startswith(exc.name):  # a real missing dependency
            raise


def _load_methods() -> None:
    global _loaded
    if _loaded:
        return
    for module in METHOD_MODULES:
        _import_method_module(module)
    _loaded = True


def known_methods() -> list[str]:
    """The table's methods and any registered besides (plug-ins, tests), without importing a method module."""
    return sorted(set(method_names()) | set(_REGISTRY))


def check_method_name(name: str) -> None:
    """InputError listing the choices when `name` is no known method; imports no method module."""
    if name not in known_methods():
        raise InputError(f"unknown method {name!r}; choose one of: {', '.join(known_methods())}")


def available_methods() -> list[str]:
    """Names of all registered methods."""
    _load_methods()
    return sorted(_REGISTRY)


def get_method(name: str) -> MethodFn:
    """Look a method up by name (importing only its module); unknown names raise InputError listing the choices."""
    if name not in _REGISTRY:
        module = next((m for m, names in METHOD_MODULES.items() if name in names), None)
        if module is not None:
            _import_method_module(module)
    if name not in _REGISTRY:
        _load_methods()  # a method registered outside the table, or the full list for the message
    if name not in _REGISTRY:
        raise InputError(f"unknown method {name!r}; choose one of: {', '.join(sorted(_REGISTRY))}")
    return _REGISTRY[name]


# Why a cloud of implausible size is refused (it would still "register", to a meaningless pose).
UNITS_HINT = (
    "points are read as millimetres and a liver is 50-300 mm across: convert the cloud, "
    "or set expected_extent_min_mm / expected_extent_max_mm for other objects"
)


class Registrar:
    """Registers complete preoperative surfaces to partial intraoperative ones (mm in, mm out)."""

    def __init__(self, config: Config | None = None, **overrides: Any) -> None:
        config = config or Config()
        self.config = config.replace(**overrides) if overrides else config.validate()
        self.cache: dict[str, Any] = {}
        if self.config.reuse_freed_memory:
            reuse_freed_memory()  # process-wide, once; see alloc.py

    def register(
        self,
        source_mm: np.ndarray,
        target_mm: np.ndarray,
        *,
        method: str | None = None,
        source_fiducials_mm: np.ndarray | None = None,
        target_fiducials_mm: np.ndarray | None = None,
        initial_T_mm: np.ndarray | None = None,
        sensor_origin_mm: np.ndarray | None = None,
    ) -> RegistrationResult:
        """Estimate T_target_source (4x4, mm). Raises InputError / RegistrationError.

        `initial_T_mm` is a prior pose, used by the `track` method (ICP from the prior).
        `sensor_origin_mm` is where the target's depth sensor stood (3 numbers, mm, target frame):
        then every hypothesis is also scored by free-space consistency (freespace.py), which
        enters the selection, the ambiguity test and `result.free_space_violation`. None (unknown)
        changes nothing.
        """
        start = time.perf_counter()
        source = clean_points(source_mm, "source", min_points=self.config.min_points)
        target = clean_points(target_mm, "target", min_points=self.config.min_points)
        for points, name in ((source, "source"), (target, "target")):
            require_plausible_extent(
                points, name, self.config.expected_extent_min_mm, self.config.expected_extent_max_mm, UNITS_HINT
            )
        fid_s, fid_t = _check_fiducials(source_fiducials_mm, target_fiducials_mm)
        name = method or self.config.method
        fn = get_method(name)
        ctx = MethodContext(fid_s, fid_t, self.cache, _check_pose(initial_T_mm), _check_origin(sensor_origin_mm))
        result = fn(source, target, self.config, ctx)
        result.method = name
        # After an ICP screening its refined hypotheses are the better evidence of a rival pose.
        from .confidence import is_ambiguous  # scipy: imported with the first registration, not with the API

        cfg = self.config
        hypotheses = result.screened or result.candidates
        result.ambiguous = is_ambiguous(
            hypotheses, source, cfg.ambiguity_residual_ratio, cfg.ambiguity_pose_mm, cfg.free_space_weight
        )
        if fid_s is not None and fid_t is not None:
            result.rms_tre_mm = rms_tre_mm(result.T_target_source, fid_s, fid_t)
            result.max_tre_mm = float(np.max(tre_mm(result.T_target_source, fid_s, fid_t)))
        result.runtime_ms["total"] = (time.perf_counter() - start) * 1e3
        return result

    def warm_up(self, source_mm: np.ndarray, method: str | None = None) -> float:
        """Compute everything the method caches about a new source (its preprocessing, source
        features, model weights, ICP index) before the first real target arrives; returns ms.

        It registers the source to a fixed partial view of itself through the normal code path,
        so no method needs a hook of its own; the result is discarded and errors are ignored
        (the first real registration reports them).
        """
        start = time.perf_counter()
        try:
            source = clean_points(source_mm, "source", min_points=self.config.min_points)
            centre = source[np.argmax(source[:, 0])]  # a deterministic cap of the surface
            near = np.argsort(np.linalg.norm(source - centre, axis=1))[: max(len(source) // 3, 3)]
            self.register(source, source[near], method=method)
        except LiverP2PError:
            pass
        return (time.perf_counter() - start) * 1e3


def register(
    source_mm: np.ndarray, target_mm: np.ndarray, method: str | None = None, **kwargs: Any
) -> RegistrationResult:
    """One-call convenience: `register(source_mm, target_mm, method="fpfh-p2p", k=5)`."""
    fiducials = {k: kwargs.pop(k) for k in ("source_fiducials_mm", "target_fiducials_mm") if k in kwargs}
    return Registrar(**kwargs).register(source_mm, target_mm, method=method, **fiducials)


def _check_pose(T: np.ndarray | None) -> np.ndarray | None:
    if T is None:
        return None
    T = as_float_array(T, "initial_T_mm")
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError(f"initial_T_mm must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InputError("initial_T_mm must be a rigid transform (its 3x3 block is not a rotation)")
    return T


def _check_origin(origin: np.ndarray | None) -> np.ndarray | None:
    if origin is None:
        return None
    origin = as_float_array(origin, "sensor origin").reshape(-1)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise InputError(f"the sensor origin must be 3 finite numbers (mm, target frame), got {origin.tolist()}")
    return origin


def _check_fiducials(fid_s: np.ndarray | None, fid_t: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None]:
    if fid_s is None or fid_t is None:
        return (
            None if fid_s is None else as_float_array(fid_s, "source fiducials"),
            None if fid_t is None else as_float_array(fid_t, "target fiducials"),
        )
    fid_s, fid_t = as_float_array(fid_s, "source fiducials"), as_float_array(fid_t, "target fiducials")
    if fid_s.shape != fid_t.shape or fid_s.ndim != 2 or fid_s.shape[1] != 3:
        raise InputError(f"fiducials must be two (F, 3) arrays of the same shape, got {fid_s.shape} and {fid_t.shape}")
    if not (np.isfinite(fid_s).all() and np.isfinite(fid_t).all()):
        # unlike cloud points they are paired one to one, so a bad one cannot just be dropped
        raise InputError("fiducials contain NaN or infinite coordinates")
    return fid_s, fid_t
