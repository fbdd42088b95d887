"""The public registration API: `Registrar(config).register(source_mm, target_mm)`.

The CLI, the benchmark, bag replay and the ROS node all call this and nothing else. It checks
the inputs, looks the method up in the table (methods.py), runs it, and adds the ambiguity test
and the TRE against ground truth.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from liver_p2p_reg.alloc import reuse_freed_memory
from liver_p2p_reg.cloud_io import as_float_array, clean_points, finite_mesh, require_plausible_extent
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.metrics import rms_tre_mm, tre_mm
from liver_p2p_reg.registration.context import MethodContext
from liver_p2p_reg.registration.methods import check_method_name, method_names, run_method
from liver_p2p_reg.registration.threads import pin_threads
from liver_p2p_reg.result import RegistrationResult

LOG = logging.getLogger("liver_p2p_reg")


def available_methods() -> list[str]:
    """Names of all methods (the table in methods.py, plug-ins included), sorted."""
    return method_names()


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
        source_triangles: np.ndarray | None = None,
        mesh_vertices_mm: np.ndarray | None = None,
    ) -> RegistrationResult:
        """Estimate T_target_source (4x4, mm). Raises InputError / RegistrationError.

        With `deform` in the config the non-rigid stage runs after the rigid pose (`self.deform`, which
        says what `source_triangles` and `mesh_vertices_mm` are).

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
        check_method_name(name)  # before the stage's surface: an unknown name is said first
        # the elastic model's surface is checked before any work: a bad one must not cost the rigid pose later
        judge = _judges(self.config, name)
        preop = (
            _preop_surface(source_mm, source, source_triangles, mesh_vertices_mm)
            if self.config.deform or judge
            else None
        )
        ctx = MethodContext(fid_s, fid_t, self.cache, _check_pose(initial_T_mm), _check_origin(sensor_origin_mm))
        if judge and preop is not None:  # small views' contenders judged by the elastic stage (contenders.py)
            from liver_p2p_reg.registration.contenders import elastic_keys

            ctx.judge_keys = elastic_keys(self.config, self.cache, source, target, *_stage_surface(source, preop))
        pin_threads(self.config.num_threads)  # the same arithmetic whatever ran before, on any thread
        result = run_method(name, source, target, self.config, ctx)
        result.method = name
        # After an ICP screening its refined hypotheses are the better evidence of a rival pose.
        from liver_p2p_reg.registration.confidence import (
            is_ambiguous,  # scipy: imported with the first registration, not with the API
        )
        from liver_p2p_reg.registration.error_calibration import attach_error_model

        cfg = self.config
        hypotheses = result.screened or result.candidates
        result.ambiguous = is_ambiguous(
            hypotheses, source, cfg.ambiguity_residual_ratio, cfg.ambiguity_pose_mm, cfg.free_space_weight
        )
        t_bound = time.perf_counter()
        attach_error_model(result, source, target, cfg)  # the fiducials only measure the error
        result.runtime_ms["error_bound"] = (time.perf_counter() - t_bound) * 1e3
        if fid_s is not None and fid_t is not None:
            result.rms_tre_mm = rms_tre_mm(result.T_target_source, fid_s, fid_t)
            result.max_tre_mm = float(np.max(tre_mm(result.T_target_source, fid_s, fid_t)))
        if preop is not None and self.config.deform:
            self._deform(result, source, target, preop, fid_s, fid_t, "frame", start=time.perf_counter())
        result.runtime_ms["total"] = (time.perf_counter() - start) * 1e3
        return result

    def deform(
        self,
        result: RegistrationResult,
        source_mm: np.ndarray,
        target_mm: np.ndarray,
        source_triangles: np.ndarray | None = None,
        source_fiducials_mm: np.ndarray | None = None,
        target_fiducials_mm: np.ndarray | None = None,
        *,
        mesh_vertices_mm: np.ndarray | None = None,
        view: str = "frame",
    ) -> RegistrationResult:
        """The non-rigid stage from `result`'s rigid pose: sets `result.deformation` (applied or why not) and,
        with fiducials and the stage applied, `deformed_rms_tre_mm`. The rigid pose in `result` is left as it is. The node calls
        this after publishing the rigid pose; `register` calls it when `deform` is on. `view`: what `target_mm` is,
        "frame" (one view) or "survey" (survey mode's fused surface): it picks the deformed bound's calibration.

        The closed preop surface is `source_triangles` over the source points, or over `mesh_vertices_mm`
        when those are given (a CT mesh beside a sampled cloud); without triangles it is rebuilt from the points.
        Vertices with NaN/inf coordinates are dropped with the triangles that use them (a warning says how many).
        """
        start = time.perf_counter()
        source = clean_points(source_mm, "source", min_points=self.config.min_points)
        target = clean_points(target_mm, "target", min_points=1)
        preop = _preop_surface(source_mm, source, source_triangles, mesh_vertices_mm)
        fid_s, fid_t = _check_fiducials(source_fiducials_mm, target_fiducials_mm)  # bad ones refused before any work
        return self._deform(result, source, target, preop, fid_s, fid_t, view, start=start)

    def _deform(
        self,
        result: RegistrationResult,
        source: np.ndarray,
        target: np.ndarray,
        preop: tuple[np.ndarray | None, np.ndarray | None],
        fid_s: np.ndarray | None,
        fid_t: np.ndarray | None,
        view: str,
        *,
        start: float,
    ) -> RegistrationResult:
        """`deform` on checked inputs: `preop` is `_preop_surface`'s (mesh vertices or None, triangles or None)."""
        from liver_p2p_reg.registration.deform import deform_result
        from liver_p2p_reg.registration.error_calibration import attach_deformed_error_model

        surface, tris, fit = _stage_surface(source, preop)
        result.deformation = deform_result(result, surface, target, self.config, self.cache, tris, fit)
        attach_deformed_error_model(result, self.config, view)  # the bound of the deformed positions, when applied
        result.runtime_ms["deform"] = (time.perf_counter() - start) * 1e3
        # a stage not applied moved nothing: the rigid rms_tre_mm is the error (replay counts only applied frames)
        if fid_s is not None and fid_t is not None and result.deformation.applied:
            moved = result.deformation.deformed_position_mm(fid_s)
            result.deformed_rms_tre_mm = float(np.sqrt(np.mean(np.sum((moved - fid_t) ** 2, axis=1))))
        return result

    def warm_up(
        self,
        source_mm: np.ndarray,
        method: str | None = None,
        *,
        source_triangles: np.ndarray | None = None,
        mesh_vertices_mm: np.ndarray | None = None,
        elastic: bool = True,
    ) -> float:
        """Compute everything the method caches about a new source (its preprocessing, source
        features, model weights, ICP index) before the first real target arrives; returns ms.

        It registers the source to a fixed partial view of itself through the normal code path,
        so no method needs a hook of its own; the result is discarded and errors are ignored
        (the first real registration reports them). The elastic model of the given surface is built too with
        `deform`, or with the contenders' judge unless `elastic` is False (a stand-in shape's warm-up).
        """
        start = time.perf_counter()
        try:
            source = clean_points(source_mm, "source", min_points=self.config.min_points)
            centre = source[np.argmax(source[:, 0])]  # a deterministic cap of the surface
            count = len(source) // 3
            small = [
                t for t in (self.config.ransac_candidate_visibility, self.config.surface_search_visibility) if t > 0
            ]
            if check_method_name(method or self.config.method).ransac_candidate and small:
                # a cap small enough for RANSAC's pose and the surface search too: Open3D's first use, the source's
                # FPFH and the search's distance field are paid here, not by the first small view (M/N, a voxel
                # share, follows the point share of a cap)
                # (never below min_points: register refuses a smaller cap, and nothing at all would be warmed)
                count = max(min(count, int(len(source) * min(small) / 2)), self.config.min_points)
            near = np.argsort(np.linalg.norm(source - centre, axis=1))[: max(count, 3)]
            # the cap warms the rigid path; a judge there would build a model of no given surface (built below instead)
            capped = (
                Registrar(self.config.replace(contender_judge_ratio=0.0)) if self.config.contender_judge_ratio else self
            )
            capped.cache = self.cache
            capped.register(source, source[near], method=method)
            if self.config.deform or (elastic and _judges(self.config, method or self.config.method)):
                # the elastic model (seconds) is built here, not on the first frame
                self.prepare_deformation(source_mm, source_triangles, mesh_vertices_mm=mesh_vertices_mm)
        except LiverP2PError:
            pass
        return (time.perf_counter() - start) * 1e3

    def prepare_deformation(
        self,
        source_mm: np.ndarray,
        source_triangles: np.ndarray | None = None,
        *,
        mesh_vertices_mm: np.ndarray | None = None,
    ) -> str:
        """Build (and cache) the preop model's elastic model; "" when ready, else why the stage cannot run."""
        from liver_p2p_reg.registration.deform import elastic_model

        if mesh_vertices_mm is None:
            source = clean_points(source_mm, "preop model", min_points=4)
        else:
            source = clean_points(source_mm, "source", min_points=self.config.min_points)
        surface, tris, fit = _stage_surface(
            source, _preop_surface(source_mm, source, source_triangles, mesh_vertices_mm)
        )
        try:
            elastic_model(self.cache, surface, tris, self.config, fit)
        except LiverP2PError as exc:
            return f"no elastic model: {exc}"
        return ""


