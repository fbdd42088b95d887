"""The README's operating-point headline: the v2 protocol's four real-anatomy test sets below visibility 0.3.

Usage: .venv/bin/python scripts/protocol_headline.py docs/benchmark_real_test_v2 docs/benchmark_real_test_v2_arap \
    docs/benchmark_real_test_camera_v2 docs/benchmark_real_test_camera_v2_arap --readme README.md \
    [--also METHOD,...] [--block PROTOCOL]

`--also` adds rows for more methods of the runs (an opt-in method judged beside the default), `--block` names
the README block (default PROTOCOL).

Reads each OUT's cases.csv (written by the commands in docs/results/protocol_v2.md) and writes the block
PROTOCOL: per set and method, the mean RMS-TRE and success@10 mm of the rows with the benchmark's 2 mm
added noise, per protocol bin: the same numbers as each run's summary.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from liver_p2p_reg.bench.bound_report import TRUE_BINS
from liver_p2p_reg.bench.cases_csv import read_rows
from liver_p2p_reg.bench.readme import write_headline
from liver_p2p_reg.bench.stats import SAFETY_TAU_MM, success_rate

METHODS = (("bound", "rigid bound"), ("fpfh-ransac-icp", "`fpfh-ransac-icp`"), ("learned-p2p-icp", "default"))
NOISE_MM = 2.0


def cell(rows: list[dict]) -> str:
    """`mean mm / success@10 %` of some rows (a failure keeps its TRE in the mean and is never a success)."""
    if not rows:
        return "–"
    mean = float(np.mean([r["rms_tre_mm"] for r in rows]))
    return f"{mean:.2f} / {100 * success_rate(rows, SAFETY_TAU_MM):.1f} %"


def set_rows(out: Path, also: tuple[str, ...] = ()) -> list[str]:
    """One table line per method (METHODS, then `also`) for the benchmark run in `out`."""
    dataset = json.loads((out / "settings.json").read_text())["dataset"]
    rows = [r for r in read_rows(out / "cases.csv") if not r.get("variant") and r["added_noise_mm"] == NOISE_MM]
    lines = []
    for method, label in (*METHODS, *((m, f"`{m}`") for m in also)):
        mine = [r for r in rows if r["method"] == method]
        if not mine:
            raise SystemExit(f"{out}: no {method} rows with {NOISE_MM:g} mm added noise")
        cells = [cell([r for r in mine if lo <= r["visibility"] < hi]) for lo, hi in TRUE_BINS]
        lines.append(f"| `{dataset}` | {label} | " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("outs", nargs="+")
    parser.add_argument("--readme")
    parser.add_argument("--also", default="", help="comma-separated methods shown after the default")
    parser.add_argument("--block", default="PROTOCOL", help="the README block to replace")
    args = parser.parse_args()
    also = tuple(m for m in args.also.split(",") if m)
    bins = " | ".join(f"[{lo:.2f},{hi:.2f})" for lo, hi in TRUE_BINS)
    lines = [f"| set | method | {bins} |", "|---|---|" + "---|" * len(TRUE_BINS)]
    for out in map(Path, args.outs):
        lines += set_rows(out, also)
    options = (f" --also {args.also}" if also else "") + (f" --block {args.block}" if args.block != "PROTOCOL" else "")
    caption = (
        f"Mean RMS-TRE (mm) / success@{SAFETY_TAU_MM:g} mm at interior points, {NOISE_MM:g} mm sensor noise, "
        "about 128 poses per cell; rigid bound: ICP started from the true pose "
        f"(`.venv/bin/python scripts/protocol_headline.py {' '.join(args.outs)} --readme {args.readme or 'README.md'}"
        f"{options}`):"
    )
    write_headline(caption, lines, args.readme, args.block)


if __name__ == "__main__":
    main()
