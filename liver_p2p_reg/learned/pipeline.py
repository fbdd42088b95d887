"""The `learned`, `learned-p2p` and `learned-p2p-icp` registration methods."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from ..config import Config
from ..pipelines import run_feature_pipeline
from ..registrar import MethodContext, method
from ..result import RegistrationResult

if TYPE_CHECKING:
    from .provider import LearnedProvider


def _provider(config: Config, ctx: MethodContext) -> Callable[[], LearnedProvider]:
    """Makes the provider, one per (weights, device) in the Registrar's cache; the pipeline calls
    it once the inputs are checked, so torch and the weights load only for a valid registration."""

    def make() -> LearnedProvider:
        from .provider import LearnedProvider

        key = f"learned_provider:{config.weights_path}:{config.device}"
        provider = ctx.cache.get(key)
        if provider is None:
            provider = ctx.cache[key] = LearnedProvider(weights_path=config.weights_path, device=config.device)
        return provider

    return make


@method("learned")
def learned(source_mm: np.ndarray, target_mm: np.ndarray, config: Config, ctx: MethodContext) -> RegistrationResult:
    """Learned matcher, complete-to-partial dual-softmax matching only."""
    return run_feature_pipeline(source_mm, target_mm, config, ctx, _provider(config, ctx), use_p2p=False, refine=False)


@method("learned-p2p")
def learned_p2p(source_mm: np.ndarray, target_mm: np.ndarray, config: Config, ctx: MethodContext) -> RegistrationResult:
    """Learned matcher + the P2P module (the default pipeline)."""
    return run_feature_pipeline(source_mm, target_mm, config, ctx, _provider(config, ctx), use_p2p=True, refine=False)


@method("learned-p2p-icp")
def learned_p2p_icp(
    source_mm: np.ndarray, target_mm: np.ndarray, config: Config, ctx: MethodContext
) -> RegistrationResult:
    """Learned matcher + P2P, then trimmed point-to-plane ICP."""
    return run_feature_pipeline(source_mm, target_mm, config, ctx, _provider(config, ctx), use_p2p=True, refine=True)
