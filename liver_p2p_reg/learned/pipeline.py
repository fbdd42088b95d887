"""The `learned`, `learned-p2p` and `learned-p2p-icp` registration methods."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from ..config import Config
from ..pipelines import run_feature_pipeline
from ..registrar import MethodContext, method, remember_latest
from ..result import RegistrationResult

if TYPE_CHECKING:
    from .provider import LearnedProvider


def _cached_provider(config: Config, ctx: MethodContext, weights_path: str) -> LearnedProvider:
    """One provider per (weights, device) in the Registrar's cache."""
    from .provider import LearnedProvider

    key = f"learned_provider:{weights_path}:{config.device}"
    provider = ctx.cache.get(key)
    if provider is None:
        provider = ctx.cache[key] = LearnedProvider(weights_path=weights_path, device=config.device)
    return provider


def _provider(config: Config, ctx: MethodContext, source_mm: np.ndarray, warnings: list[str]) -> Callable:
    """Makes the provider; the pipeline calls it once the inputs are checked, so torch and the
    weights load only for a valid registration. Prepared weights serve only their own liver:
    for another one the general weights are used and `warnings` says why."""

    def make() -> LearnedProvider:
        from .prepared import signature_mismatch, source_signature

        provider = _cached_provider(config, ctx, config.weights_path)
        if provider.prepared is None:
            return provider
        actual = remember_latest(ctx.cache, "source-signature", source_mm, (), lambda: source_signature(source_mm))
        mismatch = signature_mismatch(provider.prepared.signature, actual)
        if not mismatch:
            return provider
        name = provider.prepared.card.get("mesh_name", config.weights_path)
        warnings.append(
            f"prepared weights {config.weights_path} were made for another liver ({name}: {mismatch}); "
            "general weights used"
        )
        return _cached_provider(config, ctx, "")

    return make


def _run(
    source_mm: np.ndarray, target_mm: np.ndarray, config: Config, ctx: MethodContext, use_p2p: bool, refine: bool
) -> RegistrationResult:
    warnings: list[str] = []
    provider = _provider(config, ctx, source_mm, warnings)
    result = run_feature_pipeline(source_mm, target_mm, config, ctx, provider, use_p2p=use_p2p, refine=refine)
    result.warnings += warnings
    return result


@method("learned")
def learned(source_mm: np.ndarray, target_mm: np.ndarray, config: Config, ctx: MethodContext) -> RegistrationResult:
    """Learned matcher, complete-to-partial dual-softmax matching only."""
    return _run(source_mm, target_mm, config, ctx, use_p2p=False, refine=False)


@method("learned-p2p")
def learned_p2p(source_mm: np.ndarray, target_mm: np.ndarray, config: Config, ctx: MethodContext) -> RegistrationResult:
    """Learned matcher + the P2P module (the default pipeline)."""
    return _run(source_mm, target_mm, config, ctx, use_p2p=True, refine=False)


@method("learned-p2p-icp")
def learned_p2p_icp(
    source_mm: np.ndarray, target_mm: np.ndarray, config: Config, ctx: MethodContext
) -> RegistrationResult:
    """Learned matcher + P2P, then trimmed point-to-plane ICP."""
    return _run(source_mm, target_mm, config, ctx, use_p2p=True, refine=True)
