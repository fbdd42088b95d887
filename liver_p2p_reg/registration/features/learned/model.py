"""The matcher network: invariant point features -> node self/cross attention with distance bias -> descriptors."""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from liver_p2p_reg.config_io import quoted
from liver_p2p_reg.registration.features.learned.descriptors import NUM_FEATURES


@dataclass(frozen=True)
class ModelConfig:
    """Architecture hyper-parameters (stored with the weights so a checkpoint rebuilds its net)."""

    in_dim: int = NUM_FEATURES
    width: int = 64
    heads: int = 4
    layers: int = 3
    out_dim: int = 48
    distance_bins: int = 32  # piecewise-linear attention bias over node distance
    distance_max_norm: float = 2.0  # pairwise node distances live in [0, 2] in the unit sphere
    points_per_node: int = 8
    max_nodes: int = 256

    def to_dict(self) -> dict:
        return asdict(self)


# [low, high] of each architecture field a weights file's metadata or a training config may give: generous (the
# bundled net is 64 wide, 3 layers, 256 nodes) but bounded, so a typo builds no net of gigabytes (layers 100000
# did) and a zero or negative count is refused, not divided by or silently raised to 4 nodes.
MODEL_LIMITS: dict[str, tuple[float, float]] = {
    "in_dim": (NUM_FEATURES, NUM_FEATURES),  # the descriptors give this many features per point
    "width": (1, 4096),
    "heads": (1, 64),
    "layers": (1, 64),
    "out_dim": (1, 4096),
    "distance_bins": (1, 4096),
    "distance_max_norm": (0, 100),  # (low, high]: a distance, finite and positive
    "points_per_node": (1, 100_000),
    "max_nodes": (4, 16_384),  # _nodes takes at least 4; attention costs nodes^2
}


def model_config_from(values: Any, prefix: str = "") -> ModelConfig:
    """A ModelConfig from a mapping of its fields (the others default), each of its type and within MODEL_LIMITS.

    ValueError with one line otherwise; `prefix` goes before the field names in it ("model.")."""
    if not isinstance(values, dict):
        raise ValueError(f"must be a mapping of the architecture's fields, got {quoted(values)}")
    known = {f.name for f in fields(ModelConfig)}
    unknown = sorted(map(str, set(values) - known))
    if unknown:
        raise ValueError(f"unknown keys: {', '.join(quoted(name) for name in unknown[:5])}")
    for name, value in values.items():
        low, high = MODEL_LIMITS[name]
        if name == "distance_max_norm":
            number = isinstance(value, (int, float)) and not isinstance(value, bool)
            if not (number and math.isfinite(value) and low < value <= high):
                raise ValueError(f"{prefix}{name} must be a finite number in ({low:g}, {high:g}], got {quoted(value)}")
        elif not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
            wanted = f"{low} (the descriptors' features per point)" if low == high else f"an integer in [{low}, {high}]"
            raise ValueError(f"{prefix}{name} must be {wanted}, got {quoted(value)}")
    cfg = ModelConfig(**values)
    if cfg.width % cfg.heads:  # each head takes width / heads channels
        raise ValueError(f"{prefix}width ({cfg.width}) must be a multiple of {prefix}heads ({cfg.heads})")
    return cfg