def register(
    source_mm: np.ndarray, target_mm: np.ndarray, method: str | None = None, **kwargs: Any
) -> RegistrationResult:
    """One-call convenience: `register(source_mm, target_mm, method="fpfh-p2p", k=5)`."""
    fiducials = {k: kwargs.pop(k) for k in ("source_fiducials_mm", "target_fiducials_mm") if k in kwargs}
    return Registrar(**kwargs).register(source_mm, target_mm, method=method, **fiducials)


def _preop_surface(
    source_mm: np.ndarray,
    source: np.ndarray,
    triangles: np.ndarray | None,
    mesh_vertices_mm: np.ndarray | None,
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The non-rigid stage's closed surface: (the cleaned mesh vertices, or None for the source `source` cleaned from
    `source_mm`; its triangles, or None). Triangles are refused in one line when they are no (F, 3) integer array
    of the given points; vertices with NaN/inf coordinates are dropped with the triangles that use them."""
    if mesh_vertices_mm is None:
        given = as_float_array(source_mm, "source")  # an (N, 3) array: clean_points made `source` of it
        tris = _check_triangles(triangles, len(given))
        if tris is not None and len(source) < len(given):  # clean_points dropped rows (and warned): re-index
            tris = _without_nonfinite(given, tris, "source")
        return None, tris
    vertices = as_float_array(mesh_vertices_mm, "preop mesh")
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise InputError(f"preop mesh: expected an (N, 3) array of points, got shape {vertices.shape}")
    tris = _check_triangles(triangles, len(vertices))
    if tris is not None:
        vertices, tris = finite_mesh(vertices, tris, "preop mesh")  # one warning for its vertices and triangles
    return clean_points(vertices, "preop mesh", min_points=4), tris if tris is None or len(tris) else None


def _judges(config: Config, method: str) -> bool:
    """Whether the contenders' judge can run for `method` (contenders.py): on, a method screening RANSAC's pose on
    small views, and a threshold above 0; only then is the elastic model's surface checked and built for it."""
    row = check_method_name(method)
    return config.contender_judge_ratio > 0 and row.ransac_candidate and config.ransac_candidate_visibility > 0


