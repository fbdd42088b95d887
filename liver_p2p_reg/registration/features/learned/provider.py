"""FeatureProvider backed by the learned matcher (source features cached across registrations)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from liver_p2p_reg.config import Config
from liver_p2p_reg.registration.context import remember_latest
from liver_p2p_reg.registration.features.learned.descriptors import local_features
from liver_p2p_reg.registration.features.learned.model import MatcherNet
from liver_p2p_reg.registration.features.learned.patient import read_prepared_source
from liver_p2p_reg.registration.features.learned.weights import BUNDLED_WEIGHTS, load_weights

# Weights loaded in this process, by (file, its size and mtime, device): every Registrar (a
# batch, a replay of several bags, the node after a re-configuration) shares one loaded network.
# Inference never changes it (eval mode, no_grad); a changed file is loaded anew.
_LOADED: dict[tuple, MatcherNet] = {}


def shared_model(weights_path: str = "", device: str = "cpu") -> MatcherNet:
    """The network of these weights on this device, loaded once per process."""
    path = Path(weights_path) if weights_path else BUNDLED_WEIGHTS
    try:
        stat = path.stat()
        key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns, str(device))
    except OSError:
        return load_weights(weights_path or None, device)  # raises its one-line WeightsError
    if key not in _LOADED:
        _LOADED[key] = load_weights(weights_path or None, device)
    return _LOADED[key]


class LearnedProvider:
    """Describes (source, target) jointly with the matcher network."""

    name = "learned"

    def __init__(self, model: MatcherNet | None = None, weights_path: str = "", device: str = "cpu") -> None:
        self.model = model if model is not None else shared_model(weights_path, device)
        self.device = device
        # A patient-prepared file also carries its liver's signature and precomputed source features.
        self.prepared = read_prepared_source(weights_path) if weights_path and model is None else None

    def source_features(self, src: np.ndarray) -> np.ndarray:
        """Input features of the voxelized normalized source: the prepared ones when it is the same cloud."""
        pre = self.prepared
        if pre is not None and pre.vox_norm is not None and pre.vox_norm.shape == src.shape:
            if np.allclose(pre.vox_norm, src, rtol=0.0, atol=1e-9):
                return pre.f_src
        return local_features(src)

    def describe(
        self, source_norm: torch.Tensor, target_norm: torch.Tensor, cache: dict[str, Any]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """source (N,3), target (M,3) normalized -> L2-normalized descriptors (N,d), (M,d)."""
        src = source_norm.detach().to("cpu", torch.float64).numpy()
        dev = source_norm.device

        def encode_source() -> tuple:
            f_src = torch.as_tensor(self.source_features(src), dtype=torch.float32, device=dev)
            with torch.no_grad():
                return f_src, self.model.encode(source_norm.float(), f_src)

        # The preoperative source is fixed across frames: its inputs and its own encoding
        # (embeddings, nodes, attention biases) are computed once per model and weights.
        f_src, context = remember_latest(cache, "learned_src_context", src, (id(self.model), str(dev)), encode_source)
        f_tgt = torch.as_tensor(
            local_features(target_norm.detach().to("cpu", torch.float64).numpy()), dtype=torch.float32, device=dev
        )
        with torch.no_grad():
            xs, xt, _, _ = self.model(source_norm.float(), target_norm.float(), f_src, f_tgt, source_context=context)
        return xs, xt


def features_of(points: np.ndarray) -> torch.Tensor:
    """Invariant input features of one cloud as float32 (convenience for tests/benchmarks)."""
    return torch.as_tensor(local_features(points), dtype=torch.float32)


def _cached_provider(config: Config, cache: dict[str, Any], weights_path: str) -> LearnedProvider:
    """One provider per (weights, device) in the Registrar's cache."""
    key = f"learned_provider:{weights_path}:{config.device}"
    provider = cache.get(key)
    if provider is None:
        provider = cache[key] = LearnedProvider(weights_path=weights_path, device=config.device)
    return provider


def learned_provider(
    config: Config, cache: dict[str, Any], source_mm: np.ndarray, warnings: list[str]
) -> LearnedProvider:
    """The provider of `config.weights_path`, cached. Patient-specific weights serve only their own
    liver: for another one the general weights are used and `warnings` says why."""
    from liver_p2p_reg.registration.features.learned.patient import signature_mismatch, source_signature

    provider = _cached_provider(config, cache, config.weights_path)
    if provider.prepared is None:
        return provider
    actual = remember_latest(cache, "source-signature", source_mm, (), lambda: source_signature(source_mm))
    mismatch = signature_mismatch(provider.prepared.signature, actual)
    if not mismatch:
        return provider
    name = provider.prepared.card.get("mesh_name", "its liver")  # the mesh the file was prepared from
    warnings.append(
        f"prepared weights {config.weights_path} were prepared for another preop surface ({name}: {mismatch}): "
        "another liver, or the same one meshed or sampled otherwise; general weights used"
    )
    return _cached_provider(config, cache, "")
