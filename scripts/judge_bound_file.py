"""Judge error-bound calibration files on the poses `liver-p2p calibrate-bound` collected (its --cache).

    .venv/bin/python scripts/judge_bound_file.py --calibration FILE|REV:PATH [--calibration ...] \
        out/bound/real-test-v2-noise2mm-*.npz ... [--deformed] [--readme docs/results/error_bound_interior.md \
        --block INTERIOR-RIGID]

One row per file, as the headline of the results page `calibrate-bound --judge` writes for the file it makes
(coverage per bin, pooled, bad poses with an OK verdict, good poses warned, bound / error, cost), on the same poses:
e.g. a calibration of an earlier version beside today's. The collections must be of the settings and weights the
files were made for (not checked: it judges what it is given). `--readme` writes the rows and this command into the
page's `--block`.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from liver_p2p_reg.bench import bound_data
from liver_p2p_reg.bench.bound_markdown import results_page
from liver_p2p_reg.bench.bound_report import TRUE_BINS, judge
from liver_p2p_reg.bench.readme import write_headline
from liver_p2p_reg.config import Config
from liver_p2p_reg.registration.error_calibration import calibration_from_dict, read_calibration


def _calibration(path: str) -> Any:
    """A calibration file, or `REV:PATH` (a file as a git revision holds it, e.g. an earlier version's bundled one)."""
    if Path(path).exists() or ":" not in path:
        return read_calibration(path)
    text = subprocess.run(["git", "show", path], capture_output=True, text=True)
    if text.returncode != 0:
        raise SystemExit(f"{path}: neither a file nor a git revision's file ({text.stderr.strip()})")
    try:
        raw = json.loads(text.stdout)
    except ValueError as exc:
        raise SystemExit(f"{path}: not JSON ({exc})") from None
    return calibration_from_dict(raw, path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calibration", action="append", required=True, help="a calibration file (JSON); repeatable")
    ap.add_argument("collections", nargs="+", help="collections calibrate-bound cached (.npz)")
    ap.add_argument("--deformed", action="store_true", help="the deformed positions' bound: poses the stage applied")
    ap.add_argument("--readme", help="write the table and the command into this page's --block")
    ap.add_argument("--block", default="INTERIOR-RIGID", help="the page's block (default: INTERIOR-RIGID)")
    args = ap.parse_args()
    parts = []
    for path in args.collections:
        part = bound_data.load_cached(Path(path)) if Path(path).is_file() else None
        if part is None:
            raise SystemExit(f"{path}: not a collection of this version (collect it again with calibrate-bound)")
        parts.append(part)
    data = bound_data.concat(parts)
    if args.deformed:
        data = bound_data.subset(data, data["deform_applied"].astype(bool))
        if not len(data["count"]):
            raise SystemExit("--deformed: the stage was applied on none of these poses (collections of --deformed?)")
    config = Config()
    lo, hi = TRUE_BINS[0][0], TRUE_BINS[-1][1]
    shown = bound_data.subset(data, (data["visibility"] >= lo) & (data["visibility"] < hi))  # the page's poses
    rows = []
    for path in args.calibration:
        calibration = _calibration(path)
        _, block = results_page(
            shown, calibration, config.error_coverage, config.structure_error_warn_mm, 0, "", deformed=args.deformed
        )
        header, rule, row = block.splitlines()[2:5]
        judged = judge(shown, calibration, config.error_coverage, config.structure_error_warn_mm)
        interior = float(np.mean(judged["pose_covered"]))
        rows.append(f"| `{path}` | {calibration.pose_interior} | {interior:.1%} {row}")
    sets = ", ".join(sorted(set(str(s) for s in data["set"])))
    bound_name = (
        "`deformed_error_bound_mm` (of the deformed positions)"
        if args.deformed
        else "`error_bound_mm` (the bound the verdict reads without structures)"
    )
    lines = [
        f"Judged on {sets}, {len(shown['count'])} poses at visibility {lo:g}-{hi:g}; interior coverage: the share of "
        f"poses whose interior RMS error lies below their {bound_name}; the other columns as on the results page.",
        "",
        "| calibration file | interior quantiles made over | interior coverage " + header,
        "|---|---|---" + rule,
        *rows,
    ]
    command = " ".join([".venv/bin/python scripts/judge_bound_file.py", *sys.argv[1:]])
    write_headline(f"Command: `{command}`", lines, args.readme, args.block)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