def _stage_surface(
    source: np.ndarray, preop: tuple[np.ndarray | None, np.ndarray | None]
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The elastic model's (surface points, triangles, fit points) from `_preop_surface`'s pair: the source itself,
    or beside a mesh its vertices, fitted through the registered cloud (denser than a decimated mesh's vertices)."""
    mesh_vertices, tris = preop
    return (source, tris, None) if mesh_vertices is None else (mesh_vertices, tris, source)


def _without_nonfinite(points: np.ndarray, tris: np.ndarray, name: str) -> np.ndarray | None:
    """`tris` without those using a non-finite point, re-indexed to the points left (None when none is left);
    cloud_io.finite_mesh's re-indexing, with a line of its own (clean_points has named the points already)."""
    reindexed = finite_mesh(points, tris, name, warn=False)[1]
    LOG.warning(
        "%s: dropped the %d of %d triangles using its NaN/inf points", name, len(tris) - len(reindexed), len(tris)
    )
    return reindexed if len(reindexed) else None


def _check_triangles(triangles: np.ndarray | None, n_points: int) -> np.ndarray | None:
    """Preop triangles as (F, 3) int64 indices into the `n_points` given points, or None; refused when they cannot be."""
    if triangles is None:
        return None
    tris = np.asarray(triangles)
    if tris.size == 0:
        return None
    if tris.ndim != 2 or tris.shape[1] != 3 or tris.dtype.kind not in "iu":
        raise InputError(f"source triangles must be an (F, 3) integer array, got shape {tris.shape} {tris.dtype}")
    if tris.min() < 0 or tris.max() >= n_points:
        raise InputError(f"source triangles index {int(tris.max())}, but the source has {n_points} points")
    return tris.astype(np.int64)


# A prior pose's translation or a sensor origin beyond this (1 km) is no surgical scene: refused.
MAX_POSITION_MM = 1e6


def _check_pose(T: np.ndarray | None) -> np.ndarray | None:
    if T is None:
        return None
    T = as_float_array(T, "initial_T_mm")
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError(f"initial_T_mm must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InputError("initial_T_mm must be a rigid transform (its 3x3 block is not a rotation)")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):  # a projective matrix moves points non-rigidly
        raise InputError(f"initial_T_mm must be a rigid transform (its bottom row is {T[3].tolist()}, not 0 0 0 1)")
    with np.errstate(over="ignore"):  # 1e300 squared: inf, refused below
        shift = float(np.linalg.norm(T[:3, 3]))
    if shift > MAX_POSITION_MM:  # an organ a kilometre away: wrong units or frame (and overflow further on)
        raise InputError(
            f"initial_T_mm moves the organ {shift:.3g} mm (more than {MAX_POSITION_MM:g} mm): wrong units?"
        )
    return T


def _check_origin(origin: np.ndarray | None) -> np.ndarray | None:
    if origin is None:
        return None
    origin = as_float_array(origin, "sensor origin").reshape(-1)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise InputError(f"the sensor origin must be 3 finite numbers (mm, target frame), got {origin.tolist()}")
    with np.errstate(over="ignore"):
        far = float(np.linalg.norm(origin)) > MAX_POSITION_MM
    if far:
        raise InputError(f"the sensor origin {origin.tolist()} is more than {MAX_POSITION_MM:g} mm away: wrong units?")
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
