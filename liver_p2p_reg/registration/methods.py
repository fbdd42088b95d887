"""The table of registration methods: each name is a feature provider plus pipeline options, or a function.

`Registrar.register` looks a name up here once and calls `run_method`, which calls the pipeline
(`pipeline.py`) directly. The table imports nothing heavy: the command line checks a name, and
`liver-p2p --help` lists them, before scipy, torch or Open3D are loaded.

Adding a method: a row in METHODS below (a new combination of features, P2P, estimator and ICP),
or, for code outside the package (a plug-in, a test), `add_method(name, Method(run=fn, doc=...))`
with `fn(source_mm, target_mm, config, ctx) -> RegistrationResult`, and `remove_method(name)`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from liver_p2p_reg.errors import InputError

if TYPE_CHECKING:
    import numpy as np

    from liver_p2p_reg.config import Config
    from liver_p2p_reg.registration.context import MethodContext
    from liver_p2p_reg.result import RegistrationResult

    MethodFn = Callable[[np.ndarray, np.ndarray, Config, MethodContext], RegistrationResult]


@dataclass(frozen=True)
class Method:
    """One row: which pipeline runs, with which features or estimator, and whether P2P and ICP follow."""

    doc: str
    features: str = ""  # "fpfh" | "learned": the feature pipeline (matching [-> P2P] [-> ICP])
    estimate: str = ""  # "ransac" | "fgr" | "icp": one global estimate [-> ICP]
    prior: bool = False  # starts from ctx.initial_T_mm ([-> ICP]: `track`; as given: `evaluate`)
    oracle: bool = False  # the ground-truth fiducials' Procrustes fit
    p2p: bool = False
    refine: bool = False  # the final trimmed point-to-plane ICP
    ransac_candidate: bool = False  # feature pipelines: FPFH + RANSAC's pose joins the screened candidates
    run: MethodFn | None = None  # a plug-in's own function instead of the pipeline
    same_as: str = ""  # another name of that row's method (an error-bound calibration of either holds for both)


METHODS: dict[str, Method] = {
    "fpfh": Method("FPFH features, complete-to-partial dual-softmax matching only.", features="fpfh"),
    "fpfh-p2p": Method("FPFH features + the P2P module.", features="fpfh", p2p=True),
    "fpfh-p2p-icp": Method("FPFH + P2P, then trimmed point-to-plane ICP.", features="fpfh", p2p=True, refine=True),
    "learned": Method("Learned matcher, complete-to-partial dual-softmax matching only.", features="learned"),
    "learned-p2p": Method("Learned matcher + the P2P module (the paper's pipeline).", features="learned", p2p=True),
    "learned-p2p-icp": Method(
        "Learned matcher + P2P, with FPFH + RANSAC's pose screened beside P2P's candidates on views below "
        "ransac_candidate_visibility, then trimmed point-to-plane ICP (the default).",
        features="learned",
        p2p=True,
        refine=True,
        ransac_candidate=True,
    ),
    # The name the RANSAC candidate had while it was an opt-in: kept so that recorded commands and selections run.
    "learned-p2p-ransac-icp": Method(
        "The same as learned-p2p-icp (its name while the RANSAC candidate was opt-in).",
        features="learned",
        p2p=True,
        refine=True,
        ransac_candidate=True,
        same_as="learned-p2p-icp",
    ),
    "fpfh-ransac": Method("Open3D FPFH + RANSAC (max correspondence distance 0.05 normalized).", estimate="ransac"),
    "fpfh-ransac-icp": Method("FPFH + RANSAC, then trimmed point-to-plane ICP.", estimate="ransac", refine=True),
    "fgr": Method("Open3D Fast Global Registration on FPFH matches.", estimate="fgr"),
    "icp": Method("Point-to-plane ICP from identity (centroids aligned by the preprocessing).", estimate="icp"),
    "track": Method("Trimmed point-to-plane ICP from a prior pose (the previous frame's).", prior=True, refine=True),
    "evaluate": Method(
        "A given pose as is (no search, no ICP): its residual, uncertainty, free space, TRE.", prior=True
    ),
    "procrustes": Method(
        "Oracle: least-squares rigid fit of the ground-truth fiducials (lower bound of rigid error).", oracle=True
    ),
}
_BUILT_IN = frozenset(METHODS)


def method_names() -> list[str]:
    """The methods' names, sorted (nothing heavy is imported)."""
    return sorted(METHODS)


def check_method_name(name: str) -> Method:
    """The table's row for `name`; an InputError listing the choices when there is none."""
    row = METHODS.get(name)
    if row is None:
        raise InputError(f"unknown method {name!r}; choose one of: {', '.join(method_names())}")
    return row


def canonical_method(name: str) -> str:
    """The name `name` is another name of (`Method.same_as`), else `name` itself (unknown names too)."""
    row = METHODS.get(name)
    return row.same_as if row is not None and row.same_as else name


def add_method(name: str, method: Method) -> None:
    """Add a method to the table (a plug-in's `Method(run=fn)`); a built-in name cannot be replaced."""
    if name in _BUILT_IN:
        raise InputError(f"method {name!r} is built in and cannot be replaced")
    if method.run is None:
        raise InputError(f"method {name!r}: a plug-in method needs `run`")
    METHODS[name] = method


def remove_method(name: str) -> None:
    """Remove a method added with `add_method` (built-in ones stay)."""
    if name not in _BUILT_IN:
        METHODS.pop(name, None)


def run_method(
    name: str, source_mm: np.ndarray, target_mm: np.ndarray, config: Config, ctx: MethodContext
) -> RegistrationResult:
    """Register with the method `name`: its row's pipeline, called directly."""
    row = check_method_name(name)
    if row.run is not None:
        return row.run(source_mm, target_mm, config, ctx)
    # The pipeline imports scipy (and, for features, torch when it runs): not with the table.
    from liver_p2p_reg.registration import pipeline

    if row.features:
        return pipeline.run_feature_pipeline(
            source_mm,
            target_mm,
            config,
            ctx,
            row.features,
            use_p2p=row.p2p,
            refine=row.refine,
            ransac_candidate=row.ransac_candidate,
        )
    if row.estimate:
        return pipeline.run_global_pipeline(source_mm, target_mm, config, ctx, row.estimate, refine=row.refine)
    if row.prior:
        return pipeline.run_from_prior(source_mm, target_mm, config, ctx, name, refine=row.refine)
    if row.oracle:
        return pipeline.run_oracle(source_mm, target_mm, config, ctx)
    raise InputError(f"method {name!r} has no pipeline")  # a row of none of the kinds: a bug in the table