def mlp(sizes: list[int]) -> nn.Sequential:
    """Linear + LayerNorm + GELU stack; the last layer is plain linear."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers += [nn.LayerNorm(sizes[i + 1]), nn.GELU()]
    return nn.Sequential(*layers)


def farthest_points(points: torch.Tensor, k: int) -> torch.Tensor:
    """k indices by farthest point sampling from index 0 (invariant: uses distances only).

    Runs in NumPy float64 on the CPU: the loop is sequential and tiny per step, where torch's
    per-op overhead (or a GPU sync per step) would dominate. The coordinates are kept as three
    contiguous columns and each step writes into fixed buffers: the same squared distances bit
    for bit as ((p - q) ** 2).sum(axis=1), which adds x, y, z in that order, at a quarter of the time.
    """
    pts = points.detach().to("cpu", torch.float64).numpy()
    k = min(k, len(pts))
    chosen = np.zeros(k, dtype=np.int64)
    columns = [np.ascontiguousarray(pts[:, axis]) for axis in range(3)]
    diff, square = np.empty(len(pts)), np.empty(len(pts))

    def squared_distances(index: int, out: np.ndarray) -> np.ndarray:
        for axis, column in enumerate(columns):
            np.subtract(column, column[index], out=diff)
            if axis == 0:
                np.multiply(diff, diff, out=out)
            else:
                np.add(out, np.multiply(diff, diff, out=square), out=out)
        return out

    dist = squared_distances(0, np.empty(len(pts)))
    step = np.empty(len(pts))
    for i in range(1, k):
        nxt = int(np.argmax(dist))
        chosen[i] = nxt
        np.minimum(dist, squared_distances(nxt, step), out=dist)
    return torch.from_numpy(chosen).to(points.device)


class Attention(nn.Module):
    """Multi-head attention with an optional additive per-head bias (pre-norm residual block + FFN)."""

    def __init__(self, width: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.norm_q = nn.LayerNorm(width)
        self.norm_kv = nn.LayerNorm(width)
        self.q = nn.Linear(width, width)
        self.kv = nn.Linear(width, 2 * width)
        self.out = nn.Linear(width, width)
        self.ffn = nn.Sequential(
            nn.LayerNorm(width), nn.Linear(width, 2 * width), nn.GELU(), nn.Linear(2 * width, width)
        )

    def forward(self, x: torch.Tensor, ctx: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
        n, w = x.shape
        h = self.heads
        q = self.q(self.norm_q(x)).view(n, h, w // h).transpose(0, 1)
        k, v = self.kv(self.norm_kv(ctx)).view(ctx.shape[0], 2, h, w // h).permute(1, 2, 0, 3)
        att = F.scaled_dot_product_attention(q[None], k[None], v[None], attn_mask=None if bias is None else bias[None])
        x = x + self.out(att[0].transpose(0, 1).reshape(n, w))
        return x + self.ffn(x)


class MatcherNet(nn.Module):
    """Per-point descriptors for a (source, target) pair; invariant because only invariant
    features and pairwise distances enter (no coordinates)."""

    def __init__(self, cfg: ModelConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg = cfg or ModelConfig()
        self.embed = mlp([cfg.in_dim, cfg.width, cfg.width])
        # Learned attention bias per layer and head as a function of distance only (GeoTransformer-like).
        self.distance_bias = nn.Parameter(torch.zeros(cfg.layers, cfg.distance_bins + 1, cfg.heads))
        self.self_att = nn.ModuleList(Attention(cfg.width, cfg.heads) for _ in range(cfg.layers))
        self.cross_att = nn.ModuleList(Attention(cfg.width, cfg.heads) for _ in range(cfg.layers))
        self.head = mlp([2 * cfg.width, cfg.width, cfg.out_dim])
        self.overlap = mlp([2 * cfg.width, cfg.width, 1])

    def _nodes(self, points: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """FPS nodes, point embeddings max-pooled onto their nearest node.

        Geometry runs in float64 so FPS picks and nearest-node ties do not flip under a
        rotation. Returns point->node distances (N, n), node feats (n, w), node distances (n, n).
        """
        cfg = self.cfg
        pts = points.double()
        n_nodes = max(4, min(cfg.max_nodes, points.shape[0] // cfg.points_per_node))
        nodes = pts[farthest_points(pts, n_nodes)]
        d_point_node = torch.cdist(pts, nodes)
        owner = d_point_node.argmin(dim=1)
        pooled = torch.full((n_nodes, h.shape[1]), -1e4, dtype=h.dtype, device=h.device)
        if torch.is_grad_enabled():  # training: the reduction its gradients were always taken through
            pooled = pooled.scatter_reduce(0, owner[:, None].expand_as(h), h, reduce="amax", include_self=True)
        else:  # inference: the same maxima (exact), ~80x faster on CPU than the expanded scatter
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # "index_reduce() is in beta"
                pooled = pooled.index_reduce_(0, owner, h, "amax", include_self=True)
        return d_point_node, pooled, torch.cdist(nodes, nodes).to(h.dtype)

    def _biases(self, dist: torch.Tensor) -> list[torch.Tensor]:
        """Per-layer (heads, n, n) attention bias: linear interpolation in a learned distance table."""
        cfg = self.cfg
        pos = (dist / cfg.distance_max_norm * cfg.distance_bins).clamp(0, cfg.distance_bins - 1e-4)
        lo = pos.floor().long()
        frac = (pos - lo)[..., None]
        # One gather for all layers and heads: (bins + 1, layers * heads).
        table = self.distance_bias.permute(1, 0, 2).reshape(cfg.distance_bins + 1, -1)
        bias = table[lo] * (1 - frac) + table[lo + 1] * frac  # (n, n, layers * heads)
        bias = bias.view(*dist.shape, cfg.layers, cfg.heads).permute(2, 3, 0, 1)
        return [b.contiguous() for b in bias]

    @staticmethod
    def _interpolation(d_point_node: torch.Tensor, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """Each point's 3 nearest nodes and their normalized inverse-distance weights: (N, 3) indices, (N, 3)."""
        k = min(3, d_point_node.shape[1])
        dk, ik = d_point_node.topk(k, dim=1, largest=False)
        w = (1.0 / (dk + 1e-3)).to(dtype)
        return ik, w / w.sum(dim=1, keepdim=True)

    @staticmethod
    def _to_points(interpolation: tuple[torch.Tensor, torch.Tensor], node_feat: torch.Tensor) -> torch.Tensor:
        """Inverse-distance interpolation of node context from the 3 nearest nodes."""
        ik, w = interpolation
        return (node_feat[ik] * w[..., None]).sum(dim=1)

    def encode(self, points: torch.Tensor, features: torch.Tensor) -> tuple:
        """One cloud's own part, before any attention: point embeddings, each point's interpolation
        from its nearest nodes, node features and per-layer attention biases. Depends on that cloud
        only, so a fixed source can be encoded once and passed to `forward` as `source_context`."""
        h = self.embed(features)
        d_point_node, nodes, d_nodes = self._nodes(points, h)
        return h, self._interpolation(d_point_node, nodes.dtype), nodes, self._biases(d_nodes)

    def forward(
        self,
        src: torch.Tensor,
        tgt: torch.Tensor,
        f_src: torch.Tensor,
        f_tgt: torch.Tensor,
        with_overlap: bool = False,
        source_context: tuple | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """src (N,3), tgt (M,3), invariant features -> x_S (N,d), x_T (M,d) normalized
        [, overlap logits (N,), (M,) when `with_overlap` (training only)].
        `source_context`: `encode(src, f_src)` computed earlier (inference on a fixed source)."""
        hs, interp_s, gs, bs = source_context if source_context is not None else self.encode(src, f_src)
        ht, interp_t, gt, bt = self.encode(tgt, f_tgt)
        for i in range(self.cfg.layers):
            gs = self.self_att[i](gs, gs, bs[i])
            gt = self.self_att[i](gt, gt, bt[i])
            gs, gt = self.cross_att[i](gs, gt), self.cross_att[i](gt, gs)
        cs = torch.cat([hs, self._to_points(interp_s, gs)], dim=1)
        ct = torch.cat([ht, self._to_points(interp_t, gt)], dim=1)
        xs = F.normalize(self.head(cs), dim=1)
        xt = F.normalize(self.head(ct), dim=1)
        if not with_overlap:
            return xs, xt, None, None
        return xs, xt, self.overlap(cs)[:, 0], self.overlap(ct)[:, 0]
