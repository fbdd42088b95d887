"""Apply the RANSAC-candidate rule (docs/benchmark_real/RULE_ransac_candidate.md) on the validation sets.

    python scripts/select_ransac_candidate.py [--out-root out/select_ransac] [--speed docs/results/speed.md] \
        [--report docs/benchmark_real/selection_ransac_candidate.md]

Runs `liver-p2p benchmark` (resumable) with `learned-p2p-icp` and `learned-p2p-ransac-icp` on real-val-v2,
real-val-v2-arap and real-val-camera-v2 (visibility [0.05, 0.3), clean + 2 mm noise on every case), reads the
candidate's median time from the `SPEED-RANSAC` block that `scripts/bench_paths.py --block SPEED-RANSAC` wrote,
then writes the rule's table and verdict.

A record from before the RANSAC candidate joined the default: both names now run the same method, so a fresh run
(a new `--out-root`) compares the default with itself; the kept rows (`--no-run`) are the record.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from liver_p2p_reg.bench.candidate_runs import publish_report, run_candidate
from liver_p2p_reg.bench.ransac_candidate_rule import CANDIDATE, REFERENCE, RUN, SETS, median_ms, verdict


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out-root", default="out/select_ransac")
    parser.add_argument("--speed", default="docs/results/speed.md", help="markdown holding the SPEED-RANSAC block")
    parser.add_argument("--data-root", help="named sets' root (default: $LIVER_P2P_DATA or ./data)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--report", help="write the table and verdict here (markdown)")
    parser.add_argument("--no-run", action="store_true", help="only apply the rule to existing runs")
    args = parser.parse_args()
    if not args.no_run:
        # one run folder per set, both methods in it, the bundled weights
        run_candidate(
            RUN,
            "",
            SETS,
            [REFERENCE, CANDIDATE],
            args.out_root,
            workers=args.workers,
            data_root=args.data_root,
            threads=1,
        )
    table, line = verdict(args.out_root, median_ms(Path(args.speed)))
    title = "The RANSAC candidate on the validation sets (rule: RULE_ransac_candidate.md)"
    command = f"python scripts/select_ransac_candidate.py --out-root {args.out_root} --speed {args.speed}"
    publish_report(title, table, line, command, args.report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
