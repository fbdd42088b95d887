"""Apply the RANSAC candidate's threshold rule (docs/benchmark_real/RULE_ransac_candidate_threshold.md).

    python scripts/select_ransac_threshold.py [--out-root out/select_ransac] [--check-run] \
        [--speed docs/results/speed.md] [--report docs/benchmark_real/selection_ransac_threshold.md]

Reads the runs `scripts/select_ransac_candidate.py` made (both methods on real-val-v2, real-val-v2-arap and
real-val-camera-v2), composes each threshold's rows by the cases' M/N, checks that the two runs agree where they
must, and writes the table and verdict. `--check-run` also runs `learned-p2p-ransac-icp` at the chosen threshold
on real-val-v2 for real (resumable, into OUT_ROOT/threshold-T/) and requires its RMS-TRE to equal the composed
rows case by case. Rule 3 (time) is read from the SPEED-RANSAC-THRESHOLD block that `scripts/bench_paths.py
--methods fpfh-ransac-icp,learned-p2p-icp,learned-p2p-ransac-icp:ransac_candidate_visibility=T --block
SPEED-RANSAC-THRESHOLD` wrote.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from liver_p2p_reg.bench.candidate_runs import publish_report, run_candidate
from liver_p2p_reg.bench.cases_csv import CASES_CSV, read_rows
from liver_p2p_reg.bench.ransac_candidate_rule import CANDIDATE, SETS
from liver_p2p_reg.bench.ransac_threshold_rule import (
    SPEED_BLOCK,
    composed_rows,
    real_run_mismatches,
    set_rows,
    threshold_verdict,
    time_verdict,
    timed_method,
)

CHECK_SET = "real-val-v2"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out-root", default="out/select_ransac")
    parser.add_argument("--data-root", help="named sets' root (default: $LIVER_P2P_DATA or ./data)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--check-run", action="store_true", help="run the chosen threshold on real-val-v2 and compare")
    parser.add_argument("--speed", default="docs/results/speed.md", help=f"markdown holding the {SPEED_BLOCK} block")
    parser.add_argument("--report", help="write the table and verdict here (markdown)")
    args = parser.parse_args()
    table, line, chosen = threshold_verdict(args.out_root)
    if chosen is not None and args.check_run:
        name = f"threshold-{chosen:.2f}"
        run_candidate(
            name,
            "",
            {CHECK_SET: SETS[CHECK_SET]},
            [CANDIDATE],
            args.out_root,
            workers=args.workers,
            data_root=args.data_root,
            threads=1,
            settings={"ransac_candidate_visibility": chosen},
        )
        run_rows = read_rows(Path(args.out_root) / name / CHECK_SET / CASES_CSV)
        bad = real_run_mismatches(composed_rows(set_rows(args.out_root, CHECK_SET), chosen), run_rows)
        table += [
            "",
            f"Real run of {CANDIDATE} at {chosen:.2f} on {CHECK_SET}: {len(run_rows)} rows, "
            f"{len(bad)} differing from the composed rows" + (": " + "; ".join(bad[:5]) if bad else "."),
        ]
        if bad:
            line, chosen = "The real run differs from the composed rows: no verdict.", None
    if chosen is not None:
        timing, fast = time_verdict(Path(args.speed), chosen)
        table += ["", timing + f" Measured by `scripts/bench_paths.py --methods ...,{timed_method(chosen)}`."]
        if fast:
            line = f"Threshold {chosen:.2f} passes rules 1, 2 and 3: it is chosen."
        else:
            line = f"Threshold {chosen:.2f} passes rules 1 and 2 but not 3: the next threshold is timed."
    title = (
        "The RANSAC candidate's visibility threshold on the validation sets (rule: RULE_ransac_candidate_threshold.md)"
    )
    command = f"python scripts/select_ransac_threshold.py --out-root {args.out_root} --speed {args.speed}" + (
        " --check-run" if args.check_run else ""
    )
    publish_report(title, table, line, command, args.report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
