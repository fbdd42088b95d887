"""Apply the matcher shipping rule (docs/benchmark_real/RULE.md) to candidate weights on the validation sets.

    python scripts/select_matcher.py --candidate v2= --candidate v3s1=RUN1/best.safetensors \
        --candidate v3s2=RUN2/best.safetensors --out-root out/select --report docs/benchmark_real/selection.md

Runs `liver-p2p benchmark` (resumable) for every candidate on real-val-v1 and real-val-camera-v1
(clean + 2 mm noise on every case), insilico-val-v1 (+ 2 and 4 mm on its lowest bin) and
insilico-val-camera-v1 with `learned-p2p,learned-p2p-icp`, then writes the rule's table and
verdict. An empty path is the bundled weights. The first candidate is the reference (shipped).
"""

from __future__ import annotations

import argparse

from liver_p2p_reg.bench.candidate_runs import publish_report, run_candidate
from liver_p2p_reg.bench.matcher_rule import METHODS, SETS, verdict


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--candidate", action="append", required=True, help="NAME=WEIGHTS (empty: bundled)")
    parser.add_argument("--out-root", default="out/select")
    parser.add_argument("--data-root", help="named sets' root (default: $LIVER_P2P_DATA or ./data)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--report", help="write the table and verdict here (markdown)")
    parser.add_argument("--no-run", action="store_true", help="only apply the rule to existing runs")
    args = parser.parse_args()
    candidates = []
    for item in args.candidate:
        name, _, weights = item.partition("=")
        candidates.append(name)
        if not args.no_run:
            run_candidate(
                name, weights, SETS, list(METHODS), args.out_root, workers=args.workers, data_root=args.data_root
            )
    table, text = verdict(candidates, args.out_root)
    command = "python scripts/select_matcher.py " + " ".join(f"--candidate {c}" for c in args.candidate)
    publish_report("Matcher selection on the validation sets (rule: RULE.md)", table, text, command, args.report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
