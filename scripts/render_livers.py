"""Render a grid of generated livers to docs/livers_grid.png (documentation picture)."""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LightSource  # noqa: E402

from liver_p2p_reg.phantom.anatomy import make_liver  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="docs/livers_grid.png")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--count", type=int, default=12)
    parser.add_argument("--elev", type=float, default=25.0, help="view elevation (deg)")
    parser.add_argument("--azim", type=float, default=80.0, help="view azimuth (deg); 90 looks from anterior")
    args = parser.parse_args()
    cols = 4
    rows = int(np.ceil(args.count / cols))
    fig = plt.figure(figsize=(4 * cols, 3.4 * rows), dpi=90)
    light = LightSource(azdeg=315, altdeg=45)
    for i in range(args.count):
        seed = args.first_seed + i
        liver = make_liver(seed)
        v, f = liver.vertices_mm, liver.triangles
        ax = fig.add_subplot(rows, cols, i + 1, projection="3d")
        ax.plot_trisurf(
            v[:, 0], v[:, 1], v[:, 2], triangles=f, color="#b5523b", linewidth=0, shade=True, lightsource=light
        )
        ax.view_init(elev=args.elev, azim=args.azim)
        ax.set_box_aspect(tuple(liver.extents_mm))
        w, d, h = liver.extents_mm
        ax.set_title(f"seed {seed}: {w:.0f} x {d:.0f} x {h:.0f} mm", fontsize=9)
        ax.set_axis_off()
    fig.suptitle("Procedural livers, anterior view (RAS frame: x patient right, y anterior, z superior)")
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
