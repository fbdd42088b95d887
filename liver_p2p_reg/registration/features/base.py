"""The feature-provider interface every descriptor (FPFH, learned matcher) implements."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    import torch


class FeatureProvider(Protocol):
    """Describes voxelized, normalized clouds with L2-normalized per-point features."""

    name: str

    def describe(
        self, source_norm: torch.Tensor, target_norm: torch.Tensor, cache: dict[str, Any]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """source (N, 3), target (M, 3) -> x_S (N, d), x_T (M, d), rows L2-normalized.

        Called jointly because a learned matcher attends across clouds. `cache` lives as long
        as the Registrar (e.g. FPFH caches the fixed preoperative source's features there).
        """
        ...
