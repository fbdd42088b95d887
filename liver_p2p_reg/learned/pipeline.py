"""The `learned`, `learned-p2p` and `learned-p2p-icp` registration methods."""

from __future__ import annotations

import numpy as np

from ..config import Config
from ..pipelines import run_feature_pipeline
from ..registrar import MethodContext, method
from ..result import RegistrationResult
from .provider import LearnedProvider


def _provider(config: Config, ctx: MethodContext) -> LearnedProvider:
    """One loaded network per (weights, device), kept in the Registrar's cache."""
    key = f"learned_provider:{config.weights_path}:{config.device}"
    provider = ctx.cache.get(key)
    if provider is None:
        provider = ctx.cache[key] = LearnedProvider(weights_path=config.weights_path, device=config.device)
    return provider


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
