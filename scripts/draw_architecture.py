"""Draw docs/architecture.png: the way a cloud goes through the package, and the layers of docs/architecture.md.

    .venv/bin/python scripts/draw_architecture.py [--out docs/architecture.png]

The layers are read from the LAYERS block of docs/architecture.md (the list test/test_layers.py checks
against the imports), so the picture shows the same list; the pipeline's stages are drawn as that page's
"The way through" describes them. Deterministic: the same inputs give the same PNG on one machine.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "architecture.md"

ENTRIES = [
    ("files\nPLY STL OBJ PCD NPZ", "cli/\nliver-p2p"),
    ("rosbag2 / MCAP bags", "bags/\nreplay, play"),
    ("live ROS 2 topics", "ros/\nrclpy nodes (thin)"),
]
STAGES = [
    ("preprocess", "normalize, voxelize,\noutlier removal"),
    ("features/", "FPFH or the\nlearned matcher"),
    ("matching", "dual-softmax\nconfidences"),
    ("P2P", "K patch-to-partial\ncandidates + twins"),
    ("screen", "short ICP\nper candidate"),
    ("refine", "trimmed point-\nto-plane ICP"),
    ("confidence", "uncertainty, ambiguity,\nfree space, error bound"),
]
COLOURS = {"input": "#eeeeee", "adapter": "#cfe2f3", "stream": "#d9ead3", "core": "#fff2cc", "result": "#f4cccc"}


def read_layers(doc: Path = DOC) -> list[tuple[str, str]]:
    """(title, modules) of each layer, bottom first, from the LAYERS block."""
    text = doc.read_text()
    block = text[text.index("<!-- LAYERS:START -->") : text.index("<!-- LAYERS:END -->")]
    layers = []
    for line in block.splitlines():
        m = re.match(r"\d+\. (.*?): (.*)$", line.strip())
        if m:
            layers.append((m.group(1), m.group(2).replace("`", "")))
    return layers


def box(ax, x: float, y: float, w: float, h: float, text: str, colour: str, size: float = 8.0, bold: bool = False):
    from matplotlib.patches import FancyBboxPatch

    ax.add_patch(
        FancyBboxPatch((x, y), w, h, boxstyle="round,pad=0.01,rounding_size=0.08", fc=colour, ec="#555555", lw=0.8)
    )
    ax.text(x + w / 2, y + h / 2, text, ha="center", va="center", fontsize=size, weight="bold" if bold else "normal")


def arrow(ax, x0: float, y0: float, x1: float, y1: float) -> None:
    ax.annotate("", xy=(x1, y1), xytext=(x0, y0), arrowprops={"arrowstyle": "->", "color": "#444444", "lw": 0.9})


def draw(out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    matplotlib.rcParams["svg.hashsalt"] = "liver_p2p_reg"
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(15, 7.6))
    ax = fig.add_axes((0.0, 0.0, 0.66, 1.0))
    ax.set_xlim(0, 14)
    ax.set_ylim(0, 10)
    ax.axis("off")
    ax.set_title("A cloud's way through the package", fontsize=12, weight="bold", y=0.96)

    # Inputs and their adapters, side by side at the top.
    for i, (source, adapter) in enumerate(ENTRIES):
        x = 0.6 + i * 4.5
        box(ax, x, 8.3, 3.6, 0.9, source, COLOURS["input"])
        box(ax, x, 6.8, 3.6, 0.9, adapter, COLOURS["adapter"], bold=True)
        arrow(ax, x + 1.8, 8.3, x + 1.8, 7.7)
    box(ax, 5.1, 5.3, 3.6, 0.9, "stream/ (ROS-free)\nintake, tracking, survey, outputs", COLOURS["stream"])
    for i in (1, 2):
        arrow(ax, 0.6 + i * 4.5 + 1.8, 6.8, 6.9, 6.2)
    box(ax, 9.8, 5.3, 3.8, 0.9, "Registrar.register\nregistration/registrar.py", COLOURS["core"], bold=True)
    arrow(ax, 2.4, 6.8, 10.4, 6.2)  # the command line calls the registrar directly
    arrow(ax, 8.7, 5.75, 9.8, 5.75)
    box(ax, 9.8, 3.9, 3.8, 0.9, "methods.py: the table\nname -> features, P2P, ICP", COLOURS["core"])
    arrow(ax, 11.7, 5.3, 11.7, 4.8)

    # The feature pipeline (registration/pipeline.py), left to right, in two rows.
    ax.text(0.6, 3.6, "registration/pipeline.py (a learned or FPFH method)", fontsize=9, style="italic")
    w, gap = 1.66, 0.2
    for i, (name, what) in enumerate(STAGES):
        x = 0.6 + i * (w + gap)
        box(ax, x, 1.9, w, 1.2, f"{name}\n\n{what}", COLOURS["core"], size=7.2)
        if i:
            arrow(ax, x - gap, 2.5, x, 2.5)
    arrow(ax, 11.7, 3.9, 0.6 + w / 2, 3.1)
    box(ax, 0.6, 0.4, 13.0, 0.9, "RegistrationResult: T (source -> target, mm), residual, uncertainty, error bound, status OK / WARN, "
        "per-stage runtime, candidates", COLOURS["result"])  # fmt: skip
    last = 0.6 + (len(STAGES) - 1) * (w + gap) + w / 2
    arrow(ax, last, 1.9, last, 1.3)
    ax.text(0.6, 4.55, "baselines (RANSAC, FGR, ICP), track / evaluate,\nthe oracle: other rows of the same table",
            fontsize=7.5, color="#555555")  # fmt: skip

    # The layers, bottom first, as docs/architecture.md lists them.
    lx = fig.add_axes((0.68, 0.0, 0.31, 1.0))
    lx.set_xlim(0, 10)
    lx.set_ylim(0, 10)
    lx.axis("off")
    lx.set_title("Layers: imports only go down", fontsize=12, weight="bold", y=0.96)
    layers = read_layers()
    h = 8.6 / len(layers)
    for i, (title, modules) in enumerate(layers):
        y = 0.4 + i * h
        colour = COLOURS["core"] if i <= 1 else COLOURS["stream"] if i == 2 else COLOURS["adapter"]
        box(lx, 0.2, y, 9.6, h * 0.86, f"{i + 1}. {title}\n{modules}", colour, size=6.8)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110, metadata={"Software": None})
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "architecture.png")
    args = parser.parse_args(argv)
    draw(args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
