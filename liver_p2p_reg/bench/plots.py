"""PNG figures of a benchmark run: success rate vs tau (Fig. 7 form), RMS-TRE vs visibility (Fig. 6), K ablation (Fig. 8)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from liver_p2p_reg.bench.cases import BIN_EDGES, BIN_LABELS, PAPER_FIRST_BIN
from liver_p2p_reg.bench.jobs import BOUND, ORACLE
from liver_p2p_reg.bench.stats import METHOD_ORDER, Row, by_bin, main_rows, order_methods, select, success_curve, where
from liver_p2p_reg.plotting import pyplot

TAUS_MM = np.linspace(0.0, 40.0, 81)
# One colour per method, the same in every figure: the oracle black and dashed, the default method
# red and thicker, the others from this list (distinct from both and from each other) by their
# place in METHOD_ORDER, then alphabetically.
OTHER_COLOURS = (
    "tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:gray", "tab:olive",
    "tab:cyan", "navy", "gold", "lime", "teal", "magenta",
)  # fmt: skip


def method_style(method: str, default_method: str | None = None) -> dict:
    """Matplotlib line style of a method: colour, line style and width (see OTHER_COLOURS)."""
    if default_method is None:
        from liver_p2p_reg.config import Config

        default_method = Config().method
    if "[" in method:  # a tagged run of a method ([fs], [prepared]): its method's colour, dotted
        return {**method_style(method.split("[")[0], default_method), "linestyle": ":"}
    if method == ORACLE:
        return {"color": "black", "linestyle": "--", "linewidth": 1.5}
    if method == BOUND:
        return {"color": "dimgray", "linestyle": "-.", "linewidth": 1.5}
    if method == default_method:
        return {"color": "tab:red", "linestyle": "-", "linewidth": 2.5}
    from liver_p2p_reg.registration.methods import method_names

    known = set(METHOD_ORDER) | set(method_names()) | {method}
    others = [m for m in order_methods(known) if m not in (ORACLE, BOUND, default_method)]
    return {"color": OTHER_COLOURS[others.index(method) % len(OTHER_COLOURS)], "linestyle": "-", "linewidth": 1.5}


def _label(method: str, default_method: str | None = None) -> str:
    if default_method is None:
        from liver_p2p_reg.config import Config

        default_method = Config().method
    labels = {ORACLE: f"{ORACLE} (oracle)", BOUND: f"{BOUND} (ICP from the true pose)"}
    return {**labels, default_method: f"{default_method} (default)"}.get(method, method)


def success_vs_tau(rows: list[Row], path: Path) -> Path:
    """Success rate vs threshold tau (0-40 mm): the lowest visibility bin and all cases."""
    plt = pyplot()
    rows = main_rows(rows)
    lo, hi = BIN_EDGES[PAPER_FIRST_BIN], BIN_EDGES[PAPER_FIRST_BIN + 1]
    panels = [
        (f"visibility {BIN_LABELS[PAPER_FIRST_BIN]}", where(rows, lambda r: lo <= r["visibility"] < hi)),
        ("all visibilities", rows),
    ]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, (title, subset) in zip(axes, panels, strict=False):
        for m in order_methods({r["method"] for r in rows}):
            mine = select(subset, method=m)
            if mine:
                ax.plot(TAUS_MM, 100 * success_curve(mine, TAUS_MM), label=_label(m), **method_style(m))
        ax.set_title(title)
        ax.set_xlabel("threshold tau (mm)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success rate (%)")
    axes[1].legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def tre_vs_visibility(rows: list[Row], path: Path) -> Path:
    """Mean RMS-TRE per visibility bin for every method (log scale)."""
    plt = pyplot()
    rows = main_rows(rows)
    centres = [(a + b) / 2 for a, b in zip(BIN_EDGES, BIN_EDGES[1:], strict=False)]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for m in order_methods({r["method"] for r in rows}):
        groups = by_bin(select(rows, method=m))
        means = [float(np.mean(g)) if g.size else np.nan for g in groups]
        ax.plot(centres, means, marker="o", label=_label(m), **method_style(m))
    ax.set_yscale("log")
    # Plain millimetre tick labels (2, 5, 10, 50) read better than 10^x on a log axis.
    from matplotlib.ticker import FormatStrFormatter

    ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.yaxis.set_minor_formatter(FormatStrFormatter("%g"))
    ax.set_xlabel("visibility ratio (bin centre)")
    ax.set_ylabel("mean RMS-TRE (mm)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def k_ablation(curves: dict[str, dict[int, tuple[float, float]]], path: Path) -> Path:
    """Mean RMS-TRE vs K (number of patches) per P2P method: lowest bin and all ablation cases."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for m, per_k in sorted(curves.items()):
        ks = sorted(per_k)
        axes[0].plot(ks, [per_k[k][0] for k in ks], marker="o", label=_label(m), **method_style(m))
        axes[1].plot(ks, [per_k[k][1] for k in ks], marker="o", label=_label(m), **method_style(m))
    for ax, title in zip(axes, (f"visibility {BIN_LABELS[PAPER_FIRST_BIN]}", "all ablation cases"), strict=False):
        ax.set_title(title)
        ax.set_xlabel("K (patch candidates)")
        ax.set_ylabel("mean RMS-TRE (mm)")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
