"""Apply the small-view shipping rule (docs/benchmark_real/RULE_small_views.md) to a candidate matcher.

    python scripts/select_small_view_matcher.py --reference v3= --candidate v4=RUN/best.safetensors \
        --out-root out/select_small --report docs/benchmark_real/selection_small_views.md

Runs `liver-p2p benchmark` (resumable) with `learned-p2p-icp` and each weights on real-val-v2,
real-val-camera-v2 and insilico-val-v2 (clean + 2 mm noise on every case), then writes the rule's
table and verdict. An empty path is the bundled weights.
"""

from __future__ import annotations

import argparse

from liver_p2p_reg.bench.candidate_runs import publish_report, run_candidate
from liver_p2p_reg.bench.small_view_rule import METHOD, SETS, verdict


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--reference", required=True, help="NAME=WEIGHTS of the shipped matcher (empty: bundled)")
    parser.add_argument("--candidate", required=True, help="NAME=WEIGHTS")
    parser.add_argument("--out-root", default="out/select_small")
    parser.add_argument("--data-root", help="named sets' root (default: $LIVER_P2P_DATA or ./data)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--report", help="write the table and verdict here (markdown)")
    parser.add_argument("--no-run", action="store_true", help="only apply the rule to existing runs")
    args = parser.parse_args()
    names = []
    for item in (args.reference, args.candidate):
        name, _, weights = item.partition("=")
        names.append(name)
        if not args.no_run:
            run_candidate(
                name, weights, SETS, [METHOD], args.out_root, workers=args.workers, data_root=args.data_root, threads=1
            )
    table, text = verdict(names[0], names[1], args.out_root)
    title = "Small-view matcher selection on the validation sets (rule: RULE_small_views.md)"
    command = f"python scripts/select_small_view_matcher.py --reference {args.reference} --candidate {args.candidate}"
    publish_report(title, table, text, command, args.report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
