"""Plot a training run's CSV log: smoothed loss and the validation RMS-TRE against the step.

.venv/bin/python scripts/plot_training.py docs/training/matcher_v1_log.csv docs/training/matcher_v1_curve.png
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def read_log(path: Path) -> dict[str, np.ndarray]:
    """Columns of the log as float arrays (empty cells -> NaN); a resumed run's repeated steps keep the last."""
    with path.open() as fh:
        rows = list(csv.DictReader(fh))
    by_step = {int(r["step"]): r for r in rows}  # later rows (after a resume) win
    steps = sorted(by_step)
    cols = {key: np.array([float(by_step[s][key] or "nan") for s in steps]) for key in rows[0] if key != "step"}
    cols["step"] = np.array(steps, dtype=float)
    return cols


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("png", type=Path)
    args = parser.parse_args()
    log = read_log(args.log)
    fig, (ax_loss, ax_val) = plt.subplots(1, 2, figsize=(10, 3.6))
    window = 25
    kernel = np.ones(window) / window
    smooth = np.convolve(log["loss"], kernel, mode="valid")
    ax_loss.plot(log["step"], log["loss"], color="0.8", lw=0.6, label="loss")
    ax_loss.plot(log["step"][window - 1 :], smooth, color="C0", label=f"mean of {window} logs")
    ax_loss.set(xlabel="step", ylabel="training loss", title="matching + overlap loss")
    ax_loss.legend()
    val = ~np.isnan(log["val_learned_p2p_mm"])
    for key, label in (
        ("val_learned_mm", "learned"),
        ("val_learned_p2p_mm", "learned-p2p"),
        ("val_low_vis_p2p_mm", "learned-p2p, visibility < 0.35"),
    ):
        ax_val.plot(log["step"][val], log[key][val], marker="o", label=label)
    ax_val.set(xlabel="step", ylabel="mean RMS-TRE (mm)", title="validation (held-out livers)")
    ax_val.legend()
    fig.tight_layout()
    args.png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.png, dpi=120)
    print(f"wrote {args.png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
