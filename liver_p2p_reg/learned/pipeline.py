"""The `learned`, `learned-p2p` and `learned-p2p-icp` registration methods."""

from __future__ import annotations

import numpy as np

from ..config import Config
from ..pipelines import run_feature_pipeline
from ..registrar import MethodContext, method, remember_latest
from ..result import RegistrationResult
from .prepared import signature_mismatch, source_signature
from .provider import LearnedProvider


def _provider(config: Config, ctx: MethodContext, weights_path: str | None = None) -> LearnedProvider:
    """One loaded network per (weights, device), kept in the Registrar's cache."""
    weights_path = config.weights_path if weights_path is None else weights_path
    key = f"learned_provider:{weights_path}:{config.device}"
    provider = ctx.cache.get(key)
    if provider is None:
        provider = ctx.cache[key] = LearnedProvider(weights_path=weights_path, device=config.device)
    return provider


def _run(
    source_mm: np.ndarray, target_mm: np.ndarray, config: Config, ctx: MethodContext, use_p2p: bool, refine: bool
) -> RegistrationResult:
    """The feature pipeline with the configured weights; prepared weights only for their own liver."""
    provider = _provider(config, ctx)
    warning = ""
    if provider.prepared is not None:
        actual = remember_latest(ctx.cache, "source-signature", source_mm, (), lambda: source_signature(source_mm))
        mismatch = signature_mismatch(provider.prepared.signature, actual)
        if mismatch:
            name = provider.prepared.card.get("mesh_name", config.weights_path)
            warning = (
                f"prepared weights {config.weights_path} were made for another liver ({name}: {mismatch}); "
                "general weights used"
            )
            provider = _provider(config, ctx, weights_path="")
    result = run_feature_pipeline(source_mm, target_mm, config, ctx, provider, use_p2p=use_p2p, refine=refine)
    if warning:
        result.warnings.append(warning)
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
